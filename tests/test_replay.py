"""Sampling goal-conditioned transitions with future hindsight relabelling."""

import numpy as np
import pytest
import torch

from lerobot_murm.policy.replay import LatentReplay
from lerobot_murm.vqvae.latent_cache import LatentCache

LENGTHS = (10, 12, 8)
GRID = 2


def identifying_cache(camera: str, scale: float) -> LatentCache:
    """Every frame's latent is (row * scale) in every cell; goals use codes after the frames."""
    episode_index = np.repeat(np.arange(len(LENGTHS)), LENGTHS)
    frame_index = np.concatenate([np.arange(n) for n in LENGTHS])
    n, e = len(episode_index), len(LENGTHS)
    codebook = np.stack([np.arange(n + e) * scale, np.zeros(n + e)], axis=1).astype(np.float32)
    indices = np.broadcast_to(np.arange(n)[:, None, None], (n, GRID, GRID)).astype(np.uint16)
    goals = np.broadcast_to((n + np.arange(e))[:, None, None], (e, GRID, GRID)).astype(np.uint16)
    return LatentCache(camera, indices.copy(), goals.copy(), codebook, episode_index, frame_index)


def row_of(latents: torch.Tensor, scale: float) -> torch.Tensor:
    """Invert identifying_cache: the first cell's first dimension is row * scale."""
    return (latents[..., 0] / scale).round().long()


@pytest.fixture
def replay():
    caches = [identifying_cache("global", 1.0), identifying_cache("active", 2.0)]
    actions = np.arange(sum(LENGTHS) * 4, dtype=np.float32).reshape(-1, 4)
    return LatentReplay(caches, actions, epsilons=[0.5, 0.5], her_ratio=0.15)


def test_transitions_pair_a_frame_with_its_successor_in_the_same_episode(replay):
    batch = replay.sample(4000, torch.Generator().manual_seed(0))
    latent = GRID * GRID * 2
    rows = row_of(batch.state[:, 0, :latent], 1.0)
    assert torch.equal(row_of(batch.state[:, 1, :latent], 2.0), rows)  # both cameras see the same frame
    assert torch.equal(row_of(batch.next_state[:, 0, :latent], 1.0), rows + 1)
    episode = torch.from_numpy(np.repeat(np.arange(3), LENGTHS))
    assert torch.equal(episode[rows], episode[rows + 1])  # never across an episode boundary
    assert torch.equal(batch.action[:, 0], rows.float() * 4)
    assert len(set(rows.tolist())) == sum(LENGTHS) - len(LENGTHS)  # every non-final frame gets sampled
    assert batch.done.sum() == 0


def test_her_relabels_the_configured_share_with_future_frames_of_the_same_episode(replay):
    batch = replay.sample(40_000, torch.Generator().manual_seed(1))
    latent = GRID * GRID * 2
    rows = row_of(batch.state[:, 0, :latent], 1.0)
    goals = row_of(batch.state[:, 0, latent:], 1.0)
    n = sum(LENGTHS)
    assert abs(batch.relabelled.float().mean().item() - 0.15) < 0.01
    episode = torch.from_numpy(np.repeat(np.arange(3), LENGTHS))
    relabelled, own = goals[batch.relabelled], goals[~batch.relabelled]
    assert torch.all(relabelled > rows[batch.relabelled]) and torch.all(relabelled < n)
    assert torch.equal(episode[relabelled], episode[rows[batch.relabelled]])
    assert torch.equal(own - n, episode[rows[~batch.relabelled]])  # the episode's own goal image
    # both cameras' goals come from the same future frame
    assert torch.equal(row_of(batch.state[:, 1, latent:], 2.0)[batch.relabelled], relabelled)
    assert torch.equal(batch.state[:, :, latent:], batch.next_state[:, :, latent:])


def test_reward_is_recomputed_for_the_goal_used(replay):
    batch = replay.sample(40_000, torch.Generator().manual_seed(2))
    latent = GRID * GRID * 2
    reached = row_of(batch.next_state[:, 0, :latent], 1.0) == row_of(batch.state[:, 0, latent:], 1.0)
    assert torch.equal(batch.reward, torch.where(reached, 0.0, -2.0))
    assert reached.any() and batch.relabelled[reached].all()


def test_caches_from_different_datasets_are_refused():
    short = identifying_cache("top", 1.0)
    short.episode_index = short.episode_index.copy()
    short.episode_index[-1] += 1
    with pytest.raises(ValueError, match="different datasets"):
        LatentReplay([identifying_cache("global", 1.0), short], np.zeros((30, 4)), [1.0, 1.0], 0.15)
