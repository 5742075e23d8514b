"""Running the project's and LeRobot's commands from the tests, offline.

Each command runs in a process group of its own, and a command still running at its timeout
is killed with everything it started: `accelerate launch` starts torchrun, which starts the
ranks, and a plain `subprocess.run` timeout kills only the first of them, leaving ranks that
hold ports, memory and cores while the rest of the suite runs.
"""

import os
import signal
import subprocess
from pathlib import Path

import pytest

OFFLINE = {"HF_HUB_OFFLINE": "1", "WANDB_MODE": "disabled"}


def run_to_exit(args: list, cwd: Path, env: dict | None = None, timeout: int = 600) -> tuple[int, str, str]:
    """Run `args` (offline unless `env` is given): its exit code, stdout and stderr; fail the
    test, with the output's tail, after `timeout` seconds."""
    env = {**os.environ, **OFFLINE} if env is None else env
    process = subprocess.Popen([str(a) for a in args], cwd=cwd, env=env, stdout=subprocess.PIPE,
                               stderr=subprocess.PIPE, text=True, start_new_session=True)
    try:
        stdout, stderr = process.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        os.killpg(process.pid, signal.SIGKILL)
        stdout, stderr = process.communicate()
        pytest.fail(f"{args[0]} still ran after {timeout} s; killed with its children:\n"
                    f"{stdout[-3000:]}\n{stderr[-5000:]}")
    return process.returncode, stdout, stderr


def run_command(args: list, cwd: Path, env: dict | None = None, timeout: int = 600) -> str:
    """Run `args` (offline unless `env` is given) and return stdout + stderr; fail the test,
    with the output's tail, on a non-zero exit or after `timeout` seconds."""
    code, stdout, stderr = run_to_exit(args, cwd, env, timeout)
    assert code == 0, f"{args[:3]} failed:\n{stdout[-3000:]}\n{stderr[-5000:]}"
    return stdout + stderr
