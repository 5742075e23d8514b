"""Where to put the reward threshold epsilon (paper eq. 4-5, Table 2), per camera.

The reward says a camera's view reached its goal when the squared latent distance
||z - z_g||^2 is below epsilon. Good thresholds separate the final frames of
successful episodes (goal reached) from random frames (mostly not reached): we
report both distributions and suggest the threshold that maximises Youden's J =
P(final-success frame below) - P(random frame below).

With hindsight goals (a dataset without goal images: each episode's goal is its last
frame) the final frames sit at distance 0 from their goals by construction, so the frames
just before them, the last `HINDSIGHT_REACHED_SHARE` of each episode, stand for "goal
reached" instead.

The paper's epsilons (Table 2: 0.1, 1, 2, 3, 5) are squared distances in its own
encoders' latent scale, which it does not publish, so they cannot be used on ours as
they stand. `paper_epsilon_on_our_scale` maps them (see its docstring), and
`epsilon_at_quantile` places a threshold by the distribution of frame-to-goal
distances instead.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
from matplotlib.figure import Figure

from lerobot_murm.checkpointing import write_atomic
from lerobot_murm.vqvae.configuration_vqvae import LATENT_DISTANCE_FILE
from lerobot_murm.vqvae.frames import episode_last_rows
from lerobot_murm.vqvae.latent_cache import HINDSIGHT, LatentCache

PERCENTILES = (5, 25, 50, 75, 95)
QUANTILE_KEY = "random_frames_quantiles"  # percentiles 0, 1, ..., 100 of the random frames' distances
PAPER_CHOSEN_EPSILON = 2.0  # paper 5.1: the best success in Table 2; the authors' code's default too
HINDSIGHT_REACHED_SHARE = 0.05  # hindsight goals: each episode's last 5 % of frames (at least one) reached its goal


def goal_distances(cache: LatentCache, rows: np.ndarray) -> np.ndarray:
    """Squared latent distance between frames `rows` and their episode's goal image."""
    if not len(rows):  # e.g. no successful episode in the dataset
        return np.zeros(0, np.float32)
    diff = cache.latents(rows) - cache.goal_latents(cache.episode_index[rows])
    return np.square(diff).sum(axis=1)


def reached_rows(cache: LatentCache, episode_success: np.ndarray) -> np.ndarray:
    """The frames that reached their goal: the last frames of successful episodes, or with
    hindsight goals (every episode succeeds at its own last frame) the frames just before it."""
    last_rows = episode_last_rows(cache.episode_index)
    if not cache.hindsight:
        return last_rows[episode_success[cache.episode_index[last_rows]]]
    first_rows = np.append(0, last_rows[:-1] + 1)
    lengths = last_rows - first_rows + 1
    before = np.maximum(1, np.round(HINDSIGHT_REACHED_SHARE * lengths).astype(int))
    return np.concatenate([np.arange(last - n, last) for last, n in zip(last_rows, before, strict=True)])


def distance_statistics(cache: LatentCache, episode_success: np.ndarray, samples: int = 5000, seed: int = 0) -> dict:
    rows = len(cache.indices)
    random_rows = np.random.default_rng(seed).choice(rows, size=min(samples, rows), replace=False)
    reached = goal_distances(cache, reached_rows(cache, episode_success))
    random = goal_distances(cache, random_rows)
    candidates = np.unique(np.concatenate([reached, random]))
    below_reached = np.searchsorted(np.sort(reached), candidates, side="right") / max(len(reached), 1)
    below_random = np.searchsorted(np.sort(random), candidates, side="right") / len(random)
    best = int(np.argmax(below_reached - below_random))
    suggested = float(candidates[best])  # the reward counts d < epsilon; J counted d <= this
    if cache.hindsight:  # many frames encode exactly as their goal (d = 0): halfway to the next distance
        suggested = float(candidates[best : best + 2].mean())
    return {
        "camera": cache.camera,
        "distance": "squared L2 between 720-number latents",
        "goals": cache.goals,
        "successful_final_frames": _summary(reached),
        "random_frames": _summary(random),
        QUANTILE_KEY: np.percentile(random, np.arange(101)).tolist(),
        "suggested_epsilon": suggested,
        "youden_j": float(below_reached[best] - below_random[best]),
        "_reached": reached,
        "_random": random,
    }


