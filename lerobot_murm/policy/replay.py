"""Vectorised sampling of goal-conditioned transitions from latent caches, with future HER.

The one sampler of both trainers: `murm train` draws rows with `sample`, and under
`lerobot-train` LeRobot's sampler draws them and the policy turns the batch's `index`
column into transitions with `transitions`, so the goals, rewards and next states of
both come from the same code.

All cameras' latents (decoded from the cache's codebook indices once: 2.9 KB a frame,
0.29 GB per camera for 100,000 frames) and the actions live in memory as torch tensors
on the training device; a batch is gathered by index: row t, its successor t+1 in the
same episode, and a goal that is either the episode's own goal images or, with
probability `her_ratio`, the latents of a later frame of the same episode (paper 4.3,
future hindsight relabelling). The reward is recomputed for the goal actually used.
Episodes have a fixed horizon and no terminal states, so `done` is always 0.

Everything random about a batch (its rows, which goals are relabelled, the future frame,
and with view dropout which cameras vanish) is drawn from the batch's generator, so a
seed's batches are the same whether it trains alone or stacked with others
(`sample_stacked` draws each seed's batch from its own generator, then gathers all at once).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from lerobot.datasets.lerobot_dataset import LeRobotDataset

from lerobot_murm import features
from lerobot_murm.policy.configuration_murm import MurmConfig
from lerobot_murm.policy.iql import camera_keep_mask, sparse_reward
from lerobot_murm.vqvae.encoder_files import encoder_fingerprint
from lerobot_murm.vqvae.latent_cache import LatentCache, build_latent_cache
from lerobot_murm.vqvae.latent_dataset import read_latent_caches

# keys of a transition batch, what `MurmPolicy.forward` takes from `murm train` (not the dataset's
# feature keys, `features.STATE` / `ACTION` / `REWARD`)
TRANSITION_STATE, TRANSITION_NEXT_STATE, TRANSITION_ACTION = "state", "next_state", "action"
TRANSITION_REWARD, TRANSITION_DONE, TRANSITION_KEEP = "reward", "done", "keep"


@dataclass
class Batch:
    state: torch.Tensor  # (B, cameras, 2 * latent): (z_k, zg_k) per camera
    action: torch.Tensor  # (B, action_dim)
    reward: torch.Tensor  # (B,)
    next_state: torch.Tensor  # (B, cameras, 2 * latent)
    done: torch.Tensor  # (B,)
    relabelled: torch.Tensor  # (B,) bool, for tests and logging
    row: torch.Tensor  # (B,) the dataset row of s_t
    goal_row: torch.Tensor  # (B,) the frame whose latents are a relabelled goal; -1 for the episode's goal
    keep: torch.Tensor  # (B, cameras) bool: the cameras view dropout keeps (all without dropout)

    def transition(self) -> dict[str, torch.Tensor]:
        return {
            TRANSITION_STATE: self.state,
            TRANSITION_NEXT_STATE: self.next_state,
            TRANSITION_ACTION: self.action,
            TRANSITION_REWARD: self.reward,
            TRANSITION_DONE: self.done,
            TRANSITION_KEEP: self.keep,
        }

    def split(self, seeds: int) -> Batch:
        """(seeds * B, ...) fields as (seeds, B, ...): one batch per seed of a stack."""
        return Batch(**{name: value.unflatten(0, (seeds, -1)) for name, value in vars(self).items()})


@dataclass
class Draws:
    """What one batch draws from its generator, in this order (as `sample` always has)."""

    rows: torch.Tensor  # (B,) dataset rows with a successor
    relabel: torch.Tensor  # (B,) bool: a future frame is the goal
    future: torch.Tensor  # (B,) in [0, 1): where in t+1 .. last that frame lies
    keep: torch.Tensor  # (B, cameras) bool


class LatentReplay:
    def __init__(
        self,
        caches: list[LatentCache],
        actions: np.ndarray,
        epsilons: list[float],
        her_ratio: float,
        device: torch.device | str = "cpu",
        dropout_p: float = 0.0,
    ):
        if not caches:
            raise ValueError("at least one camera's latent cache is required")
        episode_index = caches[0].episode_index
        for cache in caches[1:]:
            if not np.array_equal(cache.episode_index, episode_index):
                raise ValueError(f"latent caches of {caches[0].camera} and {cache.camera} come from different datasets")
        if len(actions) != len(episode_index):
            raise ValueError(f"{len(actions)} actions for {len(episode_index)} frames")
        self.device = torch.device(device)
        self.her_ratio, self.dropout_p = her_ratio, dropout_p
        self.cameras = [c.camera for c in caches]
        self.latents = [torch.from_numpy(c.latents()).to(self.device) for c in caches]  # (N, D) per camera
        self.goal_latents = [torch.from_numpy(c.goal_latents()).to(self.device) for c in caches]  # (E, D)
        self.actions = torch.from_numpy(np.asarray(actions, np.float32)).to(self.device)
        self.epsilons = torch.tensor(epsilons, dtype=torch.float32, device=self.device)
        self.episode = torch.from_numpy(episode_index.astype(np.int64)).to(self.device)
        last_row = np.append(episode_index[1:] != episode_index[:-1], True)
        self.episode_end = self._episode_end(episode_index)
        self.transition_rows = torch.from_numpy(np.flatnonzero(~last_row)).to(self.device)

    def _episode_end(self, episode_index: np.ndarray) -> torch.Tensor:
        """Exclusive end row of each row's episode (rows are sorted by episode)."""
        ends = np.searchsorted(episode_index, episode_index, side="right")
        return torch.from_numpy(ends.astype(np.int64)).to(self.device)

    def sample(self, batch_size: int, generator: torch.Generator | None = None) -> Batch:
        """`batch_size` transitions from rows drawn uniformly among those with a successor."""
        return self._gather(self._draw(batch_size, generator))

    def sample_stacked(self, batch_size: int, generators: list[torch.Generator]) -> Batch:
        """One batch per generator, (seeds, B, ...), each what `sample` would draw with that
        generator alone; the gathers run once for all seeds."""
        draws = [self._draw(batch_size, g) for g in generators]
        joined = Draws(*(torch.cat(parts) for parts in zip(*(vars(d).values() for d in draws), strict=True)))
        return self._gather(joined).split(len(generators))

    def transitions(self, rows: torch.Tensor, generator: torch.Generator | None = None) -> Batch:
        """Transitions from the dataset rows `rows` (each must have a successor in its episode)."""
        rows = rows.to(self.device, torch.long)
        if (rows + 1 >= self.episode_end[rows]).any():
            raise ValueError("a row without a successor (the last frame of an episode) cannot start a transition")
        return self._gather(self._draw(len(rows), generator, rows))

    def _draw(self, batch_size: int, generator: torch.Generator | None, rows: torch.Tensor | None = None) -> Draws:
        """No host synchronisation: a CUDA graph captures it."""
        if rows is None:
            pick = torch.randint(len(self.transition_rows), (batch_size,), generator=generator, device=self.device)
            rows = self.transition_rows[pick]
        relabel = torch.rand(batch_size, generator=generator, device=self.device) < self.her_ratio
        future = torch.rand(batch_size, generator=generator, device=self.device)
        if self.dropout_p:
            keep = camera_keep_mask(batch_size, len(self.cameras), self.dropout_p, generator, self.device)
        else:  # no draw: runs without dropout keep the data order they always had
            keep = torch.ones(batch_size, len(self.cameras), dtype=torch.bool, device=self.device)
        return Draws(rows, relabel, future, keep)

    def _gather(self, draws: Draws) -> Batch:
        rows, relabel = draws.rows, draws.relabel
        next_rows = rows + 1
        span = (self.episode_end[rows] - next_rows).float()  # frames t+1 .. last
        future = next_rows + (draws.future * span).long()
        episodes = self.episode[rows]
        z = torch.stack([latents[rows] for latents in self.latents], dim=1)
        z_next = torch.stack([latents[next_rows] for latents in self.latents], dim=1)
        z_goal = torch.stack(
            [
                torch.where(relabel.unsqueeze(1), latents[future], goals[episodes])
                for latents, goals in zip(self.latents, self.goal_latents, strict=True)
            ],
            dim=1,
        )
        return Batch(
            state=torch.cat([z, z_goal], dim=-1),
            action=self.actions[rows],
            reward=sparse_reward(z_next, z_goal, self.epsilons),
            next_state=torch.cat([z_next, z_goal], dim=-1),
            done=torch.zeros(len(rows), device=self.device),
            relabelled=relabel,
            row=rows,
            goal_row=torch.where(relabel, future, -1),
            keep=draws.keep,
        )


