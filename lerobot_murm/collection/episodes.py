"""One demonstration episode, fully determined by (base seed, episode index) and the recipe.

`run_episode` is what a collection worker runs: it needs no shared state, so the
dataset is the same whatever the number of workers.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from lerobot_murm.env import EPISODE_STEPS, MurmEnv
from lerobot_murm.env.murm_env import SCENE_VERSION
from lerobot_murm.expert import PAPER_NOISE_STD, ScriptedExpert, noisy_action
from lerobot_murm.features import goal_key


@dataclass(frozen=True)
class EpisodeRecipe:
    """How every episode of a collection is made."""

    task: str
    cameras: tuple[str, ...]
    image_size: int = 48
    base_seed: int = 0
    noisy_fraction: float = 1.0  # share of episodes with noise (Table 7 varies it)
    # the noise's scale, the one knob: paper 4.1's a = clip(a* + k N(0, 0.1), -1, 1) is
    # a = clip(a* + N(0, noise_std), -1, 1) with noise_std = 0.1 k; the collections use the
    # per-task calibrated std (recipes stored with a separate `noise_k` read as k * noise_std)
    noise_std: float = PAPER_NOISE_STD
    scene: int = SCENE_VERSION  # the simulator's scene and camera version the episodes were rendered in

    def episode_start(self, index: int) -> tuple[int, bool, np.random.Generator]:
        """Episode `index`'s env seed, whether it is noisy, and the generator of its noise:
        from base seed and index alone.

        The flag is the generator's first draw, so the noise that follows does not depend
        on the noisy fraction: a noisy episode is the same at any fraction, and so is a
        clean one (`donors.py` builds on this)."""
        sequence = np.random.SeedSequence([self.base_seed, index])
        env_seed = int(sequence.generate_state(1)[0])
        rng = np.random.default_rng(sequence.spawn(1)[0])
        return env_seed, bool(rng.random() < self.noisy_fraction), rng


@dataclass
class Episode:
    index: int
    env_seed: int
    noisy: bool
    images: dict[str, np.ndarray]  # camera -> (T, H, W, 3) uint8
    goal_images: dict[str, np.ndarray]  # camera -> (H, W, 3) uint8
    state: np.ndarray  # (T, 4)
    environment_state: np.ndarray  # (T, 6)
    action: np.ndarray  # (T, 4)
    success: np.ndarray  # (T,) task success after each action

    @property
    def succeeded(self) -> bool:
        """Success at any step, the rule lerobot-eval applies."""
        return bool(self.success.any())


_ENV_CACHE: dict[tuple, MurmEnv] = {}


def _env_for(recipe: EpisodeRecipe) -> MurmEnv:
    """One simulator per process, reused across episodes (reset rebuilds the scene)."""
    key = (recipe.task, recipe.cameras, recipe.image_size)
    if key not in _ENV_CACHE:
        _ENV_CACHE[key] = MurmEnv(task=recipe.task, cameras=recipe.cameras, image_size=recipe.image_size)
    return _ENV_CACHE[key]


def run_episode(recipe: EpisodeRecipe, index: int, observe: Callable[[MurmEnv, int], None] | None = None) -> Episode:
    """`observe(env, t)`, if given, sees the simulator in the state of each recorded frame t
    (the encoders' object check renders masks of exactly the dataset's frames with it)."""
    env_seed, noisy, rng = recipe.episode_start(index)
    env = _env_for(recipe)
    expert = ScriptedExpert(recipe.task)
    obs, _ = env.reset(seed=env_seed)
    images = {c: np.empty((EPISODE_STEPS, recipe.image_size, recipe.image_size, 3), np.uint8) for c in recipe.cameras}
    goal_images = {c: obs["pixels"][goal_key(c)] for c in recipe.cameras}
    state = np.empty((EPISODE_STEPS, 4), np.float32)
    environment_state = np.empty((EPISODE_STEPS, 6), np.float32)
    action = np.empty((EPISODE_STEPS, 4), np.float32)
    success = np.empty(EPISODE_STEPS, bool)
    for t in range(EPISODE_STEPS):
        for camera in recipe.cameras:
            images[camera][t] = obs["pixels"][camera]
        state[t], environment_state[t] = obs["agent_pos"], obs["environment_state"]
        if observe is not None:
            observe(env, t)
        act = expert.act(obs)
        if noisy:
            act = noisy_action(act, rng, recipe.noise_std)
        action[t] = act
        obs, _, _, _, info = env.step(act)
        success[t] = info["is_success"]
    return Episode(index, env_seed, noisy, images, goal_images, state, environment_state, action, success)
