"""`MurmEnv`: the gymnasium environment tying robot, task and cameras together.

Observations follow LeRobot's env convention so that `lerobot-eval` maps them
without help: `pixels` holds one HxWx3 uint8 image per camera and, under
`<camera>_goal`, that camera's goal image; `agent_pos` is the robot state and
`environment_state` the privileged object and goal positions (used by the expert,
recorded in the dataset, never by the learned policy).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, ClassVar

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from lerobot_murm.env import bullet, objects
from lerobot_murm.env.cameras import CAMERA_NAMES, CameraRig, validate_camera_names
from lerobot_murm.env.robot import MAX_FINGER_WIDTH, Panda
from lerobot_murm.env.tasks import WORKSPACE_HIGH, WORKSPACE_LOW, make_task
from lerobot_murm.env.video_frame import compose_frame, tile_size
from lerobot_murm.features import goal_key

PHYSICS_TIMESTEP = 1.0 / 240.0
SUBSTEPS = 10
CONTROL_FPS = round(1.0 / (PHYSICS_TIMESTEP * SUBSTEPS))  # 24 Hz
MAX_STEP_M = 0.025  # end-effector displacement for an action of 1 along an axis
EPISODE_STEPS = 100
# Bumped whenever a camera or the scene changes (2: the top camera moved; 3: the authors'
# cameras and blur), so that datasets rendered by another version are neither resumed nor reused.
SCENE_VERSION = 3
HOME_EE_POSITION = np.array([0.45, 0.0, 0.22])
HOME_JITTER_M = 0.02
SETTLE_SUBSTEPS = 20
STATE_DIM = 4  # end-effector xyz, finger opening
ENV_STATE_DIM = 6  # object xyz, goal xyz
MIN_IMAGE_SIZE, MAX_IMAGE_SIZE = 8, 512
WORLD_LIMIT_M = 3.0  # bound of object coordinates; the table is 2 m wide
TASK_DESCRIPTIONS = {
    "place_in_box": "put the cube into the box shown in the goal images",
    "place_in_random_box": "put the cube into the box shown in the goal images",
    "pick_up": "pick up the object that is lifted in the goal images",
}


class MurmEnv(gym.Env):
    """Franka Panda, 4-DoF end-effector control, one of three MURM tasks, five cameras."""

    metadata: ClassVar[dict[str, Any]] = {"render_modes": ["rgb_array"], "render_fps": CONTROL_FPS}

    def __init__(
        self,
        task: str = "place_in_box",
        cameras: tuple[str, ...] | list[str] = CAMERA_NAMES,
        image_size: int = 48,
        goal_images: bool = True,
        render_mode: str | None = "rgb_array",
        render_size: int = 256,
        render_views: bool = True,
        lowpoly_robot: bool = True,
    ):
        super().__init__()
        make_task(task)  # fail early, with the valid names, on an unknown task
        self.validate_image_size(image_size)
        if render_mode not in (None, "rgb_array"):
            raise ValueError(f"render_mode must be 'rgb_array' or None, got {render_mode!r}")
        self.task_name = task
        self.cameras = validate_camera_names(cameras)
        self.image_size = int(image_size)
        self.goal_images = goal_images
        self.render_mode = render_mode
        self.render_size = render_size
        self.render_views = render_views
        self.lowpoly_robot = lowpoly_robot

        image_space = spaces.Box(0, 255, (self.image_size, self.image_size, 3), np.uint8)
        pixel_spaces = dict.fromkeys(self.cameras, image_space)
        if goal_images:
            pixel_spaces |= {goal_key(name): image_space for name in self.cameras}
        self.observation_space = spaces.Dict(
            {
                "pixels": spaces.Dict(pixel_spaces),
                "agent_pos": spaces.Box(
                    np.append(WORKSPACE_LOW - 0.05, 0.0).astype(np.float32),
                    np.append(WORKSPACE_HIGH + 0.05, MAX_FINGER_WIDTH + 0.01).astype(np.float32),
                ),
                "environment_state": spaces.Box(-WORLD_LIMIT_M, WORLD_LIMIT_M, (ENV_STATE_DIM,), np.float32),
            }
        )
        self.action_space = spaces.Box(-1.0, 1.0, (4,), np.float32)

        self._client = bullet.connect()
        self._rig = CameraRig(self._client, self.cameras, self.image_size)
        self._overview = CameraRig(self._client, ("global",), self.render_size, blurred=False)
        self._task = make_task(task)
        self._robot: Panda | None = None
        self._goal_pixels: dict[str, np.ndarray] = {}
        self._pixels: dict[str, np.ndarray] = {}  # the last observation's images, for render()

    @staticmethod
    def validate_image_size(image_size) -> None:
        valid = isinstance(image_size, int | np.integer) and not isinstance(image_size, bool)
        if not valid or not MIN_IMAGE_SIZE <= image_size <= MAX_IMAGE_SIZE:
            raise ValueError(
                f"image_size must be an integer in [{MIN_IMAGE_SIZE}, {MAX_IMAGE_SIZE}] (MURM uses 48), "
                f"got {image_size!r}"
            )

    # --- gymnasium API -------------------------------------------------------------------
    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None):
        super().reset(seed=seed)
        client = self._client
        client.resetSimulation()
        client.setGravity(0, 0, -9.81)
        client.setTimeStep(PHYSICS_TIMESTEP)
        objects.create_table(client)
        self._robot = Panda(client, lowpoly=self.lowpoly_robot)
        self._robot.reset_to_rest()
        self._task = make_task(self.task_name)
        self._task.build(client, self.np_random)
        home = HOME_EE_POSITION + self.np_random.uniform(-HOME_JITTER_M, HOME_JITTER_M, size=3)
        self._robot.teleport(home, MAX_FINGER_WIDTH)
        self._robot.hold(close_gripper=False)
        for _ in range(SETTLE_SUBSTEPS):
            client.stepSimulation()
        self._goal_pixels = self._render_goal() if self.goal_images else {}
        return self._observation(), {"is_success": False}

    def step(self, action):
        if self._robot is None:
            raise RuntimeError("call reset() before step()")
        action = np.asarray(action, dtype=np.float64)
        if action.shape != (4,):
            raise ValueError(f"action must have shape (4,) = (dx, dy, dz, gripper), got {action.shape}")
        if not np.all(np.isfinite(action)):
            raise ValueError(f"action must be finite, got {action.tolist()}")
        action = np.clip(action, -1.0, 1.0)
        target = np.clip(self._robot.ee_position() + action[:3] * MAX_STEP_M, WORKSPACE_LOW, WORKSPACE_HIGH)
        self._robot.command(target, close_gripper=bool(action[3] > 0))
        for _ in range(SUBSTEPS):
            self._client.stepSimulation()
        success = self._task.is_success(self._client)
        return self._observation(), float(success), False, False, {"is_success": success}

    def render(self) -> np.ndarray | None:
        """The frame of rollout videos: a larger view from the global camera and, with `render_views`,
        beside it each camera's last observed image above its goal image (see `video_frame`)."""
        if self.render_mode is None:
            return None
        if not self.render_views or not self._pixels:
            return self._overview.render("global", self._ee_position())
        overview = self._overview.render("global", self._ee_position(), size=2 * tile_size(self.render_size))
        views = {name: self._pixels[name] for name in self.cameras}
        goals = {name: self._pixels[goal_key(name)] for name in self.cameras if goal_key(name) in self._pixels}
        return compose_frame(overview, views, goals)

    def close(self) -> None:
        if getattr(self, "_client", None) is not None:
            self._client.disconnect()
            self._client = None

    # --- LeRobot hooks -----------------------------------------------------------------
    @property
    def task_description(self) -> str:
        return TASK_DESCRIPTIONS[self.task_name]

    # --- internals ---------------------------------------------------------------------
    def _ee_position(self) -> np.ndarray:
        return self._robot.ee_position() if self._robot is not None else HOME_EE_POSITION

    def _render_goal(self) -> dict[str, np.ndarray]:
        images = self._at_goal(self._rig.render_all)
        return {goal_key(name): image for name, image in images.items()}

    def _at_goal(self, render: Callable[[np.ndarray], dict]) -> dict:
        """Move object and hand to the goal, call `render(ee_position)`, restore the scene exactly."""
        client, task = self._client, self._task
        snapshot = client.saveState()
        orientation = client.getBasePositionAndOrientation(task.object_body)[1]
        client.resetBasePositionAndOrientation(task.object_body, task.goal_position.tolist(), orientation)
        self._robot.teleport(task.goal_ee_position(), task.goal_finger_width())
        images = render(self._robot.ee_position())
        client.restoreState(snapshot)
        client.removeState(snapshot)
        return images

    def object_views(self, at_goal: bool = False) -> dict[str, tuple[np.ndarray, np.ndarray]]:
        """Per camera, the image of the current scene (or of the goal scene) and the mask of the
        task's object in it, from the segmentation buffer. A render of its own, for checking
        what an encoder keeps of the object; observations never pay for it."""
        if self._robot is None:
            raise RuntimeError("call reset() before object_views()")

        def render(ee_position: np.ndarray) -> dict:
            body = self._task.object_body
            return {name: self._rig.render_with_mask(name, ee_position, body) for name in self.cameras}

        return self._at_goal(render) if at_goal else render(self._robot.ee_position())

    def _observation(self) -> dict[str, Any]:
        ee = self._robot.ee_position()
        pixels = self._rig.render_all(ee) | {k: v.copy() for k, v in self._goal_pixels.items()}
        self._pixels = pixels
        agent_pos = np.append(ee, self._robot.finger_width()).astype(np.float32)
        env_state = np.concatenate([self._task.object_position(self._client), self._task.goal_position])
        return {"pixels": pixels, "agent_pos": agent_pos, "environment_state": env_state.astype(np.float32)}

    # Privileged accessors for the scripted expert and the tests.
    @property
    def task(self):
        return self._task

    @property
    def robot(self) -> Panda:
        return self._robot

    @property
    def client(self):
        return self._client
