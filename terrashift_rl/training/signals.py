"""A run's answer to SIGINT (Ctrl-C) and SIGTERM (a scheduler's kill): finish the iteration,
checkpoint, stop; a signal during a step that can be left out (the final evaluation) skips it."""

from __future__ import annotations

import contextlib
import logging
import signal
from collections.abc import Iterator
from typing import Any

__all__ = ["StopRequest"]

log = logging.getLogger(__name__)


class _Skip(BaseException):
    """Raised by the handler inside :meth:`StopRequest.skippable`: leaves that step out."""


class StopRequest:
    """SIGINT (Ctrl-C) and SIGTERM (a scheduler's kill) handler: the first signal lets the
    running iteration finish, so the checkpoint written then is a consistent one; a second
    interrupts at once (``KeyboardInterrupt``), and :attr:`activity` says what it interrupted.
    Inside :meth:`skippable` a signal leaves that step out instead. Restores the previous
    handlers on exit.

    Args:
        announce: whether this process says what a signal does (a data-parallel run's other
            ranks are silent).

    Example:
        >>> with StopRequest(announce=False) as stop:
        ...     with stop.skippable("the final evaluation"):
        ...         stop(signal.SIGINT, None)
        ...         print("not reached")
        ...     stop.requested, stop.activity
        (False, 'the iteration')
    """

    SIGNALS = (signal.SIGINT, signal.SIGTERM)

    def __init__(self, *, announce: bool = True) -> None:
        self.announce = announce
        self.requested = False
        self.activity = "the iteration"
        """What a second signal would interrupt, for the message that says so; the run sets
        it as it moves on."""
        self._skipping: str | None = None

    def __call__(self, signum: int, frame: Any) -> None:
        if self._skipping is not None:
            raise _Skip
        if self.requested:
            raise KeyboardInterrupt
        self.requested = True
        if self.announce:
            log.info(
                f"{signal.Signals(signum).name}: stopping after this iteration, then saving a "
                "checkpoint to resume from (signal again to quit at once, without it)"
            )

    @contextlib.contextmanager
    def skippable(self, step: str) -> Iterator[None]:
        """A step the run can do without (the final evaluation): a signal inside leaves the rest
        of it out, says so, and the run goes on as if it had not been asked to stop."""
        self._skipping = step
        try:
            yield
        except _Skip:
            if self.announce:
                log.info(f"{step} skipped")
        finally:
            self._skipping = None

    def __enter__(self) -> StopRequest:
        self.previous = {number: signal.signal(number, self) for number in self.SIGNALS}
        return self

    def __exit__(self, *exc_info: Any) -> None:
        for number, handler in self.previous.items():
            signal.signal(number, handler)
