"""One writer per output folder: a second `murm collect` or `murm train` of a folder exits at
once with one line naming the holder, and the first finishes as if alone; the lock dies with
its holder (kill -9 included), never lives on in a forked child, and a reproduce job waits."""

import csv
import os
import signal
import subprocess
import sys
import time
from contextlib import suppress
from pathlib import Path

import psutil
import pytest
from lerobot.datasets.lerobot_dataset import LeRobotDataset

from lerobot_murm import locking
from lerobot_murm.locking import FolderInUse, exclusive, lock_file

sys.path.insert(0, str(Path(__file__).parent / "helpers"))
from commands import OFFLINE, run

MURM = Path(sys.executable).parent / "murm"
QUIET = {**os.environ, **OFFLINE, "TQDM_DISABLE": "1"}  # no progress bars: stderr holds only what went wrong

HOLD = """
import os, signal, sys, time
import multiprocessing
from lerobot_murm.locking import exclusive
with exclusive(sys.argv[1]):
    if sys.argv[2] == "fork":  # a child forked while the lock is held, as evaluation workers are
        child = multiprocessing.get_context("fork").Process(target=time.sleep, args=(600,))
        child.start()
        print(child.pid, flush=True)
    print("locked", flush=True)
    if sys.argv[2] == "release":
        sys.stdin.readline()
    else:
        os.kill(os.getpid(), signal.SIGKILL)
"""


def holder(folder: Path, how: str) -> tuple[subprocess.Popen, list[str]]:
    """A process that takes `folder`'s lock, then dies of kill -9 (`kill`, `fork`) or releases
    it when its stdin is closed (`release`); with what it printed until it held the lock."""
    printed = folder.with_name(f"{how}.out")
    with printed.open("w") as out:
        process = subprocess.Popen(
            [sys.executable, "-c", HOLD, str(folder), how], stdin=subprocess.PIPE, stdout=out, text=True
        )
    deadline = time.monotonic() + 300  # a liveness bound for a crowded machine
    while "locked" not in printed.read_text().split():
        assert process.poll() in (None, -signal.SIGKILL), f"the holder exited with {process.returncode} before locking"
        assert time.monotonic() < deadline, "the holder took no lock"
        time.sleep(0.01)
    return process, printed.read_text().split()


def lock_holder(folder: Path) -> str:
    try:
        return lock_file(folder).read_text().strip()
    except FileNotFoundError:
        return ""


def wait_for_lock(folder: Path, process: subprocess.Popen) -> None:
    """Until `process` holds `folder`'s lock (its PID in the lock file)."""
    deadline = time.monotonic() + 300  # a liveness bound for a crowded machine
    while lock_holder(folder) != str(process.pid):
        assert process.poll() is None, f"it ended (exit {process.returncode}) before it was seen holding the lock"
        assert time.monotonic() < deadline, "no lock taken"
        time.sleep(0.01)


def test_a_second_writer_fails_at_once_naming_the_holder(tmp_path):
    folder = tmp_path / "out"
    with exclusive(folder):
        with exclusive(folder):  # its holder takes it again (a reproduce job calling `collect`)
            pass
        result = run([sys.executable, "-c", HOLD, folder, "release"], timeout=600, cwd=tmp_path, env=QUIET)
        code, stderr = result.returncode, result.stderr
        assert code == 1
        assert stderr.splitlines()[-1] == (
            f"lerobot_murm.locking.FolderInUse: {folder} is in use by another writer "
            f"(PID {os.getpid()}); wait for it to finish or stop it"
        )
    assert not lock_file(folder).exists()  # removed on release


@pytest.mark.parametrize("how", ["kill", "fork"])
def test_the_lock_dies_with_its_holder_even_with_a_forked_child_alive(tmp_path, how):
    folder = tmp_path / "out"
    process, printed = holder(folder, how)
    assert process.wait(timeout=60) == -signal.SIGKILL
    try:
        with exclusive(folder):  # at once: no stale lock, and the orphaned child holds none
            assert lock_file(folder).read_text() == f"{os.getpid()}\n"
    finally:
        if how == "fork":
            child = int(printed[0])
            os.kill(child, signal.SIGKILL)
            deadline = time.monotonic() + 30  # it dies a moment after the signal (under load, after the test)
            while time.monotonic() < deadline and _alive(child):
                time.sleep(0.05)


