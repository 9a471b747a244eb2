"""The newcomer benchmark's timer: marks, the Ctrl-C to the process group, processor time."""

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))

from first_hour import timed_in_terminal  # noqa: E402

PROGRAM = """
import signal, sys, time
print("ready", flush=True)
busy = time.process_time() + 0.3
while time.process_time() < busy:  # processor time before the mark
    pass
print("step [1]", flush=True)
try:
    time.sleep(60)
except KeyboardInterrupt:
    print("stopped", flush=True)
    sys.exit(3)
"""


def test_marks_a_ctrl_c_after_one_and_the_exit_with_their_processor_time(tmp_path):
    result = timed_in_terminal(
        [sys.executable, "-c", PROGRAM],
        cwd=tmp_path,
        marks={"first line": r"\S", "step": r"step \[", "never": "not printed"},
        interrupt=("step", 0.2),
        timeout=30,
    )
    assert result["returncode"] == 3  # the program's answer to SIGINT, not a kill
    assert "stopped" in result["output"]
    assert set(result["marks"]) == {"first line", "step"}
    first, step = result["marks"]["first line"], result["marks"]["step"]
    assert first["wall_s"] <= step["wall_s"] < 20
    assert step["processor_s"] - first["processor_s"] >= 0.2  # the busy loop between them
    assert result["after_interrupt"]["wall_s"] < 10  # not the minute's sleep
    assert result["wall_s"] >= step["wall_s"] + 0.2
    assert result["processor_s"] >= step["processor_s"]
