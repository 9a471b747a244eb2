"""A run's answer to SIGINT (Ctrl-C) and SIGTERM (a scheduler's kill): finish the iteration,
checkpoint, stop."""

from __future__ import annotations

import signal
from typing import Any

from tqdm import tqdm

__all__ = ["StopRequest"]


class StopRequest:
    """SIGINT (Ctrl-C) and SIGTERM (a scheduler's kill) handler: the first signal lets the
    running iteration finish, so the checkpoint written then is a consistent one; a second
    interrupts at once, without a checkpoint. Restores the previous handlers on exit."""

    SIGNALS = (signal.SIGINT, signal.SIGTERM)

    def __init__(self, progress: tqdm) -> None:
        self.progress = progress
        self.requested = False

    def __call__(self, signum: int, frame: Any) -> None:
        if self.requested:
            raise KeyboardInterrupt
        self.requested = True
        if self.progress.disable:  # a data-parallel run's other ranks are silent
            return
        self.progress.write(
            f"{signal.Signals(signum).name}: stopping after this iteration, then saving a "
            "checkpoint to resume from (signal again to quit at once, without one)"
        )

    def __enter__(self) -> StopRequest:
        self.previous = {number: signal.signal(number, self) for number in self.SIGNALS}
        return self

    def __exit__(self, *exc_info: Any) -> None:
        for number, handler in self.previous.items():
            signal.signal(number, handler)