def _alive(pid: int) -> bool:
    try:
        return psutil.Process(pid).status() != psutil.STATUS_ZOMBIE
    except psutil.NoSuchProcess:
        return False


@pytest.mark.timeout(600)  # were the holder never to release its lock
def test_a_job_waits_for_the_holder(tmp_path, monkeypatch):
    """What a `murm reproduce` job does where another job builds the artefact it needs."""
    folder = tmp_path / "dataset"
    process, _ = holder(folder, "release")
    with pytest.raises(FolderInUse), exclusive(folder):
        pass
    notes = []

    def note(text: str, **_: object) -> None:
        notes.append(text)
        process.stdin.close()  # the holder finishes while this one waits

    monkeypatch.setattr(locking, "print", note, raising=False)
    with exclusive(folder, wait=True):
        assert process.wait(timeout=60) == 0
    assert notes == [f"waiting for PID {process.pid} to finish writing {folder}"]


def test_a_second_collection_of_one_folder_exits_at_once_and_the_first_finishes(tmp_path):
    """Two collections of one folder made a corrupt parquet file that stock LeRobot could not read."""
    root = tmp_path / "ds"
    collect = [
        MURM,
        "collect",
        "--task",
        "pick_up",
        "--episodes",
        "5",
        "--workers",
        "1",
        "--cameras",
        "global",
        "--image-size",
        "16",
        "--root",
        root,
    ]
    first = subprocess.Popen(
        [str(a) for a in collect], env=QUIET, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True
    )
    try:
        wait_for_lock(root, first)
        first.send_signal(signal.SIGSTOP)  # it holds the lock, mid-collection, while the second runs
        result = run([*collect, "--resume"], timeout=300, cwd=tmp_path, env=QUIET)
        code, stderr = result.returncode, result.stderr
        first.send_signal(signal.SIGCONT)
        assert code == 1 and stderr.splitlines() == [
            f"murm collect: {root} is in use by another writer (PID {first.pid}); wait for it to finish or stop it "
            "(--debug shows where)"
        ]
        assert first.wait(timeout=300) == 0, first.stderr.read()[-2000:]
    finally:
        first.kill()
        first.communicate()
    dataset = LeRobotDataset("local/murm_pick_up", root=root, video_backend="pyav")
    assert dataset.meta.total_episodes == 5 and dataset[len(dataset) - 1]["episode_index"] == 4


@pytest.mark.slow
def test_a_second_training_of_one_run_folder_exits_at_once_and_the_first_logs_each_step_once(tiny_train_yaml, tmp_path):
    """Two trainers of one folder wrote every log row twice and two final evaluations."""
    path = tiny_train_yaml()
    train = [MURM, "train", "--config", path]
    first = subprocess.Popen(
        [str(a) for a in train],
        env=QUIET,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,
    )
    try:
        wait_for_lock(tmp_path / "run", first)
        os.killpg(first.pid, signal.SIGSTOP)  # with its simulator workers
        result = run(train, timeout=300, cwd=tmp_path, env=QUIET)
        code, stderr = result.returncode, result.stderr
        os.killpg(first.pid, signal.SIGCONT)
        assert code == 1 and stderr.splitlines() == [
            f"murm train: {tmp_path / 'run'} is in use by another writer (PID {first.pid}); wait for it to finish or "
            "stop it (--debug shows where)"
        ]
        assert first.wait(timeout=600) == 0, first.stderr.read()[-3000:]
    finally:
        with suppress(ProcessLookupError):  # what is left of it after a failure
            os.killpg(first.pid, signal.SIGKILL)
        first.communicate()
    with (tmp_path / "run" / "log.csv").open() as f:
        assert [int(row["step"]) for row in csv.DictReader(f)] == [1, 2, 3, 4]
    with (tmp_path / "run" / "eval.csv").open() as f:
        assert [row["split"] for row in csv.DictReader(f)] == ["validation", "test"]
