"""Env steps per second with all five cameras (and goal images) rendered, in one process.

Compares the project's low-poly Panda with the stock pybullet_data Panda meshes in the
same run, so the ratio is not spoiled by machine noise. Not a test: run it by hand,

    .venv/bin/python benchmarks/bench_env.py [--episodes 3] [--repeats 3]

and copy the printed table into BENCHMARKS.md.
"""

from __future__ import annotations

import argparse
import statistics
import time

import numpy as np

from lerobot_murm.env import TASK_NAMES, MurmEnv


def steps_per_second(task: str, lowpoly: bool, episodes: int, seed: int) -> float:
    """Wall-clock env steps/s over `episodes` full episodes of random actions, resets included."""
    env = MurmEnv(task=task, lowpoly_robot=lowpoly)
    rng = np.random.default_rng(seed)
    steps = 0
    start = time.perf_counter()
    for episode in range(episodes):
        env.reset(seed=seed + episode)
        for _ in range(100):
            env.step(rng.uniform(-1, 1, size=4))
            steps += 1
    elapsed = time.perf_counter() - start
    env.close()
    return steps / elapsed


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--episodes", type=int, default=3)
    parser.add_argument("--repeats", type=int, default=3, help="median over this many interleaved runs")
    args = parser.parse_args()

    print(f"{'task':<22}{'low-poly steps/s':>18}{'stock steps/s':>16}{'ratio':>8}")
    for task in TASK_NAMES:
        fast, slow = [], []
        for repeat in range(args.repeats):  # interleave so drift hits both alike
            fast.append(steps_per_second(task, True, args.episodes, seed=repeat))
            slow.append(steps_per_second(task, False, 1, seed=repeat))
        f, s = statistics.median(fast), statistics.median(slow)
        print(f"{task:<22}{f:>18.1f}{s:>16.1f}{f / s:>8.1f}x")


if __name__ == "__main__":
    main()
