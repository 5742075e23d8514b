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
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from lerobot.datasets.lerobot_dataset import LeRobotDataset

from lerobot_murm import features
from lerobot_murm.policy.configuration_murm import MurmConfig
from lerobot_murm.policy.iql import sparse_reward
from lerobot_murm.vqvae.latent_cache import LatentCache, build_latent_cache, encoder_fingerprint
from lerobot_murm.vqvae.latent_dataset import read_latent_caches

# keys of a transition batch, what `MurmPolicy.forward` takes from `murm train`
STATE, NEXT_STATE, ACTION, REWARD, DONE = "state", "next_state", "action", "reward", "done"


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

    def transition(self) -> dict[str, torch.Tensor]:
        return {STATE: self.state, NEXT_STATE: self.next_state, ACTION: self.action, REWARD: self.reward,
                DONE: self.done}


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
        """`batch_size` transitions from rows drawn uniformly among those with a successor."""
        pick = torch.randint(len(self.transition_rows), (batch_size,), generator=generator, device=self.device)
        return self.transitions(self.transition_rows[pick], generator)

    def transitions(self, rows: torch.Tensor, generator: torch.Generator | None = None) -> Batch:
        """Transitions from the dataset rows `rows` (each must have a successor in its episode)."""
        rows = rows.to(self.device, torch.long)
        batch_size, next_rows = len(rows), rows + 1
        if (next_rows >= self.episode_end[rows]).any():
            raise ValueError("a row without a successor (the last frame of an episode) cannot start a transition")
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
            row=rows,
            goal_row=torch.where(relabel, future, -1),
        )


def replay_for_dataset(config: MurmConfig, dataset: LeRobotDataset, cache_dir: Path | None,
                       device: torch.device | str = "cpu") -> LatentReplay:
    """The replay of `config.cameras` over every row of `dataset`, for either trainer.

    A latent dataset (`murm encode --to-dataset`) gives its codes; a dataset of images is
    encoded once with the frozen encoders (through the latent cache in `cache_dir`, or in
    memory without one).
    """
    config.load_encoder_settings()
    encoder_dir = Path(config.encoder_dir or "")
    if features.latent_cameras(dataset.meta.features):
        fingerprints = {c: encoder_fingerprint(encoder_dir / c) for c in config.cameras} if config.encoder_dir else None
        caches = read_latent_caches(dataset, config.cameras, fingerprints)
    else:
        caches = [build_latent_cache(dataset.repo_id, dataset.root, encoder_dir / c, cache_dir, str(device))
                  for c in config.cameras]
    actions = dataset.hf_dataset.with_format("arrow").select_columns([features.ACTION])[:][features.ACTION]
    actions = np.array(actions.combine_chunks().flatten(), np.float32).reshape(len(dataset), -1)
    return LatentReplay(caches, actions, config.epsilon, config.her_ratio, device=device)
