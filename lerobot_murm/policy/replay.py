"""Vectorised sampling of goal-conditioned transitions from latent caches, with future HER.

All cameras' latents (decoded from the cache's codebook indices once: 2.9 KB a frame,
0.29 GB per camera for 100,000 frames) and the actions live in memory as torch tensors
on the training device; a batch is gathered by index: row t, its successor t+1 in the
same episode, and a goal that is either the episode's own goal images or, with
probability `her_ratio`, the latents of a later frame of the same episode (paper 4.3,
future hindsight relabelling). The reward is recomputed for the goal actually used.
Episodes have a fixed horizon and no terminal states, so `done` is always 0.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from lerobot_murm.policy.iql import sparse_reward
from lerobot_murm.vqvae.latent_cache import LatentCache


@dataclass
class Batch:
    state: torch.Tensor  # (B, cameras, 2 * latent): (z_k, zg_k) per camera
    action: torch.Tensor  # (B, action_dim)
    reward: torch.Tensor  # (B,)
    next_state: torch.Tensor  # (B, cameras, 2 * latent)
    done: torch.Tensor  # (B,)
    relabelled: torch.Tensor  # (B,) bool, for tests and logging


class LatentReplay:
    def __init__(self, caches: list[LatentCache], actions: np.ndarray, epsilons: list[float],
                 her_ratio: float, device: torch.device | str = "cpu"):
        if not caches:
            raise ValueError("at least one camera's latent cache is required")
        episode_index = caches[0].episode_index
        for cache in caches[1:]:
            if not np.array_equal(cache.episode_index, episode_index):
                raise ValueError(f"latent caches of {caches[0].camera} and {cache.camera} come from different datasets")
        if len(actions) != len(episode_index):
            raise ValueError(f"{len(actions)} actions for {len(episode_index)} frames")
        self.device = torch.device(device)
        self.her_ratio = her_ratio
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
        pick = torch.randint(len(self.transition_rows), (batch_size,), generator=generator, device=self.device)
        rows = self.transition_rows[pick]
        next_rows = rows + 1
        relabel = torch.rand(batch_size, generator=generator, device=self.device) < self.her_ratio
        span = (self.episode_end[rows] - next_rows).float()  # frames t+1 .. last
        future = next_rows + (torch.rand(batch_size, generator=generator, device=self.device) * span).long()
        episodes = self.episode[rows]
        z = torch.stack([latents[rows] for latents in self.latents], dim=1)
        z_next = torch.stack([latents[next_rows] for latents in self.latents], dim=1)
        z_goal = torch.stack(
            [torch.where(relabel.unsqueeze(1), latents[future], goals[episodes])
             for latents, goals in zip(self.latents, self.goal_latents, strict=True)],
            dim=1,
        )
        return Batch(
            state=torch.cat([z, z_goal], dim=-1),
            action=self.actions[rows],
            reward=sparse_reward(z_next, z_goal, self.epsilons),
            next_state=torch.cat([z_next, z_goal], dim=-1),
            done=torch.zeros(batch_size, device=self.device),
            relabelled=relabel,
        )
