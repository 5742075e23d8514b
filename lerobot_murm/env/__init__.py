"""The MURM simulator: a Franka Panda in PyBullet with three tasks and five cameras."""

import gymnasium as gym

from lerobot_murm.env import bullet  # noqa: F401  (first: imports pybullet without its build-time line)
from lerobot_murm.env.cameras import CAMERA_NAMES
from lerobot_murm.env.murm_env import EPISODE_STEPS, MurmEnv
from lerobot_murm.env.tasks import TASK_NAMES

GYM_IDS: dict[str, str] = {
    "place_in_box": "murm/PlaceInBox-v0",
    "place_in_random_box": "murm/PlaceInRandomBox-v0",
    "pick_up": "murm/PickUp-v0",
}

for _task, _gym_id in GYM_IDS.items():
    if _gym_id not in gym.registry:
        gym.register(
            id=_gym_id,
            entry_point="lerobot_murm.env.murm_env:MurmEnv",
            max_episode_steps=EPISODE_STEPS,
            kwargs={"task": _task},
        )

__all__ = ["CAMERA_NAMES", "EPISODE_STEPS", "GYM_IDS", "TASK_NAMES", "MurmEnv"]
