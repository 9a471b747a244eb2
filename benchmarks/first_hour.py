"""A newcomer's first minutes: the README's commands timed as a terminal shows them.

Runs ``python recipes/mapoca_pretrain.py`` in a pseudo-terminal in a temporary folder (removed
after) and notes when its first line, its run line (the step target) and its first progress
update appear; presses Ctrl-C (SIGINT to the process group, as a terminal does) some seconds
after the first update and notes how long the run takes to exit, and whether it printed the
command that resumes it and left ``checkpoints/last.pt``; then runs ``python recipes/evaluate.py
checkpoint=<run>/checkpoints/last.pt`` the same way. Each time is given as wall clock and as
the processor time (user + sys) the process had used by then: on a shared machine the wall
clock grows with the other work, the processor time less. The load average is noted
before and after each command. ``--cold-kernel-cache`` gives both an empty Warp kernel cache
(``WARP_CACHE_PATH``), as on a machine's first run. Linux only (``/proc``). Prints a table and
writes JSON.

    python benchmarks/first_hour.py
    python benchmarks/first_hour.py --cold-kernel-cache
    python benchmarks/first_hour.py --interrupt-after 5 --out first_hour.json
"""

from __future__ import annotations

import fcntl
import os
import pty
import re
import resource
import select
import shlex
import signal
import struct
import subprocess
import sys
import tempfile
import termios
import time
from pathlib import Path

import torch
from common import benchmark_parser, run_header, table_header, table_row, write_results

ROOT = Path(__file__).resolve().parents[1]
RESULTS = Path(__file__).resolve().parent / "results"

PRETRAIN_MARKS = {
    "first line": r"\S",
    "run line": r"env-steps",
    "first progress update": r"[1-9][\d.]*[kMG]?step \[",  # the bar after its first iteration
}
EVALUATE_MARKS = {
    "first line": r"\S",
    "scores written": r"wrote \S*evaluation\.json",
}


TIMES = ("wall_s", "processor_s")


def processor_seconds(pid: int) -> float:
    """User and system time of process ``pid`` and of its children it has waited for [s]."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return sum(int(field) for field in fields[11:15]) / os.sysconf("SC_CLK_TCK")


def _default_sigint() -> None:
    """In the command's process: Ctrl-C's default action, as a terminal's programs start with,
    also when this timer runs in the background of a shell, which starts it with SIGINT
    ignored (a disposition its children would inherit)."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def timed_in_terminal(
    command: list[str],
    *,
    cwd: Path,
    marks: dict[str, str],
    interrupt: tuple[str, float] | None = None,
    timeout: float = 600.0,
) -> dict:
    """Runs ``command`` in a pseudo-terminal of 120 columns and times it.

    Args:
        command: the program and its arguments.
        cwd: the working folder.
        marks: name -> regular expression: when the output first matches it (the output so
            far, carriage returns and all), its wall clock and processor time are noted.
        interrupt: (mark, seconds): SIGINT to the command's process group that many seconds
            after that mark, as Ctrl-C in a terminal.
        timeout: seconds after which the command is killed.

    Returns:
        ``marks``: name -> ``{"wall_s", "processor_s"}`` for each mark seen; ``wall_s`` and
        ``processor_s`` at the exit (the processor time of every process it waited for);
        ``after_interrupt``, the same from the interrupt to the exit (None without one);
        ``returncode``; ``output``,
        the text it wrote with its line ends as a terminal gets them; ``load_average``,
        the one-minute load average before and after.
    """
    load_before = os.getloadavg()[0]
    main, terminal = pty.openpty()
    fcntl.ioctl(terminal, termios.TIOCSWINSZ, struct.pack("HHHH", 40, 120, 0, 0))
    children = resource.getrusage(resource.RUSAGE_CHILDREN)
    start = time.monotonic()
    process = subprocess.Popen(
        command,
        cwd=cwd,
        stdin=terminal,
        stdout=terminal,
        stderr=terminal,
        start_new_session=True,
        preexec_fn=_default_sigint,
    )
    os.close(terminal)
    output, seen, interrupted = "", {}, None
    mark, delay = interrupt or ("", 0.0)
    while process.poll() is None:
        ready, _, _ = select.select([main], [], [], 0.05)
        now = time.monotonic() - start
        if ready:
            output += _read(main)
            for name, pattern in marks.items():
                if name not in seen and re.search(pattern, output):
                    seen[name] = {"wall_s": now, "processor_s": processor_seconds(process.pid)}
        if interrupted is None and mark in seen and now >= seen[mark]["wall_s"] + delay:
            interrupted = {"wall_s": now, "processor_s": processor_seconds(process.pid)}
            os.killpg(process.pid, signal.SIGINT)
        if now > timeout:
            os.killpg(process.pid, signal.SIGKILL)
    wall = time.monotonic() - start
    while select.select([main], [], [], 0)[0] and (text := _read(main)):  # what it wrote last
        output += text
    os.close(main)
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    processor = after.ru_utime + after.ru_stime - children.ru_utime - children.ru_stime
    return {
        "marks": seen,
        "wall_s": wall,
        "processor_s": processor,
        "after_interrupt": interrupted
        and {
            "wall_s": wall - interrupted["wall_s"],
            "processor_s": processor - interrupted["processor_s"],
        },
        "returncode": process.returncode,
        "output": output,
        "load_average": [load_before, os.getloadavg()[0]],
    }


