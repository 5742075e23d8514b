"""How much a kill -9 of `murm collect` loses: episodes finished before the kill minus
episodes still there after the repair `--resume` does. Expected: at most `--flush-every`.

Not a test. Run it and copy the table into BENCHMARKS.md:

    .venv/bin/python benchmarks/bench_kill9.py [--episodes 60] [--flush-every 10] [--kills 3]
    .venv/bin/python benchmarks/bench_kill9.py --task place_in_random_box --full-size --episodes 1000 \
        --spread --keep DIR      # a real default-recipe collection, killed three times across its length

One collection (`--task`, place_in_box by default; the tiny two-camera 16x16 recipe of the tests unless
`--full-size`) is killed with SIGKILL at random moments (seeded), each time at least one
flush after the previous kill; after each kill the dataset is repaired as `--resume`
repairs it and read back with stock LeRobot, and the collection is resumed. "Finished" is
the progress bar's count at the kill (episodes handed to LeRobot's writer). `--spread` puts
the kills across the whole collection instead of one flush apart at its start; `--keep DIR`
collects into DIR and keeps the dataset (its expert success is printed).
"""

from __future__ import annotations

import argparse
import json
import random
import re
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from lerobot.datasets.lerobot_dataset import LeRobotDataset

from lerobot_murm.collection.dataset import SUMMARY_FILE, read_summary
from lerobot_murm.collection.durability import restore

MURM = Path(sys.executable).parent / "murm"
PROGRESS = re.compile(r"(\d+)/(\d+) \[")


def finished(log: Path) -> int:
    counts = PROGRESS.findall(log.read_text(errors="replace"))
    return int(counts[-1][0]) if counts else 0


def descendants(pid: int) -> list[int]:
    children = subprocess.run(["pgrep", "-P", str(pid)], capture_output=True, text=True).stdout.split()
    return [int(c) for c in children] + [d for c in children for d in descendants(int(c))]


def gone(pids: list[int]) -> bool:
    for pid in pids:
        try:
            if Path(f"/proc/{pid}/stat").read_text().split(") ")[1][0] != "Z":
                return False
        except FileNotFoundError:
            pass
    return True


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--episodes", type=int, default=60)
    parser.add_argument("--flush-every", type=int, default=10)
    parser.add_argument("--kills", type=int, default=3)
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--full-size", action="store_true", help="five 48x48 cameras instead of two 16x16")
    parser.add_argument("--task", default="place_in_box")
    parser.add_argument("--spread", action="store_true", help="kills spread over the whole collection")
    parser.add_argument("--keep", type=Path, default=None, help="collect into this folder and keep it")
    args = parser.parse_args()
    recipe = [] if args.full_size else ["--cameras", "global,active", "--image-size", "16"]
    rng = random.Random(args.seed)
    print(subprocess.run("lscpu | grep 'Model name'", shell=True, capture_output=True, text=True).stdout.strip())
    print("| kill | finished at the kill | kept after repair | lost | workers gone after |")
    print("|---:|---:|---:|---:|---:|")
    with tempfile.TemporaryDirectory() as tmp:
        root, log = args.keep or Path(tmp) / "ds", Path(tmp) / "stderr.txt"
        command = [
            str(MURM),
            "collect",
            "--task",
            args.task,
            "--root",
            str(root),
            *recipe,
            "--episodes",
            str(args.episodes),
            "--workers",
            str(args.workers),
            "--flush-every",
            str(args.flush_every),
        ]
        worst = 0
        for kill in range(1, args.kills + 1):
            kept_before = read_summary(root)["episodes"] if (root / SUMMARY_FILE).exists() else 0
            target = kept_before + args.flush_every + rng.randint(0, args.flush_every - 1)
            if args.spread:  # near kill / (kills + 1) of the way through
                target = max(target, kill * args.episodes // (args.kills + 1) + rng.randint(0, args.flush_every - 1))
            with log.open("w") as stderr:
                process = subprocess.Popen(
                    command + (["--resume"] if kill > 1 else []), stdout=subprocess.DEVNULL, stderr=stderr
                )
            while finished(log) < target:
                assert process.poll() is None, log.read_text()[-2000:]
                time.sleep(0.05)
            time.sleep(rng.uniform(0, 2.0))  # anywhere inside an episode or a flush
            workers = descendants(process.pid)
            at_kill = finished(log)
            process.send_signal(signal.SIGKILL)
            process.wait()
            killed = time.perf_counter()
            while not gone(workers):
                time.sleep(0.05)
            workers_s = time.perf_counter() - killed
            summary = read_summary(root)
            restore(root, summary["flushed"], SUMMARY_FILE)  # what --resume does first
            dataset = LeRobotDataset(f"local/{root.name}", root=root, video_backend="pyav")
            kept = dataset.meta.total_episodes
            assert kept == summary["episodes"] and len(dataset) == 100 * kept
            dataset[len(dataset) - 1]  # every file readable
            worst = max(worst, at_kill - kept)
            print(f"| {kill} | {at_kill} | {kept} | {at_kill - kept} | {workers_s:.1f} s |", flush=True)
        done = subprocess.run(command + ["--resume"], capture_output=True, text=True)
        assert done.returncode == 0, done.stderr[-2000:]
        summary = json.loads((root / SUMMARY_FILE).read_text())
    print(
        f"\nworst loss {worst} episodes with --flush-every {args.flush_every}; resumed to {summary['episodes']} "
        f"episodes; expert success {summary['success_rate']:.1%}"
    )


if __name__ == "__main__":
    main()
