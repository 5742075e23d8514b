"""Goal-conditioned Implicit Q-Learning on VQ-VAE latents (paper 4.3, eq. 4-11), in one file.

State s = (z_1, zg_1, ..., z_i, zg_i): one (latent, goal latent) pair per camera. The
pieces here are plain torch and know nothing of LeRobot; `modeling_murm.py` wires
them into a LeRobot policy and the fast trainer samples batches for them.

- reward (eq. 4-5, `sparse_reward`): per camera, 1 if ||z_k - zg_k||^2 < epsilon_k, summed,
  minus the number of cameras: 0 when every view has reached its goal, -i when none has.
- value (eq. 6/9, `value_loss`): expectile regression of V(s) towards min(Q1, Q2)(s, a) of
  the targets.
- Q (eq. 7/10, `critic_loss`): TD regression towards r + gamma (1 - done) V(s') (`td_target`).
- policy (eq. 8, `actor_loss`): advantage-weighted log-likelihood, weights exp(beta A) clipped.
- separated Q (eq. 11, `DoubleQ` with one group per camera): one Q per camera on
  (z_k, zg_k, a), averaged.
- dropout (`camera_keep_mask` draws it, `drop_views` applies it): whole (z_k, zg_k) pairs
  zeroed with probability p, never all cameras; with separated Q a dropped camera's Q_k may
  instead be left out of the mean.

`MurmPolicy.iql_loss` (modeling_murm.py) is these pieces in a row, as CORL's IQL writes them.

Every network and loss here also takes leading dimensions before the batch: the seeds of a
seed stack (`training/seed_stack.py`), whose weights carry the same leading dimension. Losses
reduce over the batch (the last dimension) only, so a stack gets one loss per seed.

The policy is a Gaussian whose mean is squashed by tanh and whose log-std is a learned
state-independent vector squashed into [log_std_min, log_std_max] by a sigmoid (a hard
clamp would stop its gradient whenever it sits outside the range); actions are clipped
to [-1, 1] (no tanh change of variables, as in IQL's reference implementation).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import nn

from lerobot_murm.policy.precision import fp32_output


def sparse_reward(z: torch.Tensor, z_goal: torch.Tensor, epsilons: torch.Tensor) -> torch.Tensor:
    """Eq. 4-5. z, z_goal: (B, cameras, latent); epsilons: (cameras,). Returns (B,) in [-cameras, 0]."""
    reached = (z - z_goal).pow(2).sum(-1) < epsilons
    return reached.float().sum(-1) - z.shape[1]


def expectile_loss(diff: torch.Tensor, expectile: float) -> torch.Tensor:
    """L_2^tau of eq. 6: asymmetric squared error, tau for positive diffs (Q above V); the
    mean over the batch (the last dimension)."""
    weight = torch.where(diff > 0, expectile, 1.0 - expectile)
    return (weight * diff.pow(2)).mean(-1)


def advantage_weights(advantage: torch.Tensor, beta: float, max_weight: float) -> torch.Tensor:
    """exp(beta * A), clipped at `max_weight` (eq. 8); no gradient flows into the critics."""
    return torch.exp(beta * advantage.detach()).clamp(max=max_weight)


def value_loss(
    value: nn.Module, state: torch.Tensor, q_target: torch.Tensor, expectile: float
) -> tuple[torch.Tensor, torch.Tensor]:
    """Eq. 6 (eq. 9 with separated Q): L_V = E[L_2^tau(min(Q^_1, Q^_2)(s, a) - V(s))], the
    target critics' value `q_target` against V(s). Returns the loss and V(s)."""
    v = value(state.flatten(-2)).squeeze(-1)
    return expectile_loss(q_target - v, expectile), v


def td_target(
    value: nn.Module, reward: torch.Tensor, done: torch.Tensor, next_state: torch.Tensor, discount: float
) -> torch.Tensor:
    """r + gamma (1 - done) V(s'), the regression target of eq. 7 and 10."""
    next_v = value(next_state.flatten(-2)).squeeze(-1)
    return reward + discount * (1.0 - done) * next_v


def critic_loss(
    critic: DoubleQ,
    critic_input: torch.Tensor,
    action: torch.Tensor,
    q_heads: torch.Tensor | None,
    target: torch.Tensor,
) -> torch.Tensor:
    """Eq. 7 (eq. 10 with separated Q, Q the mean of eq. 11): L_Q = E[(target - Q(s, a))^2] for
    each of the clipped double Q's two sets, their MSEs summed."""
    q = critic(critic_input, action, q_heads)
    return (q - target.unsqueeze(-2)).pow(2).mean(-1).sum(-1)