def _read(terminal: int) -> str:
    """What the command wrote to the terminal since the last read ("" once it closed)."""
    try:
        return os.read(terminal, 65536).decode(errors="replace")
    except OSError:  # the command's side closed: it has exited
        return ""


def newcomers_commands(folder: Path, interrupt_after: float) -> tuple[dict, dict | None, bool]:
    """The main job, interrupted ``interrupt_after`` seconds after its first progress update,
    then the evaluation of its ``last.pt`` (None without one), both run in ``folder``, timed by
    :func:`timed_in_terminal`; and whether the job printed the command that resumes it."""
    recipe = str(ROOT / "recipes/mapoca_pretrain.py")
    pretrain = timed_in_terminal(
        [sys.executable, recipe],
        cwd=folder,
        marks=PRETRAIN_MARKS,
        interrupt=("first progress update", interrupt_after),
    )
    last = next(folder.glob("outputs/*/*/checkpoints/last.pt"), None)
    resume = f"resume with: {shlex.join(['python', recipe])} run.resume="  # the recipe's words
    evaluate = None
    if last is not None:
        evaluate = timed_in_terminal(
            [sys.executable, str(ROOT / "recipes/evaluate.py"), f"checkpoint={last}"],
            cwd=folder,
            marks=EVALUATE_MARKS,
        )
    return pretrain, evaluate, last is not None and resume in pretrain["output"]


def main() -> None:
    parser = benchmark_parser(__doc__)
    parser.add_argument(
        "--interrupt-after",
        type=float,
        default=10.0,
        help="seconds after the first progress update to press Ctrl-C",
    )
    parser.add_argument(
        "--cold-kernel-cache", action="store_true", help="an empty Warp kernel cache, as at first"
    )
    parser.add_argument("--out", type=Path, default=None)
    args = parser.parse_args()
    device = torch.device("cuda" if torch.cuda.is_available() else "cpu")
    cold = "_cold_kernel_cache" if args.cold_kernel_cache else ""
    out = args.out or RESULTS / f"first_hour_{device.type}{cold}.json"
    with tempfile.TemporaryDirectory(prefix="first_hour_") as folder:
        if args.cold_kernel_cache:  # the commands inherit it
            os.environ["WARP_CACHE_PATH"] = str(Path(folder) / "warp_cache")
        pretrain, evaluate, resumable = newcomers_commands(Path(folder), args.interrupt_after)
    rows = [(f"pretrain: {name}", times) for name, times in pretrain["marks"].items()]
    rows.append(("pretrain: from Ctrl-C to the exit", pretrain["after_interrupt"]))
    if evaluate is not None:
        rows += [(f"evaluate: {name}", times) for name, times in evaluate["marks"].items()]
        rows.append(("evaluate: exit", evaluate))
    print(table_header(["moment", "wall clock [s]", "processor time [s]"]))
    for name, times in rows:
        cells = ["-", "-"] if times is None else [f"{times[key]:.1f}" for key in TIMES]
        print(table_row([name, *cells]))
    print(
        f"load average {pretrain['load_average'][0]:.2f} before, "
        f"{(evaluate or pretrain)['load_average'][1]:.2f} after; resume command and last.pt "
        f"{'there' if resumable else 'missing'}"
    )
    for result in (pretrain, evaluate):
        if result is not None:
            del result["output"]  # the bars' redraws: long
    write_results(
        out,
        {
            **run_header(device),
            "cores": os.cpu_count(),
            "cold_kernel_cache": args.cold_kernel_cache,
            "pretrain": pretrain,
            "resume_command_and_last_pt": resumable,
            "evaluate": evaluate,
        },
    )
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
