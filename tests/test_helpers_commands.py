"""A test can fail, never hang: commands and whole test runs leave no process behind."""

import sys
import textwrap
import time
from pathlib import Path

import pytest

HELPERS = Path(__file__).parent / "helpers"
sys.path.insert(0, str(HELPERS))
from commands import run, run_command  # noqa: E402

# A grandchild in a session of its own (as torchrun starts its ranks), holding the command's
# stdout: neither a process-group kill nor a pipe read would get past it.
# The launcher records the grandchild's pid itself (atomically, before it says "started"): a
# grandchild killed before its first line of Python still has a pid to check.
ESCAPING_GRANDCHILD = """
import os, subprocess, sys, time
child = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(300)"], start_new_session=True)
open('child.pid.tmp', 'w').write(str(child.pid))
os.replace('child.pid.tmp', 'child.pid')
print("started", flush=True)
time.sleep({parent_sleep})
"""


def is_running(pid: int) -> bool:
    try:
        state = Path(f"/proc/{pid}/status").read_text()
    except FileNotFoundError:
        return False
    return "State:\tZ" not in state  # a zombie has exited


def wait_for_pid_file(path: Path) -> int:
    deadline = time.monotonic() + 30
    while not path.exists() or not path.read_text():
        assert time.monotonic() < deadline, f"{path} never appeared"
        time.sleep(0.05)
    return int(path.read_text())


def test_a_command_past_its_timeout_fails_with_its_output_and_nothing_it_started_survives(tmp_path):
    with pytest.raises(pytest.fail.Exception, match=r"(?s)killed with everything it started.*started"):
        run_command([sys.executable, "-c", ESCAPING_GRANDCHILD.format(parent_sleep=300)], tmp_path, timeout=5)
    assert not is_running(wait_for_pid_file(tmp_path / "child.pid"))


def test_a_command_that_exits_leaves_no_process_behind(tmp_path):
    """A rank that outlives its launcher is ended when the launcher returns."""
    result = run([sys.executable, "-c", ESCAPING_GRANDCHILD.format(parent_sleep=0)], timeout=60, cwd=tmp_path)
    assert result.returncode == 0 and result.stdout == "started\n"
    assert not is_running(wait_for_pid_file(tmp_path / "child.pid"))


def test_a_failing_command_fails_the_test_with_its_output(tmp_path):
    with pytest.raises(AssertionError, match="no such thing"):
        run_command([sys.executable, "-c", "import sys; sys.exit('no such thing')"], tmp_path)


INNER_CONFTEST = f"""
import sys
sys.path.insert(0, {str(HELPERS)!r})
from process_guard import no_process_outlives_its_test
"""

INNER_TESTS = f"""
import subprocess, sys, time
from pathlib import Path
import pytest
from commands import run_command

GRANDCHILD = {ESCAPING_GRANDCHILD.format(parent_sleep=300)!r}


@pytest.mark.timeout(4)
def test_hangs_in_a_command(tmp_path_factory):
    run_command([sys.executable, "-c", GRANDCHILD], Path({{where!r}}) / "command", timeout=600)


@pytest.mark.timeout(4)
def test_hangs_with_a_tree_it_started_itself():
    subprocess.Popen([sys.executable, "-c", GRANDCHILD], cwd=Path({{where!r}}) / "popen")
    time.sleep(600)
"""


def test_a_test_past_the_suite_timeout_fails_with_output_and_leaves_no_process(tmp_path):
    """The suite's per-test timeout (pytest-timeout) fails a hanging test; the process tree it
    started, through the command runner or by hand, is gone afterwards."""
    inner = tmp_path / "inner"
    inner.mkdir()
    for sub in ("command", "popen"):
        (tmp_path / sub).mkdir()
    (inner / "conftest.py").write_text(INNER_CONFTEST)
    (inner / "test_hanging.py").write_text(textwrap.dedent(INNER_TESTS.format(where=str(tmp_path))))
    result = run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", str(inner)], timeout=120, cwd=inner)
    assert result.returncode == 1, result.stdout + result.stderr
    assert "2 failed" in result.stdout and "Timeout" in result.stdout, result.stdout
    assert "output of python" in result.stdout and "started" in result.stdout, result.stdout
    for sub in ("command", "popen"):
        assert not is_running(wait_for_pid_file(tmp_path / sub / "child.pid")), sub
