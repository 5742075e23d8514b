"""The tests' command runner leaves nothing running behind a command that hangs."""

import sys
import time
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).parent / "helpers"))
from commands import run_command  # noqa: E402

GRANDPARENT = """
import subprocess, sys, time
subprocess.Popen([sys.executable, "-c", "import os, time; open('child.pid', 'w').write(str(os.getpid())); time.sleep(120)"],
                 stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)  # holds none of the runner's pipes
time.sleep(120)
"""


def is_running(pid: int) -> bool:
    try:
        state = Path(f"/proc/{pid}/status").read_text()
    except FileNotFoundError:
        return False
    return "State:\tZ" not in state  # a zombie has exited


def test_a_command_past_its_timeout_is_killed_with_the_processes_it_started(tmp_path):
    with pytest.raises(pytest.fail.Exception, match="killed with its children"):
        run_command([sys.executable, "-c", GRANDPARENT], tmp_path, timeout=5)
    child = int((tmp_path / "child.pid").read_text())
    deadline = time.monotonic() + 10
    while is_running(child) and time.monotonic() < deadline:
        time.sleep(0.1)
    assert not is_running(child)


def test_a_failing_command_fails_the_test_with_its_output(tmp_path):
    with pytest.raises(AssertionError, match="no such thing"):
        run_command([sys.executable, "-c", "import sys; sys.exit('no such thing')"], tmp_path)