def actor_loss(
    actor: GaussianPolicy,
    state: torch.Tensor,
    action: torch.Tensor,
    advantage: torch.Tensor,
    beta: float,
    max_weight: float,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Eq. 8: L_pi = -E[exp(beta (Q^(s, a) - V(s))) log pi(a | s)], the weights clipped at
    `max_weight` (`advantage_weights`). Returns the loss and the weights."""
    weights = advantage_weights(advantage, beta, max_weight)
    log_prob = actor.distribution(state.flatten(-2)).log_prob(action.clamp(-1.0, 1.0)).sum(-1)
    return -(weights * log_prob).mean(-1), weights


@dataclass
class Views:
    """What each network sees of s_t and s_t+1, (B, cameras, 2 * latent) each, after view dropout."""

    state: torch.Tensor  # V(s)'s input
    next_state: torch.Tensor  # V(s')'s input, for the TD target
    critic: torch.Tensor  # the critics' input: (B, cameras, 2 * latent) with separated Q, else (B, 1, all)
    actor: torch.Tensor  # the policy's input
    q_heads: torch.Tensor | None  # (B, cameras) bool: the Q heads each row averages (None: all of them)


def drop_views(
    state: torch.Tensor,
    next_state: torch.Tensor,
    keep: torch.Tensor | None,
    separated_q: bool,
    scope: str = "all",
    dropped_q: str = "zeros",
) -> Views:
    """The dropout method (paper 4.3): the (z_k, zg_k) pairs `keep` drops are zeroed, the same
    cameras in s_t and s_t+1 (`keep` None: no dropout). `scope` "all" (the paper) shows the
    dropped state to V, Q and the policy, "actor" to the policy alone. `dropped_q` "excluded"
    (separated Q, scope "all"): each Q_k keeps its own pair and the dropped cameras' Q_k leave
    eq. 11's mean instead of seeing a zero pair."""

    def critic_input(s: torch.Tensor) -> torch.Tensor:
        return s if separated_q else s.flatten(-2).unsqueeze(-2)

    if keep is None:
        return Views(state, next_state, critic_input(state), state, None)
    dropped = state * keep.unsqueeze(-1)
    if scope == "actor":
        return Views(state, next_state, critic_input(state), dropped, None)
    next_dropped = next_state * keep.unsqueeze(-1)
    if dropped_q == "excluded":
        return Views(dropped, next_dropped, critic_input(state), dropped, keep)
    return Views(dropped, next_dropped, critic_input(dropped), dropped, None)


@torch.no_grad()
def polyak_update(target: nn.Module, source: nn.Module, tau: float) -> None:
    for t, s in zip(target.parameters(), source.parameters(), strict=True):
        t.lerp_(s, tau)


def camera_keep_mask(
    batch: int, cameras: int, p: float, generator: torch.Generator | None = None, device: torch.device | str = "cpu"
) -> torch.Tensor:
    """(B, cameras) bool: True keeps a camera. Each dropped with probability p; a row that
    would drop every camera keeps them all (the paper's rule)."""
    keep = torch.rand(batch, cameras, generator=generator, device=device) >= p
    all_dropped = ~keep.any(dim=1, keepdim=True)
    return keep | all_dropped


def mlp(in_dim: int, hidden: int, layers: int, out_dim: int) -> nn.Sequential:
    modules: list[nn.Module] = []
    for i in range(layers):
        modules += [Linear(in_dim if i == 0 else hidden, hidden), nn.ReLU()]
    modules.append(OutputLinear(hidden, out_dim))
    return nn.Sequential(*modules)


class Linear(nn.Linear):
    """nn.Linear (same parameters, same checkpoints) whose weight may carry a leading seed
    dimension, (seeds, out, in), applied to (seeds, B, in) as one batched matmul."""

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if self.weight.dim() == 2:
            return super().forward(x)
        return torch.baddbmm(self.bias.unsqueeze(-2), x, self.weight.transpose(-1, -2))


class OutputLinear(Linear):
    """A network's last layer: float32 under mixed precision (see `fp32_output`)."""

    forward = fp32_output(Linear.forward)


class EnsembleLinear(nn.Module):
    """`heads` independent linear layers applied as one batched matmul: (heads, B, in) -> (heads, B, out);
    with a seed stack's leading dimension, (seeds, heads, B, in): all seeds' heads in one matmul."""

    def __init__(self, heads: int, in_dim: int, out_dim: int):
        super().__init__()
        bound = in_dim**-0.5  # nn.Linear's default initialisation, per head
        self.weight = nn.Parameter(torch.empty(heads, in_dim, out_dim).uniform_(-bound, bound))
        self.bias = nn.Parameter(torch.empty(heads, 1, out_dim).uniform_(-bound, bound))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        out = torch.baddbmm(self.bias.flatten(0, -3), x.flatten(0, -3), self.weight.flatten(0, -3))
        return out.view(*x.shape[:-1], -1)


class EnsembleOutput(EnsembleLinear):
    """An ensemble's last layer: float32 under mixed precision (see `fp32_output`)."""

    forward = fp32_output(EnsembleLinear.forward)


class DoubleQ(nn.Module):
    """Clipped double Q as one ensemble: two sets of `groups` Q heads, each set averaged.

    groups = 1: Q(s, a) on the whole state (single, concat and dropout methods).
    groups = cameras: eq. 11, Q_k(z_k, zg_k, a) per camera, averaged (separated Q).
    All 2 x groups heads run as batched matmuls; the first layer, which carries almost
    all the FLOPs, is one matmul per input group for both sets.
    """

    def __init__(self, groups: int, group_dim: int, action_dim: int, hidden: int, layers: int):
        super().__init__()
        self.groups, self.hidden = groups, hidden
        self.first = EnsembleLinear(groups, group_dim + action_dim, 2 * hidden)
        self.body = nn.ModuleList(EnsembleLinear(2 * groups, hidden, hidden) for _ in range(layers - 1))
        self.out = EnsembleOutput(2 * groups, hidden, 1)

    def forward(self, state: torch.Tensor, action: torch.Tensor, keep: torch.Tensor | None = None) -> torch.Tensor:
        """state: (B, groups, group_dim); keep: optional (B, groups) bool, the heads each row
        averages over (all when None). Returns (2, B): the two sets' averaged Q values.
        A seed stack's inputs and output have its seed dimension in front."""
        action = action.to(state.dtype).unsqueeze(-2).expand(*state.shape[:-1], -1)
        x = torch.cat([state, action], dim=-1).transpose(-3, -2)  # (groups, B, in)
        h = torch.relu(self.first(x))  # (groups, B, 2 * hidden): both sets at once
        h = h.unflatten(-1, (2, self.hidden)).movedim(-2, -4).flatten(-4, -3)  # (2 * groups, B, hidden)
        for layer in self.body:
            h = torch.relu(layer(h))
        q = self.out(h).squeeze(-1).unflatten(-2, (2, self.groups))  # (2, groups, B)
        if keep is None:
            return q.mean(-2)
        weights = keep.transpose(-1, -2).to(q.dtype).unsqueeze(-3)  # (1, groups, B)
        return (q * weights).sum(-2) / weights.sum(-2)


class GaussianPolicy(nn.Module):
    def __init__(
        self, state_dim: int, action_dim: int, hidden: int, layers: int, log_std_min: float, log_std_max: float
    ):
        super().__init__()
        self.mean = mlp(state_dim, hidden, layers, action_dim)
        self.log_std_logit = nn.Parameter(torch.zeros(action_dim))  # starts mid-range
        self.log_std_min, self.log_std_max = log_std_min, log_std_max

    def distribution(self, state: torch.Tensor) -> torch.distributions.Normal:
        mean = torch.tanh(self.mean(state))
        span = self.log_std_max - self.log_std_min
        std = (self.log_std_min + span * torch.sigmoid(self.log_std_logit)).exp().unsqueeze(-2)
        # no argument validation: its data-dependent checks would synchronise with the device at
        # every step, which a CUDA graph cannot capture
        return torch.distributions.Normal(mean, std.expand_as(mean), validate_args=False)

    def act(self, state: torch.Tensor, deterministic: bool = True) -> torch.Tensor:
        dist = self.distribution(state)
        action = dist.mean if deterministic else dist.sample()
        return action.clamp(-1.0, 1.0)

    def forward(self, state: torch.Tensor) -> torch.Tensor:
        """The deterministic action: what evaluation runs (for a stack's seeds at once, through
        `torch.func.functional_call`)."""
        return self.act(state)
