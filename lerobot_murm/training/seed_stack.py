"""Seeds side by side: the K seeds of one cell trained as one stacked model.

Our networks are small, so one seed's update is mostly per-operation cost (Python dispatch,
~100 small kernels, their launches on a GPU) rather than arithmetic. A stack gives every
weight and Adam moment a leading seed dimension and runs `MurmPolicy.iql_loss` once on
them (`torch.func.functional_call`; every network in `policy/iql.py` takes leading seed dimensions):
the twin-Q and per-camera heads of all seeds become one ensemble of batched matmuls, and
Adam and Polyak one update per tensor for all seeds. nn.Linear weights are stacked as
(seeds, in, out), the layout a batched matmul reads without a transposed copy (a transposed
copy of a stacked weight and of its gradient cost more than the matmul on a CPU).

Each seed stays what it would be alone: its `MurmPolicy` is built as a lone run builds it
(its own initialisation), its batches come from its own generator
(`LatentReplay.sample_stacked`), its loss reaches only its own weights (the stack's loss is
the sum over seeds) and Adam is element-wise. The stack is a training device only:
`write_back` puts each seed's weights into its own `MurmPolicy` and `optimizer_state(k)`
is a lone optimizer's state dict, so checkpoints are ordinary LeRobot ones and a run resumes
stacked or alone from them.
"""

from __future__ import annotations

import copy

import torch
from torch import Tensor, nn

from lerobot_murm.policy.modeling_murm import MurmPolicy
from lerobot_murm.policy.precision import cpu_has_native_bf16, matmul_precision, resolve_precision
from lerobot_murm.policy.replay import Batch


class _IQLLoss(nn.Module):
    """`MurmPolicy.iql_loss` as a module's forward, for `torch.func.functional_call`."""

    def __init__(self, policy: MurmPolicy):
        super().__init__()
        self.policy = policy

    def forward(self, transition: dict[str, Tensor]) -> tuple[Tensor, Tensor]:
        return self.policy.iql_loss(transition)


