"""LeRobot env type `murm`: `lerobot-eval --env.type=murm --env.task=place_in_box ...`."""

from __future__ import annotations

from dataclasses import dataclass, field

from lerobot.configs import FeatureType, PolicyFeature
from lerobot.envs.configs import EnvConfig
from lerobot.utils.constants import ACTION, OBS_IMAGES, OBS_STATE

from lerobot_murm.env import GYM_IDS
from lerobot_murm.env.cameras import CAMERA_NAMES, validate_camera_names
from lerobot_murm.env.murm_env import CONTROL_FPS, EPISODE_STEPS, STATE_DIM, MurmEnv
from lerobot_murm.env.tasks import TASK_NAMES
from lerobot_murm.features import goal_key


@EnvConfig.register_subclass("murm")
@dataclass
class MurmEnvConfig(EnvConfig):
    """The MURM simulator as seen by LeRobot: which task, which cameras, what image size."""

    task: str = "place_in_box"
    fps: int = CONTROL_FPS
    episode_length: int = EPISODE_STEPS
    cameras: list[str] = field(default_factory=lambda: list(CAMERA_NAMES))
    image_size: int = 48
    goal_images: bool = True
    render_size: int = 256
    # Videos show each camera's image above its goal image beside the render (false: the render alone).
    render_views: bool = True

    def __post_init__(self) -> None:
        if self.task not in TASK_NAMES:
            raise ValueError(f"unknown task {self.task!r}; valid tasks: {list(TASK_NAMES)}")
        self.cameras = list(validate_camera_names(self.cameras))
        MurmEnv.validate_image_size(self.image_size)
        image = PolicyFeature(type=FeatureType.VISUAL, shape=(self.image_size, self.image_size, 3))
        names = self.cameras + ([goal_key(c) for c in self.cameras] if self.goal_images else [])
        self.features = {
            ACTION: PolicyFeature(type=FeatureType.ACTION, shape=(4,)),
            "agent_pos": PolicyFeature(type=FeatureType.STATE, shape=(STATE_DIM,)),
            **{f"pixels/{name}": image for name in names},
        }
        self.features_map = {
            ACTION: ACTION,
            "agent_pos": OBS_STATE,
            **{f"pixels/{name}": f"{OBS_IMAGES}.{name}" for name in names},
        }

    @property
    def package_name(self) -> str:
        return "lerobot_murm.env"

    @property
    def gym_id(self) -> str:
        return GYM_IDS[self.task]

    @property
    def gym_kwargs(self) -> dict:
        return {
            "cameras": tuple(self.cameras),
            "image_size": self.image_size,
            "goal_images": self.goal_images,
            "render_size": self.render_size,
            "render_views": self.render_views,
            "max_episode_steps": self.episode_length,
        }