def paper_epsilon_on_our_scale(paper_epsilon: float, stats: dict) -> float:
    """A paper-scale epsilon (Table 2) on our encoder's scale: its ratio to the paper's chosen
    2.0, times the epsilon `murm encode` suggests for this camera.

    Why this mapping: the paper publishes no distances of its encoders, so no quantile of its
    values can be known; the one point the two scales share is the threshold each side chose
    for its encoders (the paper: 2.0, best success in its sweep; ours: the Youden-J
    suggestion). A squared distance scales linearly when the latents are rescaled
    (z -> a z gives d -> a^2 d), so the ratio to the chosen value is what carries over: the
    paper's sweep 0.1, 1, 2, 3, 5 becomes 0.05, 0.5, 1, 1.5 and 2.5 times our suggestion.
    """
    if paper_epsilon <= 0:
        raise ValueError(f"a paper-scale epsilon must be positive, got {paper_epsilon}")
    if stats["suggested_epsilon"] <= 0:
        raise ValueError(
            f"the {stats['camera']} encoder's suggested epsilon is 0 (its frames encode alike): "
            "there is no scale to map the paper's epsilon to"
        )
    return paper_epsilon / PAPER_CHOSEN_EPSILON * float(stats["suggested_epsilon"])


def epsilon_on_paper_scale(epsilon: float, stats: dict) -> float | None:
    """The inverse of `paper_epsilon_on_our_scale`: where our epsilon sits on the paper's scale
    (None when the suggestion is 0 and there is no scale)."""
    suggested = float(stats["suggested_epsilon"])
    return epsilon / suggested * PAPER_CHOSEN_EPSILON if suggested > 0 else None


def epsilon_at_quantile(quantile: float, stats: dict) -> float:
    """The epsilon below which a share `quantile` (0-1) of random frames lies from their goal."""
    if not 0.0 < quantile < 1.0:
        raise ValueError(f"an epsilon quantile must be in (0, 1), got {quantile}")
    return float(np.interp(100 * quantile, np.arange(101), _quantiles(stats)))


def quantile_of_epsilon(epsilon: float, stats: dict) -> float:
    """The share (0-1) of random frames closer to their goal than `epsilon`: where a threshold
    sits in the distance distribution, comparable across encoders."""
    quantiles = _quantiles(stats)
    return float(np.interp(epsilon, quantiles, np.arange(101)) / 100)


def _quantiles(stats: dict) -> list[float]:
    if QUANTILE_KEY not in stats:
        raise ValueError(
            f"these distance statistics ({stats.get('camera')}) predate {QUANTILE_KEY}; run `murm encode` again"
        )
    return stats[QUANTILE_KEY]


def read_statistics(encoder_dir: Path) -> dict:
    """The statistics `save_beside_encoder` wrote, or a one-line error saying how to make them."""
    path = Path(encoder_dir) / LATENT_DISTANCE_FILE
    if not path.exists():
        raise FileNotFoundError(f"no {path}: run `murm encode` with this encoder first")
    return json.loads(path.read_text())


def public_statistics(stats: dict) -> dict:
    """The JSON-able part of `distance_statistics` (without the raw distances)."""
    return {k: v for k, v in stats.items() if not k.startswith("_")}


def save_beside_encoder(stats: dict, encoder_dir: Path) -> None:
    """Write the statistics where the MURM policy config looks for its default epsilon."""
    text = json.dumps(public_statistics(stats), indent=2) + "\n"
    write_atomic(Path(encoder_dir) / LATENT_DISTANCE_FILE, text.encode())


def _summary(values: np.ndarray) -> dict:
    if not len(values):
        return {"count": 0}
    return {"count": len(values), "mean": float(values.mean())} | {
        f"p{p}": float(np.percentile(values, p)) for p in PERCENTILES
    }


def plot_distances(stats: list[dict], path: Path) -> None:
    fig = Figure(figsize=(3.6 * len(stats), 3.0))
    axes = fig.subplots(1, len(stats), squeeze=False)
    for ax, s in zip(axes[0], stats, strict=True):
        bins = np.linspace(0, np.percentile(np.concatenate([s["_reached"], s["_random"]]), 99), 40)
        ax.hist(s["_random"], bins=bins, alpha=0.6, density=True, label="random frames")
        reached = (
            f"last {HINDSIGHT_REACHED_SHARE:.0%} of episodes" if s["goals"] == HINDSIGHT else "final frames, success"
        )
        ax.hist(s["_reached"], bins=bins, alpha=0.6, density=True, label=reached)
        ax.axvline(s["suggested_epsilon"], color="k", linestyle="--", label=f"epsilon {s['suggested_epsilon']:.2f}")
        ax.set_title(f"{s['camera']} (J = {s['youden_j']:.2f})", fontsize=9)
        ax.set_xlabel("||z - z_goal||^2", fontsize=8)
    axes[0, 0].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
