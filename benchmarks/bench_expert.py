"""Scripted-expert success per task: the default recipe, the paper's noise and a noise sweep.

Not a test. Uses the collection's own episode code (`run_episode`) with one tiny camera,
since rendering does not change the physics. Failed episodes are sorted by what went
wrong, from the privileged object height: the object never lifted (missed grasps,
including grasps broken by noise before the lift), or lifted and then not on the goal
(dropped in transit, placed beside the box, or run out of time while carrying).

    .venv/bin/python benchmarks/bench_expert.py [--episodes 200] [--calibrate 0.5,0.55,0.6]
"""

from __future__ import annotations

import argparse
from multiprocessing import Pool

import numpy as np

from lerobot_murm.collection import EpisodeRecipe, run_episode
from lerobot_murm.env import TASK_NAMES
from lerobot_murm.expert import PAPER_NOISE_STD, default_noise_std

LIFTED_M = 0.02  # the object counts as lifted once 2 cm above where it started
BASE_SEED = 7  # not the collections' seed 0: the benchmark's episodes are not the datasets'


def outcome(job: tuple[str, float, float, int]) -> str:
    task, std, noisy_fraction, index = job
    recipe = EpisodeRecipe(
        task=task, cameras=("global",), image_size=8, base_seed=BASE_SEED, noise_std=std, noisy_fraction=noisy_fraction
    )
    episode = run_episode(recipe, index)
    if episode.succeeded:
        return "success"
    height = episode.environment_state[:, 2]
    return "lifted, not placed" if (height - height[0]).max() > LIFTED_M else "never lifted"


def rates(task: str, std: float, noisy_fraction: float, episodes: int, pool: Pool) -> dict[str, float]:
    outcomes = pool.map(outcome, [(task, std, noisy_fraction, i) for i in range(episodes)], chunksize=8)
    kinds = ("success", "never lifted", "lifted, not placed")
    return {kind: float(np.mean([o == kind for o in outcomes])) for kind in kinds}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--episodes", type=int, default=200)
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--calibrate", default="", help="comma-separated noise stds to sweep instead")
    args = parser.parse_args()
    with Pool(args.workers) as pool:
        if args.calibrate:
            stds = [float(s) for s in args.calibrate.split(",")]
            print(f"| task | {' | '.join(f'std {s:g}' for s in stds)} |\n|---|" + "---:|" * len(stds))
            for task in TASK_NAMES:
                cells = [f"{rates(task, s, 1.0, args.episodes, pool)['success']:.0%}" for s in stds]
                print(f"| {task} | {' | '.join(cells)} |", flush=True)
            return
        print(f"{args.episodes} seeded episodes per cell (base seed {BASE_SEED})\n")
        print(
            "| task | noiseless | paper's std 0.1 | default std | default: success | never lifted "
            "| lifted, not placed |"
        )
        print("|---|---:|---:|---:|---:|---:|---:|")
        for task in TASK_NAMES:
            clean = rates(task, 0.0, 0.0, args.episodes, pool)["success"]
            paper = rates(task, PAPER_NOISE_STD, 1.0, args.episodes, pool)["success"]
            default = rates(task, default_noise_std(task), 1.0, args.episodes, pool)
            print(
                f"| {task} | {clean:.0%} | {paper:.0%} | {default_noise_std(task):g} | {default['success']:.0%} | "
                f"{default['never lifted']:.0%} | {default['lifted, not placed']:.0%} |",
                flush=True,
            )


if __name__ == "__main__":
    main()
