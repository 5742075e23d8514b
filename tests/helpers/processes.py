"""Ending a command with everything it started, wherever its descendants went.

`accelerate launch` starts torchrun, whose ranks run in sessions of their own; `ray start`
daemonises; `murm reproduce --jobs` starts workers that start simulators. Killing a process
group or a snapshot of the process tree misses whoever moved session or was reparented to init.
Every process a test starts carries a tag in its environment instead (children inherit it), and
`kill_tagged` ends every process that carries it, however it got there.
"""

from __future__ import annotations

import os
import time
import uuid

import psutil

TAG_VARIABLE = "MURM_TEST_PROCESS_TAG"


def new_tag() -> str:
    return uuid.uuid4().hex


# multiprocessing's helpers of this very process (the forkserver, the resource tracker) start
# lazily inside whichever test first needs them and serve every later test: they are not that
# test's to kill (a reaped forkserver fails the next test's pool with "No child processes").
SHARED_HELPERS = ("multiprocessing.forkserver", "multiprocessing.resource_tracker")


def tagged_processes(tag: str) -> list[psutil.Process]:
    """The live processes (not this one, nor its multiprocessing helpers) whose environment
    carries `tag`."""
    found = []
    for process in psutil.process_iter():
        if process.pid == os.getpid():
            continue
        try:
            if process.environ().get(TAG_VARIABLE) != tag or process.status() == psutil.STATUS_ZOMBIE:
                continue
            if process.ppid() == os.getpid() and any(h in " ".join(process.cmdline()) for h in SHARED_HELPERS):
                continue
            found.append(process)
        except (psutil.NoSuchProcess, psutil.AccessDenied, psutil.ZombieProcess):
            continue
    return found


def kill_tagged(tag: str, within_s: float = 10.0) -> list[int]:
    """SIGKILL every process tagged `tag`, again until none is left (one may fork while we look);
    return their pids. Waits for them to die, reaping the ones that are this process's children."""
    killed: list[int] = []
    deadline = time.monotonic() + within_s
    while (survivors := tagged_processes(tag)) and time.monotonic() < deadline:
        for process in survivors:
            try:
                process.kill()
                killed.append(process.pid)
            except psutil.NoSuchProcess:
                pass
        psutil.wait_procs(survivors, timeout=1.0)
    return sorted(set(killed))
