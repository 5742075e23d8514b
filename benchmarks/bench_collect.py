"""Collection throughput: env steps/s and episodes/min for 1 and 2 workers, five cameras.

Not a test. Run it on an otherwise idle machine and copy the table into BENCHMARKS.md:

    .venv/bin/python benchmarks/bench_collect.py [--episodes 30] [--task place_in_box] [--donors]

Each run collects a fresh dataset of `--episodes` episodes (default 30) into a
temporary folder with `murm collect`'s own code, and reports wall-clock rates, the
projected time for 1000 episodes and the size on disk per 1000 episodes. `--donors`
instead times a 50 %-noisy collection (2 workers) simulated against the same one copied
from finished all-clean and all-noisy collections (collection/donors.py).
"""

from __future__ import annotations

import argparse
import shutil
import subprocess
import tempfile
import time
from pathlib import Path

from lerobot_murm.collection import CollectConfig, collect
from lerobot_murm.collection.prefixes import noise_donors
from lerobot_murm.env import EPISODE_STEPS


def run(task: str, episodes: int, workers: int, root: Path) -> tuple[float, int]:
    start = time.perf_counter()
    collect(CollectConfig(task=task, root=root, episodes=episodes, workers=workers))
    elapsed = time.perf_counter() - start
    size = int(subprocess.run(["du", "-sb", str(root)], capture_output=True, text=True).stdout.split()[0])
    return elapsed, size


def time_donors(task: str, episodes: int, tmp: Path) -> None:
    """A 50 %-noisy collection simulated, then copied from its all-clean and all-noisy donors."""

    def config(name: str, fraction: float) -> CollectConfig:
        return CollectConfig(task=task, root=tmp / "datasets" / name, episodes=episodes, noisy_fraction=fraction)

    for name, fraction in (("clean", 0.0), ("noisy", 1.0)):
        collect(config(name, fraction))
    times = {}
    for way, donors in (("simulated", False), ("copied", True)):
        half = config(f"half-{way}", 0.5)
        start = time.perf_counter()
        collect(half, donors=noise_donors(half) if donors else None)
        times[way] = time.perf_counter() - start
    print(f"\ntask {task}, {episodes} episodes, 50 % noisy, 2 workers")
    for way, elapsed in times.items():
        print(
            f"{way:>10}: {elapsed:6.1f} s, {episodes / elapsed * 60:6.1f} episodes/min, "
            f"1000 episodes {1000 * elapsed / episodes / 60:5.1f} min"
        )
    print(f"copying is {times['simulated'] / times['copied']:.1f}x faster")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--task", default="place_in_box")
    parser.add_argument("--episodes", type=int, default=30)
    parser.add_argument("--donors", action="store_true", help="time copying from noise donors instead")
    args = parser.parse_args()
    if args.donors:
        with tempfile.TemporaryDirectory() as tmp:
            time_donors(args.task, args.episodes, Path(tmp))
        return

    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for workers in (1, 2):
            elapsed, size = run(args.task, args.episodes, workers, Path(tmp) / f"w{workers}")
            rows.append((workers, elapsed, size))
            shutil.rmtree(Path(tmp) / f"w{workers}")
    print(f"\ntask {args.task}, {args.episodes} episodes of {EPISODE_STEPS} steps, five cameras + goal images")
    print(f"{'workers':>8}{'steps/s':>10}{'episodes/min':>14}{'1000 episodes':>15}{'MB per 1000 ep':>16}")
    for workers, elapsed, size in rows:
        steps_per_s = args.episodes * EPISODE_STEPS / elapsed
        projected_min = 1000 * elapsed / args.episodes / 60
        mb_per_1000 = size / args.episodes * 1000 / 1e6
        episodes_per_min = args.episodes / elapsed * 60
        print(
            f"{workers:>8}{steps_per_s:>10.1f}{episodes_per_min:>14.1f}{projected_min:>12.1f} min{mb_per_1000:>16.0f}"
        )
    print(f"scaling 1 -> 2 workers: {rows[0][1] / rows[1][1]:.2f}x")


if __name__ == "__main__":
    main()
