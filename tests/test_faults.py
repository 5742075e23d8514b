"""Fault injection: kill -9 and a full disk during `murm collect`, a torn checkpoint swap."""

import hashlib
import json
import os
import random
import resource
import signal
import subprocess
import sys
import time
from pathlib import Path

import pyarrow.parquet as pq
import pytest
import torch

from lerobot_murm.checkpointing import CheckpointError, load_state, recover, save_state, staging_folder, swap_in
from lerobot_murm.collection import CollectConfig, collect

MURM = Path(sys.executable).parent / "murm"
RECIPE = ["--task", "place_in_box", "--cameras", "global,active", "--image-size", "16"]
SUMMARY = "meta/murm_collection.json"


def contents(root: Path) -> dict[str, object]:
    """Every file of a dataset by content: parquet as its table (less the random fingerprint
    `datasets` stamps on each write), anything else as bytes."""
    return {
        p.relative_to(root).as_posix(): pq.read_table(p).replace_schema_metadata(None)
        if p.suffix == ".parquet" else hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(root.rglob("*"))
        if p.is_file()
    }


def saved_episodes(root: Path) -> int:
    path = root / SUMMARY
    return json.loads(path.read_text())["episodes"] if path.exists() else 0


def alive(pid: int) -> bool:
    try:
        return Path(f"/proc/{pid}/stat").read_text().split(") ")[1][0] != "Z"
    except FileNotFoundError:
        return False


def descendants(pid: int) -> list[int]:
    children = subprocess.run(["pgrep", "-P", str(pid)], capture_output=True, text=True).stdout.split()
    return [int(c) for c in children] + [d for c in children for d in descendants(int(c))]


def collect_until_killed(root: Path, episodes: int, flush_every: int, rng: random.Random, resume: bool) -> None:
    """Start `murm collect`, kill -9 it at a random moment after its next flush."""
    args = [str(MURM), "collect", *RECIPE, "--root", str(root), "--episodes", str(episodes), "--workers", "2"]
    args += ["--flush-every", str(flush_every)] + (["--resume"] if resume else [])
    before = saved_episodes(root)
    process = subprocess.Popen(args, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    deadline = time.monotonic() + 240
    while saved_episodes(root) <= before:
        assert process.poll() is None, "the collection ended before it could be killed"
        assert time.monotonic() < deadline, "no flush"
        time.sleep(0.05)
    time.sleep(rng.uniform(0.0, 1.5))  # anywhere: mid-episode, mid-write, mid-flush
    workers = descendants(process.pid)
    assert workers, "no worker processes"
    process.kill()
    process.wait()
    deadline = time.monotonic() + 20
    while any(alive(pid) for pid in workers):
        assert time.monotonic() < deadline, f"processes left behind: {[p for p in workers if alive(p)]}"
        time.sleep(0.1)


def test_kill_9_at_random_points_then_resume_gives_the_unbroken_dataset(tmp_path):
    episodes, flush_every = 6, 2
    reference = tmp_path / "unbroken"
    collect(CollectConfig(task="place_in_box", root=reference, episodes=episodes, workers=1,
                          cameras=("global", "active"), image_size=16, flush_every=flush_every))

    root, rng = tmp_path / "killed", random.Random(16)
    collect_until_killed(root, episodes, flush_every, rng, resume=False)
    collect_until_killed(root, episodes, flush_every, rng, resume=True)
    assert saved_episodes(root) < episodes, "killed too late to test anything"
    finished = subprocess.run(
        [str(MURM), "collect", *RECIPE, "--root", str(root), "--episodes", str(episodes), "--workers", "2",
         "--flush-every", str(flush_every), "--resume"], capture_output=True, text=True, timeout=300,
    )
    assert finished.returncode == 0, finished.stderr[-2000:]
    assert contents(root) == contents(reference)  # the same files, metadata included