class SeedStack:
    """K policies of one recipe (same config, encoders and data; own weights) trained as one model."""

    def __init__(self, policies: list[MurmPolicy]):
        base = policies[0]
        if any(p.config.method != base.config.method or p.cameras != base.cameras for p in policies):
            raise ValueError("a seed stack holds the seeds of one cell: one method and one set of cameras")
        # every parameter but the frozen encoders' gets a seed dimension; the encoders and the
        # buffers (latent statistics, epsilon: the cell's data) stay shared
        own = [dict(p.named_parameters()) for p in policies]
        stacked = [n for n in own[0] if not n.startswith("encoders.")]
        shared = [(n, t) for n, t in base.state_dict().items() if n not in stacked]
        if any(not torch.equal(p.state_dict()[n], t) for p in policies[1:] for n, t in shared):
            raise ValueError("the seeds of a stack share their encoders and latent statistics (one dataset)")
        self.policies = policies
        self.device = next(base.parameters()).device
        self._precision = resolve_precision(base.config.precision, self.device)
        self._transposed = {f"{n}.weight" for n, m in base.named_modules() if isinstance(m, nn.Linear)}
        with torch.no_grad():
            self.tensors = {
                n: torch.stack([self._stacked_layout(n, o[n]) for o in own]).requires_grad_(own[0][n].requires_grad)
                for n in stacked
            }
        name_of = {id(t): n for n, t in base.named_parameters()}
        groups = [g | {"params": [self.tensors[name_of[id(t)]] for t in g["params"]]} for g in base.get_optim_params()]
        self._optimized = [name_of[id(t)] for g in base.get_optim_params() for t in g["params"]]
        self.optimizer = base.config.get_optimizer_preset().build(groups)
        critic = [n for n, _ in base.critic.named_parameters()]
        self._targets = [(self.tensors[f"critic_target.{n}"], self.tensors[f"critic.{n}"]) for n in critic]
        self._loss = _IQLLoss(base)

    def __len__(self) -> int:
        return len(self.policies)

    def _stacked_layout(self, name: str, tensor: Tensor) -> Tensor:
        """One seed's tensor as the stack holds it (an nn.Linear weight transposed); its own inverse."""
        return tensor.t() if name in self._transposed else tensor

    def loss(self, batch: Batch) -> tuple[Tensor, Tensor]:
        """Every seed's IQL loss on its own batch ((seeds, B, ...) fields): (seeds,) losses
        and (seeds, len(LOGGED)) logged values, still on the device."""
        weights = {f"policy.{n}": t.transpose(-1, -2) if n in self._transposed else t for n, t in self.tensors.items()}
        with matmul_precision(self._precision, self.device):
            return torch.func.functional_call(self._loss, weights, (batch.transition(),), strict=False)

    def step(self, batch: Batch) -> Tensor:
        """One update of every seed (loss, backward, Adam, Polyak); the logged values, left on
        the device for the caller to read when it logs (no host synchronisation here)."""
        loss, logged = self.loss(batch)
        self.optimizer.zero_grad(set_to_none=True)
        loss.sum().backward()
        self.optimizer.step()
        self.update_targets()
        return logged

    @torch.no_grad()
    def update_targets(self) -> None:
        """`MurmPolicy.update` for every seed at once."""
        tau = self.policies[0].config.target_update_rate
        for target, source in self._targets:
            target.lerp_(source, tau)

    @torch.no_grad()
    def write_back(self) -> list[MurmPolicy]:
        """Each seed's current weights into its own `MurmPolicy` (to save or evaluate it)."""
        for k, policy in enumerate(self.policies):
            own = dict(policy.named_parameters())
            for name, stacked in self.tensors.items():
                own[name].copy_(self._stacked_layout(name, stacked[k]))
        return self.policies

    def optimizer_state(self, k: int) -> dict:
        """Seed k's part of the optimizer state, as its lone optimizer's `state_dict()`."""
        state = self.optimizer.state_dict()
        # contiguous: fused Adam walks a moment and its parameter element by element in memory order
        per_param = {
            i: {
                key: (value if key == "step" else self._stacked_layout(self._optimized[i], value[k])).clone(
                    memory_format=torch.contiguous_format
                )
                for key, value in moments.items()
            }
            for i, moments in state["state"].items()
        }
        return {"state": per_param, "param_groups": state["param_groups"]}

    def load_optimizer_states(self, states: list[dict]) -> None:
        """The seeds' lone optimizer states (from their checkpoints, all at one step) into the stack."""
        if len(states) != len(self):
            raise ValueError(f"{len(states)} optimizer states for a stack of {len(self)} seeds")
        first = states[0]["state"]
        for s in states[1:]:
            if s["state"].keys() != first.keys() or any(
                not torch.equal(s["state"][i]["step"], first[i]["step"]) for i in first
            ):
                raise ValueError("the seeds' optimizer states are at different steps; a stack trains in lockstep")
        stacked = {
            i: {
                key: value
                if key == "step"
                else torch.stack([self._stacked_layout(self._optimized[i], s["state"][i][key]) for s in states])
                for key, value in moments.items()
            }
            for i, moments in first.items()
        }
        self.optimizer.load_state_dict({"state": stacked, "param_groups": states[0]["param_groups"]})


class LoneSeed:
    """One seed on its own modules and optimizer (as `lerobot-train` trains it), with a stack's
    interface: a stack of one runs batched matmuls of one, a few % slower than plain ones."""

    def __init__(self, policy: MurmPolicy):
        self.policies = [policy]
        self.device = next(policy.parameters()).device
        self._precision = resolve_precision(policy.config.precision, self.device)
        self.optimizer = policy.config.get_optimizer_preset().build(policy.get_optim_params())

    def __len__(self) -> int:
        return 1

    def step(self, batch: Batch) -> Tensor:
        """`SeedStack.step` for a batch of one seed ((1, B, ...) fields)."""
        policy = self.policies[0]
        with matmul_precision(self._precision, self.device):
            loss, logged = policy.iql_loss({key: value[0] for key, value in batch.transition().items()})
        self.optimizer.zero_grad(set_to_none=True)
        loss.backward()
        self.optimizer.step()
        policy.update()
        return logged.unsqueeze(0)

    def write_back(self) -> list[MurmPolicy]:
        return self.policies

    def optimizer_state(self, k: int) -> dict:
        return copy.deepcopy(self.optimizer.state_dict())

    def load_optimizer_states(self, states: list[dict]) -> None:
        self.optimizer.load_state_dict(states[0])


def train_together(policies: list[MurmPolicy]) -> SeedStack | LoneSeed:
    """What trains these seeds' policies in lockstep: a stack, or the lone seed itself."""
    return SeedStack(policies) if len(policies) > 1 else LoneSeed(policies[0])


def stacking_pays(device: torch.device) -> bool:
    """Whether seeds train faster stacked than one after another: on a GPU (launch-bound) and on
    CPUs with native bf16 (BENCHMARKS.md, "Seeds side by side"); a CPU without it trains in
    fp32, where a stacked step is no faster than the seeds' steps one after another."""
    return device.type == "cuda" or cpu_has_native_bf16()
