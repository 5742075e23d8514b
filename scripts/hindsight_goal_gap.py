"""How far each demonstration's hindsight goal (its last frame) lies from its rendered goal image,
in the latent space MURM's reward measures (squared L2 between 720-number latents), split by
whether the demonstration succeeded; the episodes' first frames give the scale. It is what the
hindsight grid (issue 44, REPORT.md) trains on, measured before any of its runs:

    python scripts/hindsight_goal_gap.py --dataset outputs/murm/datasets/place_in_box-... \\
        --encoders outputs/murm/vqvae/place_in_box-.../global outputs/murm/vqvae/place_in_box-.../adjacent

Reads the latent caches `murm encode` builds (from --cache-dir; built there if missing).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from lerobot_murm.collection.dataset import episode_successes
from lerobot_murm.vqvae.frames import episode_last_rows
from lerobot_murm.vqvae.latent_cache import build_latent_cache


def squared_distance(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return ((a - b) ** 2).sum(-1)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--dataset", type=Path, required=True, help="a dataset folder with goal images")
    parser.add_argument("--encoders", type=Path, nargs="+", required=True, help="VQ-VAE folders, one per camera")
    parser.add_argument("--cache-dir", type=Path, default=Path("outputs/latent_cache"))
    args = parser.parse_args()
    repo_id = f"local/{args.dataset.name}"
    succeeded = episode_successes(repo_id, args.dataset)
    print(
        "| camera | episodes | last frame to goal: successful (median, 90 %) | failed (median, 90 %) "
        "| first frame to goal (median) |"
    )
    print("|---|---:|---:|---:|---:|")
    for encoder in args.encoders:
        cache = build_latent_cache(repo_id, args.dataset, encoder, args.cache_dir)
        if cache.hindsight:
            raise SystemExit(f"{args.dataset} has no goal images to measure hindsight goals against")
        episodes = cache.episode_index
        last = episode_last_rows(episodes)
        first = np.flatnonzero(np.insert(episodes[1:] != episodes[:-1], 0, True))
        goals = cache.goal_latents()
        to_goal = squared_distance(cache.latents(last), goals)
        start = squared_distance(cache.latents(first), goals)
        parts = [
            f"{np.median(to_goal[m]):.2f}, {np.quantile(to_goal[m], 0.9):.2f} ({m.sum()})" if m.any() else "-"
            for m in (succeeded, ~succeeded)
        ]
        print(f"| {cache.camera} | {len(last)} | {parts[0]} | {parts[1]} | {np.median(start):.2f} |")


if __name__ == "__main__":
    main()
