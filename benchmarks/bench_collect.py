"""Collection throughput: env steps/s and episodes/min for 1 and 2 workers, five cameras.

Not a test. Run it on an otherwise idle machine and copy the table into BENCHMARKS.md:

    .venv/bin/python benchmarks/bench_collect.py [--episodes 30] [--task place_in_box]

Each run collects a fresh dataset of `--episodes` episodes (default 30) into a
temporary folder with `murm collect`'s own code, and reports wall-clock rates, the
projected time for 1000 episodes and the size on disk per 1000 episodes.
"""

from __future__ import annotations

import argparse
import shutil
import subprocess
import tempfile
import time
from pathlib import Path

from lerobot_murm.collection import CollectConfig, collect
from lerobot_murm.env import EPISODE_STEPS


def run(task: str, episodes: int, workers: int, root: Path) -> tuple[float, int]:
    start = time.perf_counter()
    collect(CollectConfig(task=task, root=root, episodes=episodes, workers=workers))
    elapsed = time.perf_counter() - start
    size = int(subprocess.run(["du", "-sb", str(root)], capture_output=True, text=True).stdout.split()[0])
    return elapsed, size


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--task", default="place_in_box")
    parser.add_argument("--episodes", type=int, default=30)
    args = parser.parse_args()

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
        print(f"{workers:>8}{steps_per_s:>10.1f}{args.episodes / elapsed * 60:>14.1f}{projected_min:>12.1f} min{mb_per_1000:>16.0f}")
    print(f"scaling 1 -> 2 workers: {rows[0][1] / rows[1][1]:.2f}x")


if __name__ == "__main__":
    main()
