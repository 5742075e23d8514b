"""Scripted-expert success per task, noiseless and with the default noise (paper 4.1).

Not a test. Uses the collection's own episode code (`run_episode`) with one tiny
camera, since rendering does not change the physics:

    .venv/bin/python benchmarks/bench_expert.py [--episodes 100]
"""

from __future__ import annotations

import argparse

import numpy as np

from lerobot_murm.collection import EpisodeRecipe, run_episode
from lerobot_murm.env import TASK_NAMES


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--episodes", type=int, default=100)
    args = parser.parse_args()
    print(f"{'task':<22}{'noiseless':>11}{'k=1, std 0.1':>14}   ({args.episodes} seeded episodes each)")
    for task in TASK_NAMES:
        rates = []
        for noisy_fraction in (0.0, 1.0):
            recipe = EpisodeRecipe(task=task, cameras=("top",), image_size=8, noisy_fraction=noisy_fraction)
            rates.append(np.mean([run_episode(recipe, i).succeeded for i in range(args.episodes)]))
        print(f"{task:<22}{rates[0]:>10.0%}{rates[1]:>14.0%}")


if __name__ == "__main__":
    main()