def replay_for_dataset(
    config: MurmConfig, dataset: LeRobotDataset, cache_dir: Path | None, device: torch.device | str = "cpu"
) -> LatentReplay:
    """The replay of `config.cameras` over every row of `dataset`, for either trainer.

    A latent dataset (`murm encode --to-dataset`) gives its codes; a dataset of images is
    encoded once with the frozen encoders (through the latent cache in `cache_dir`, or in
    memory without one). With `hindsight_goals` each episode's goal is its last frame.
    """
    config.load_encoder_settings()
    encoder_dir = Path(config.encoder_dir or "")
    if features.latent_cameras(dataset.meta.features):
        fingerprints = {c: encoder_fingerprint(encoder_dir / c) for c in config.cameras} if config.encoder_dir else None
        caches = read_latent_caches(dataset, config.cameras, fingerprints)
    else:
        caches = [
            build_latent_cache(dataset.repo_id, dataset.root, encoder_dir / c, cache_dir, str(device))
            for c in config.cameras
        ]
    if config.hindsight_goals:
        caches = [cache.with_hindsight_goals() for cache in caches]
    actions = dataset.hf_dataset.with_format("arrow").select_columns([features.ACTION])[:][features.ACTION]
    actions = np.array(actions.combine_chunks().flatten(), np.float32).reshape(len(dataset), -1)
    return LatentReplay(
        caches,
        actions,
        config.epsilon,
        config.her_ratio,
        device=device,
        dropout_p=config.dropout_p if config.view_dropout else 0.0,
    )
