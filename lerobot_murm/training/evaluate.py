"""Success rate of a MURM policy in the simulator over a fixed list of seeded episodes.

An episode succeeds if the task's success condition holds at any step, as in
`lerobot-eval`, so once it has succeeded its simulator is not stepped again (`HeldAfterSuccess`).
Camera masking (Table 4) is the policy's own `eval_mask_p`, so this
evaluation and `lerobot-eval` mask identically. The simulators run in worker processes
(a gymnasium AsyncVectorEnv) where there are cores to spare, else in the trainer's process
(a SyncVectorEnv), while the policy acts on the whole batch at once.

The seeds of a stack (`seed_stack.py`) evaluate together: `num_envs` simulators per seed in
one pool, each seed's group running the very episodes (seeds, batching, masking draws) it
would run alone, and one forward per step for all of them: the shared encoders once over
every observation, then all seeds' actors as one batched network.
"""

from __future__ import annotations

import os
import signal
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from functools import partial

import gymnasium as gym
import numpy as np
import torch
from gymnasium.vector.async_vector_env import _async_worker

from lerobot_murm.env import EPISODE_STEPS, GYM_IDS
from lerobot_murm.features import goal_image_key, goal_key, image_key
from lerobot_murm.policy.modeling_murm import MurmPolicy


@dataclass
class EvalResult:
    task: str
    mask_p: float
    mask_mode: str
    seeds: list[int]
    successes: list[bool]
    seconds: float
    success_rate: float = field(init=False)

    def __post_init__(self) -> None:
        self.success_rate = float(np.mean(self.successes)) if self.successes else 0.0


class EvaluationStopped(Exception):
    """A stop was asked for during an evaluation; its episodes so far are dropped."""


VALIDATION_SEED = 200_000  # learning curves and every choice (hyperparameters, update counts, variants)
TEST_SEED = 300_000  # the reported numbers only, never looked at to choose


def evaluation_seeds(episodes: int, first_seed: int) -> list[int]:
    """Fixed, consecutive evaluation seeds. Both ranges lie far from the collection's episode
    seeds and from each other; 100,000-100,099 were the test range of an earlier setting in
    which choices were made on them, so neither range uses them."""
    return list(range(first_seed, first_seed + episodes))


class HeldAfterSuccess(gym.Wrapper):
    """A simulator whose episode has already succeeded skips its remaining steps: an action of
    NaNs (which `MurmEnv` refuses as an action) returns its last step again, unsimulated.

    Its success cannot be undone, so the evaluation's outcome is the same; the policy still acts
    on every row (on a held row's last observation), so every other row's actions and masking
    draws are those of a run that simulates every step, bit for bit. In an unmasked validation of
    the hindsight grid's global camera (90,000 updates, 81 % success) a third of the simulated
    steps came after their episode's success (BENCHMARKS.md)."""

    def reset(self, **kwargs):
        observation, info = self.env.reset(**kwargs)
        self._last = observation, 0.0, False, False, info
        return observation, info

    def step(self, action):
        if np.isnan(action).all():
            return self._last
        self._last = self.env.step(action)
        return self._last


def _make_worker_env(env_id: str, kwargs: dict, trainer_pid: int) -> gym.Env:
    """A simulator worker leaves a stop to the trainer. Ctrl-C reaches the terminal's whole
    process group and `pkill -f murm` matches the forked workers too; a worker that died of
    it would break the trainer's pipes before the trainer could save its checkpoint.
    Gymnasium also calls this once in the trainer itself, to read the spaces: that process
    (itself a child process under `murm reproduce --jobs`) keeps its handlers."""
    if os.getpid() != trainer_pid:
        signal.signal(signal.SIGINT, signal.SIG_IGN)
        signal.signal(signal.SIGTERM, signal.SIG_IGN)
    return HeldAfterSuccess(gym.make(env_id, **kwargs))


def act_together(
    policies: list[MurmPolicy],
    batch: dict[str, torch.Tensor],
    actors: tuple[dict, dict] | None = None,
    goals: torch.Tensor | None = None,
) -> torch.Tensor:
    """Deterministic actions of policies that share their encoders, for equal consecutive groups
    of the batch's rows (group k: policy k, masked by policy k's own settings and draws). One
    encoder pass for all rows; the actors run as one batched network (`actors`, their weights
    stacked by `torch.func.stack_module_state`; made here if not given). `goals`: the rows' goal
    latents (`MurmPolicy.goal_state`), encoded once per episode; else the batch's goal images."""
    seeds = len(policies)
    latents = policies[0].observation_latents(batch, goals).unflatten(0, (seeds, -1))
    states = torch.stack(
        [
            p.masked_state(z, p.config.eval_mask_p, p.config.eval_mask_mode)
            for p, z in zip(policies, latents, strict=True)
        ]
    )
    weights = actors or torch.func.stack_module_state([p.actor for p in policies])
    return torch.func.functional_call(policies[0].actor, weights, (states.flatten(-2),)).flatten(0, 1)


def _worker(*args: object) -> None:
    """Gymnasium's simulator worker, which exits quietly when the trainer is gone (kill -9):
    its pipe to the trainer then breaks, and gymnasium's worker would report that with a
    `BrokenPipeError` traceback into the output the trainer shared with it."""
    try:
        _async_worker(*args)
    except (EOFError, ConnectionError):
        os._exit(1)


