"""Goal-conditioned Implicit Q-Learning on VQ-VAE latents (paper 4.3, eq. 4-11), in one file.

State s = (z_1, zg_1, ..., z_i, zg_i): one (latent, goal latent) pair per camera. The
pieces here are plain torch and know nothing of LeRobot; `modeling_murm.py` wires
them into a LeRobot policy and the fast trainer samples batches for them.

- reward (eq. 4-5): per camera, 1 if ||z_k - zg_k||^2 < epsilon_k, summed, minus the
  number of cameras: 0 when every view has reached its goal, -i when none has.
- value (eq. 6/9): expectile regression of V(s) towards min(Q1, Q2)(s, a) of the targets.
- Q (eq. 7/10): TD regression towards r + gamma (1 - done) V(s').
- policy (eq. 8): advantage-weighted log-likelihood, weights exp(beta A) clipped.
- separated Q (eq. 11): one Q per camera on (z_k, zg_k, a), averaged.
- dropout: whole (z_k, zg_k) pairs zeroed with probability p, never all cameras.

The policy is a Gaussian whose mean is squashed by tanh and whose log-std is a learned
state-independent vector clamped to [log_std_min, log_std_max]; actions are clipped
to [-1, 1] (no tanh change of variables, as in IQL's reference implementation).
"""

from __future__ import annotations

import torch
from torch import nn


def sparse_reward(z: torch.Tensor, z_goal: torch.Tensor, epsilons: torch.Tensor) -> torch.Tensor:
    """Eq. 4-5. z, z_goal: (B, cameras, latent); epsilons: (cameras,). Returns (B,) in [-cameras, 0]."""
    reached = (z - z_goal).pow(2).sum(-1) < epsilons
    return reached.float().sum(-1) - z.shape[1]


def expectile_loss(diff: torch.Tensor, expectile: float) -> torch.Tensor:
    """L_2^tau of eq. 6: asymmetric squared error, tau for positive diffs (Q above V)."""
    weight = torch.where(diff > 0, expectile, 1.0 - expectile)
    return (weight * diff.pow(2)).mean()


def advantage_weights(advantage: torch.Tensor, beta: float, max_weight: float) -> torch.Tensor:
    """exp(beta * A), clipped at `max_weight` (eq. 8); no gradient flows into the critics."""
    return torch.exp(beta * advantage.detach()).clamp(max=max_weight)


@torch.no_grad()
def polyak_update(target: nn.Module, source: nn.Module, tau: float) -> None:
    for t, s in zip(target.parameters(), source.parameters(), strict=True):
        t.lerp_(s, tau)


def camera_keep_mask(batch: int, cameras: int, p: float, generator: torch.Generator | None = None,
                     device: torch.device | str = "cpu") -> torch.Tensor:
    """(B, cameras) bool: True keeps a camera. Each dropped with probability p; a row that
    would drop every camera keeps them all (the paper's rule)."""
    keep = torch.rand(batch, cameras, generator=generator, device=device) >= p
    all_dropped = ~keep.any(dim=1, keepdim=True)
    return keep | all_dropped


def mlp(in_dim: int, hidden: int, layers: int, out_dim: int) -> nn.Sequential:
    modules: list[nn.Module] = []
    for i in range(layers):
        modules += [nn.Linear(in_dim if i == 0 else hidden, hidden), nn.ReLU()]
    modules.append(nn.Linear(hidden, out_dim))
    return nn.Sequential(*modules)


class TwinQ(nn.Module):
    """Clipped double Q on the whole state (single, concat and dropout methods)."""

    def __init__(self, state_dim: int, action_dim: int, hidden: int, layers: int):
        super().__init__()
        self.q1 = mlp(state_dim + action_dim, hidden, layers, 1)
        self.q2 = mlp(state_dim + action_dim, hidden, layers, 1)

    def forward(self, state: torch.Tensor, action: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        x = torch.cat([state.flatten(1), action], dim=-1)
        return self.q1(x).squeeze(-1), self.q2(x).squeeze(-1)


class SeparatedTwinQ(nn.Module):
    """Eq. 11: per camera k, Q_k(z_k, zg_k, a); Q_mean is their average. Two such sets."""

    def __init__(self, cameras: int, pair_dim: int, action_dim: int, hidden: int, layers: int):
        super().__init__()
        self.q1 = nn.ModuleList(mlp(pair_dim + action_dim, hidden, layers, 1) for _ in range(cameras))
        self.q2 = nn.ModuleList(mlp(pair_dim + action_dim, hidden, layers, 1) for _ in range(cameras))

    def forward(self, state: torch.Tensor, action: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """state: (B, cameras, pair_dim) with pair = (z_k, zg_k)."""
        pairs = [torch.cat([state[:, k], action], dim=-1) for k in range(state.shape[1])]
        mean = [torch.stack([head(x).squeeze(-1) for head, x in zip(heads, pairs, strict=True)]).mean(0)
                for heads in (self.q1, self.q2)]
        return mean[0], mean[1]


class GaussianPolicy(nn.Module):
    def __init__(self, state_dim: int, action_dim: int, hidden: int, layers: int,
                 log_std_min: float, log_std_max: float):
        super().__init__()
        self.mean = mlp(state_dim, hidden, layers, action_dim)
        self.log_std = nn.Parameter(torch.zeros(action_dim))
        self.log_std_min, self.log_std_max = log_std_min, log_std_max

    def distribution(self, state: torch.Tensor) -> torch.distributions.Normal:
        mean = torch.tanh(self.mean(state.flatten(1)))
        std = self.log_std.clamp(self.log_std_min, self.log_std_max).exp()
        return torch.distributions.Normal(mean, std.expand_as(mean))

    def act(self, state: torch.Tensor, deterministic: bool = True) -> torch.Tensor:
        dist = self.distribution(state)
        action = dist.mean if deterministic else dist.sample()
        return action.clamp(-1.0, 1.0)
