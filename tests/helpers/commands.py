"""Running the project's and LeRobot's commands from the tests, offline, without ever hanging.

A command runs with a tag of its own in its environment (`processes.py`): at its timeout, on
any exception (pytest-timeout's included) and after it exits, every process that carries the
tag is killed, whatever session it moved to. Its output goes to files, not pipes, so that a
survivor holding a pipe open cannot keep the test waiting.
"""

from __future__ import annotations

import os
import subprocess
import tempfile
from pathlib import Path

import pytest
from processes import TAG_VARIABLE, kill_tagged, new_tag

OFFLINE = {"HF_HUB_OFFLINE": "1", "WANDB_MODE": "disabled"}


def run(
    args: list, *, timeout: float, cwd: Path | None = None, env: dict | None = None, preexec_fn=None
) -> subprocess.CompletedProcess:
    """`subprocess.run(args, capture_output=True, text=True)` that cannot hang: past `timeout`
    seconds the test fails with the output's tail; no process of the command survives it."""
    tag = new_tag()
    env = {**(os.environ if env is None else env), TAG_VARIABLE: tag}
    with tempfile.TemporaryFile("w+") as stdout, tempfile.TemporaryFile("w+") as stderr:

        def output() -> tuple[str, str]:
            stdout.seek(0), stderr.seek(0)
            return stdout.read(), stderr.read()

        process = subprocess.Popen(
            [str(a) for a in args], cwd=cwd, env=env, stdout=stdout, stderr=stderr, text=True, preexec_fn=preexec_fn
        )
        interruption: BaseException | None = None
        try:
            process.wait(timeout=timeout)
        except BaseException as error:  # its timeout, pytest-timeout's failure, Ctrl-C: the command goes too
            interruption = error
        kill_tagged(tag)  # with whatever it left running (a rank that outlived its launcher)
        process.wait()
        out, err = output()
    name = Path(str(args[0])).name
    if isinstance(interruption, subprocess.TimeoutExpired):
        pytest.fail(
            f"{name} still ran after {timeout} s; killed with everything it started:\n{out[-3000:]}\n{err[-5000:]}"
        )
    if isinstance(interruption, pytest.fail.Exception):
        pytest.fail(f"{interruption}\noutput of {name} so far:\n{out[-3000:]}\n{err[-5000:]}")
    if interruption is not None:
        raise interruption
    return subprocess.CompletedProcess(args, process.returncode, out, err)


def run_command(args: list, cwd: Path, env: dict | None = None, timeout: int = 600) -> str:
    """Run `args` (offline unless `env` is given) and return stdout + stderr; fail the test,
    with the output's tail, on a non-zero exit or after `timeout` seconds."""
    result = run(args, timeout=timeout, cwd=cwd, env={**os.environ, **OFFLINE} if env is None else env)
    assert result.returncode == 0, f"{args[:3]} failed:\n{result.stdout[-3000:]}\n{result.stderr[-5000:]}"
    return result.stdout + result.stderr