class Evaluator:
    """Keeps `num_envs` simulators per policy evaluated together alive between evaluations.

    They step in worker processes when this process has more than one core (torch's thread
    count: `murm train` alone has the machine's, a grid's job `cores // jobs`), else in this
    process: on one core the workers only add pipes and context switches (evaluations 1.2x
    slower with two jobs on two cores, BENCHMARKS.md). `processes` forces either way. The
    episodes, their batching and the masking draws are the same either way. `hold_succeeded`
    False simulates every step of every episode, as before `HeldAfterSuccess` (the same
    successes, more time: benchmarks/bench_eval_held.py)."""

    def __init__(
        self,
        task: str,
        cameras: list[str],
        image_size: int = 48,
        num_envs: int = 4,
        policies: int = 1,
        processes: bool | None = None,
        hold_succeeded: bool = True,
    ):
        if task not in GYM_IDS:
            raise ValueError(f"unknown task {task!r}; choose one of {sorted(GYM_IDS)}")
        self.task, self.cameras, self.num_envs, self.policies = task, list(cameras), num_envs, policies
        self.hold_succeeded = hold_succeeded
        kwargs = {"cameras": self.cameras, "image_size": image_size, "render_mode": None}
        makers = [partial(_make_worker_env, GYM_IDS[task], kwargs, os.getpid()) for _ in range(num_envs * policies)]
        in_workers = torch.get_num_threads() > 1 if processes is None else processes
        if in_workers:
            self.envs = gym.vector.AsyncVectorEnv(makers, context="fork", worker=_worker)
        else:
            self.envs = gym.vector.SyncVectorEnv(makers)

    def close(self) -> None:
        self.envs.close()

    def __enter__(self) -> Evaluator:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _batch(self, observation: dict, device: torch.device, goals: bool = True) -> dict[str, torch.Tensor]:
        """Env observations -> the policy's input, as LeRobot's preprocessing makes it (float in
        [0, 1]); `goals` False leaves the goal images out (their latents are known)."""
        pixels = observation["pixels"]
        batch = {}
        for camera in self.cameras:
            keys = [(camera, image_key(camera))]
            if goals:
                keys.append((goal_key(camera), goal_image_key(camera)))
            for key, feature in keys:
                images = torch.from_numpy(np.ascontiguousarray(pixels[key])).to(device)
                batch[feature] = images.permute(0, 3, 1, 2).float().div_(255.0)
        return batch

    @torch.no_grad()
    def evaluate(
        self,
        policies: list[MurmPolicy],
        seeds: list[int],
        mask_p: float = 0.0,
        mask_mode: str = "paper",
        stop: Callable[[], bool] | None = None,
    ) -> list[EvalResult]:
        """Each policy's success on the episodes `seeds`, as if it were evaluated alone; the
        seconds are those of the whole evaluation, which they share. `stop` is asked before
        each batch of episodes: if it says so, `EvaluationStopped` (a trainer's Ctrl-C or
        SIGTERM then takes seconds, not the minutes an evaluation of hundreds of episodes takes)."""
        if len(policies) != self.policies:
            raise ValueError(f"this evaluator runs {self.policies} policies at a time, not {len(policies)}")
        start = time.perf_counter()
        device = next(policies[0].parameters()).device
        saved = [(p.training, p.config.eval_mask_p, p.config.eval_mask_mode) for p in policies]
        threads = torch.get_num_threads()
        torch.set_num_threads(1)  # the simulator processes need the other cores more
        for policy in policies:
            policy.eval()
            policy.config.eval_mask_p, policy.config.eval_mask_mode = mask_p, mask_mode
            policy.mask_generator.manual_seed(policy.config.eval_mask_seed)
        actors = torch.func.stack_module_state([p.actor for p in policies])
        successes: list[list[bool]] = [[] for _ in policies]
        try:
            for first in range(0, len(seeds), self.num_envs):
                if stop is not None and stop():
                    raise EvaluationStopped
                chunk = seeds[first : first + self.num_envs]
                padded = chunk + [chunk[-1]] * (self.num_envs - len(chunk))  # idle envs repeat a seed
                observation, _ = self.envs.reset(seed=padded * len(policies))
                succeeded = np.zeros(self.num_envs * len(policies), bool)
                # an episode's goal images stay as its reset rendered them (no episode ends early):
                # encoded once here, not at every step (the same latents, bit for bit)
                goals = policies[0].goal_state(self._batch(observation, device))
                for _ in range(EPISODE_STEPS):
                    batch = self._batch(observation, device, goals=False)
                    action = act_together(policies, batch, actors, goals).cpu().numpy()
                    if self.hold_succeeded:
                        action[succeeded] = np.nan  # HeldAfterSuccess: not simulated again
                    observation, _, _, _, info = self.envs.step(action)
                    succeeded |= np.asarray(info["is_success"], bool)
                for k, group in enumerate(succeeded.reshape(len(policies), self.num_envs)):
                    successes[k] += group[: len(chunk)].tolist()
        finally:
            torch.set_num_threads(threads)
            for policy, (training, old_p, old_mode) in zip(policies, saved, strict=True):
                policy.config.eval_mask_p, policy.config.eval_mask_mode = old_p, old_mode
                policy.train(training)
        seconds = time.perf_counter() - start
        return [EvalResult(self.task, mask_p, mask_mode, list(seeds), s, seconds) for s in successes]
