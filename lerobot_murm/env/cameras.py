"""The five MURM cameras (paper 4.2), as the authors render them: every camera parameter lives here.

The paper gives no camera parameters; the authors' code does. Every value below is taken from
their 48x48 five-camera environment, JangSeongwon/MURM `murm_env_48/murm_env.py` at commit
a71d8b4b20b804793e60c2cf04a4633552a6ade9 (class MURMENV; lines cited per camera), rendered by
`envs/bullet/misc.py` at 02bcf6f208ed5dd811390aeb0b9fbd98cd8065c9 (projection l.144-147, blur
l.162-164):

- a view is `computeViewMatrixFromYawPitchRoll(target, distance, yaw, pitch, roll=0, up=z)`.
  Their code passes roll = angle - 270 for side, top, back and active, but it pins pybullet 2.5.5,
  which ignored roll (bullet3 648844e, PhysicsClientC_API.cpp `rollRad = 0.0`); the views their
  images came from had roll 0, so ours do too (a current pybullet would turn them);
- 60 degree field of view, near 0.1 m, far 5.5 m; images rendered at 48x48 by TinyRenderer with
  light direction (1, 1, 1) and no shadow, then `cv2.GaussianBlur(image, (5, 5), 0)`;
- the paper's "adjacent" view is the fixed camera their code calls `back` (`render_obs_back`):
  their code has no camera named adjacent, and `back` is its only fifth fixed view.

Their scene differs from ours by a rigid map plus a mirror: their robot stands at z = 1.0 on a
table whose top is at z = 0.9925, and their 3x3 boxes lie at x in {0.275, 0.4, 0.525},
y in {-0.25, -0.375, -0.5} (`run/objects.py` d828135, l.115-143), on the robot's right; ours stand
on the table top z = 0 with the boxes at x in {0.43, 0.555, 0.68}, y in {0.05, 0.175, 0.30}, on its
left. `from_authors_frame` maps their boxes exactly onto ours and their table top onto ours, so
every camera frames our tasks as theirs framed their tasks; the mirror makes our images the
mirror images of theirs, which changes nothing a policy can learn.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
import pybullet

FIELD_OF_VIEW_DEG = 60.0  # misc.py l.144 `fov=60` (the RealSense D435's 69 is not what their code renders)
NEAR_PLANE_M = 0.1  # misc.py l.144
FAR_PLANE_M = 5.5  # misc.py l.144
BLUR_KERNEL = 5  # misc.py l.162-164: cv2.GaussianBlur(img, (5, 5), 0), on every camera (murm_env.py l.562-636)
AUTHORS_LIGHT_DIRECTION = (1.0, 1.0, 1.0)  # murm_env.py l.562 `light_direction=[1, 1, 1]`
AUTHORS_TABLE_TOP_Z = 0.9925  # table.urdf at (0.2, 0, -0.57), scale 2.5 (run/objects.py l.56-59)
AUTHORS_TO_OURS_X = 0.155  # their box column x = 0.275 lands on ours at 0.43


def from_authors_frame(point) -> tuple[float, float, float]:
    """A point of the authors' scene in ours: x shifted, y mirrored about the box grids' centres
    (their -0.375 onto our 0.175), z from their table top to ours."""
    x, y, z = point
    return _rounded((x + AUTHORS_TO_OURS_X, -y - 0.2, z - AUTHORS_TABLE_TOP_Z))


def _mirror_vector(vector) -> tuple[float, float, float]:
    x, y, z = vector
    return _rounded((x, -y, z))


def _rounded(vector) -> tuple[float, float, float]:
    """Plain floats to the micrometre: pybullet's float32 view matrices carry no more."""
    return tuple(round(float(v), 6) + 0.0 for v in vector)


def _authors_eye_and_up(target, distance: float, yaw: float, pitch: float) -> tuple[np.ndarray, np.ndarray]:
    """Eye and image-up of pybullet's yaw/pitch camera (roll 0, z up), in the authors' frame:
    read back from the view matrix pybullet itself builds, so the convention is pybullet's own."""
    view = np.asarray(pybullet.computeViewMatrixFromYawPitchRoll(list(target), distance, yaw, pitch, 0.0, 2))
    rotation_translation = view.reshape(4, 4).T  # pybullet returns it column-major
    rotation, translation = rotation_translation[:3, :3], rotation_translation[:3, 3]
    eye = -rotation.T @ translation
    return eye, rotation[1]


@dataclass(frozen=True)
class FixedCamera:
    """A camera fixed to the world at `eye`, looking at `target`; `up` is the image's up."""

    eye: tuple[float, float, float]
    target: tuple[float, float, float]
    up: tuple[float, float, float] = (0.0, 0.0, 1.0)

    @classmethod
    def from_authors(cls, target, distance: float, yaw: float, pitch: float) -> FixedCamera:
        """The authors' `get_view_matrix(target, distance, yaw, pitch)`, moved into our scene."""
        eye, up = _authors_eye_and_up(target, distance, yaw, pitch)
        return cls(eye=from_authors_frame(eye), target=from_authors_frame(target), up=_mirror_vector(up))

    def view_matrix(self) -> tuple[float, ...]:
        return pybullet.computeViewMatrix(self.eye, self.target, self.up)


@dataclass(frozen=True)
class EndEffectorCamera:
    """A camera that moves with the hand: it looks at a point `target_offset` from the
    end-effector from `distance` along `direction` (unit, world frame).

    The authors aim it at the end-effector + 0.085 m along world x, from 0.2 m, with yaw and
    pitch taken from the hand's Euler angles (murm_env.py l.569-585). Their IK and ours hold the
    hand at Euler (pi, 0, 0), so those angles are constant (yaw 180, pitch -90: straight down,
    image-up along their -y) and fixed world-frame offsets reproduce the camera exactly.
    """

    target_offset: tuple[float, float, float]
    eye_offset: tuple[float, float, float]
    up: tuple[float, float, float]

    @classmethod
    def from_authors(cls, target_offset, distance: float, yaw: float, pitch: float) -> EndEffectorCamera:
        eye, up = _authors_eye_and_up((0.0, 0.0, 0.0), distance, yaw, pitch)
        return cls(target_offset=_mirror_vector(target_offset), eye_offset=_mirror_vector(eye), up=_mirror_vector(up))

    def view_matrix(self, ee_position: np.ndarray) -> tuple[float, ...]:
        target = np.asarray(ee_position) + np.asarray(self.target_offset)
        eye = target + np.asarray(self.eye_offset)
        return pybullet.computeViewMatrix(eye.tolist(), target.tolist(), list(self.up))


CAMERAS: dict[str, FixedCamera | EndEffectorCamera] = {
    # render_obs, l.556-563: in front of the robot, 0.41 m above the table, looking back at it 25 deg down
    "global": FixedCamera.from_authors(target=(1.0, -0.22, 1.4), distance=0.01, yaw=90, pitch=-25),
    # render_obs_back, l.625-638: above the robot's base, looking out over the boxes 45 deg down
    "adjacent": FixedCamera.from_authors(target=(0.15, -0.375, 1.3), distance=0.2, yaw=-90, pitch=45 - 90),
    # render_obs_side, l.590-602: beyond the boxes, looking across them at the robot 15 deg down
    "side": FixedCamera.from_authors(target=(0.4, -0.8, 1.3), distance=0.2, yaw=0, pitch=75 - 90),
    # render_obs_top, l.607-620: straight down from 0.76 m over the middle of the workspace
    "top": FixedCamera.from_authors(target=(0.4, -0.2, 1.6), distance=0.15, yaw=0, pitch=0 - 90),
    # render_obs_active, l.569-585: 0.2 m above a point 8.5 cm ahead of the fingers, looking down
    "active": EndEffectorCamera.from_authors(target_offset=(0.085, 0.0, 0.0), distance=0.2, yaw=180, pitch=0 - 90),
}

CAMERA_NAMES: tuple[str, ...] = tuple(CAMERAS)
LIGHT_DIRECTION = _mirror_vector(AUTHORS_LIGHT_DIRECTION)


def projection_matrix(aspect: float = 1.0) -> tuple[float, ...]:
    return pybullet.computeProjectionMatrixFOV(FIELD_OF_VIEW_DEG, aspect, NEAR_PLANE_M, FAR_PLANE_M)


def validate_camera_names(names: tuple[str, ...] | list[str]) -> tuple[str, ...]:
    """Return `names` as a tuple, or raise a ValueError naming the valid cameras."""
    names = tuple(names)
    if not names:
        raise ValueError(f"at least one camera is required; valid cameras: {list(CAMERA_NAMES)}")
    unknown = [name for name in names if name not in CAMERAS]
    if unknown:
        raise ValueError(f"unknown camera(s) {unknown}; valid cameras: {list(CAMERA_NAMES)}")
    if len(set(names)) != len(names):
        raise ValueError(f"camera names must be unique, got {list(names)}")
    return names


def blur(image: np.ndarray) -> np.ndarray:
    """The authors' blur: OpenCV's 5x5 Gaussian with sigma from the size (its fixed binomial
    kernel [1, 4, 6, 4, 1] / 16), reflected borders; deterministic integer arithmetic."""
    return cv2.GaussianBlur(image, (BLUR_KERNEL, BLUR_KERNEL), 0)


class CameraRig:
    """Renders a set of cameras of one PyBullet client into HxWx3 uint8 arrays.

    `blurred` applies the authors' blur, as every observation and goal image has it; the larger
    overview of rollout videos is rendered sharp (a 5-pixel blur is a property of 48x48 images)."""

    def __init__(self, client, names: tuple[str, ...], image_size: int, blurred: bool = True):
        self._client = client
        self.names = validate_camera_names(names)
        self.image_size = image_size
        self.blurred = blurred
        self._projection = projection_matrix()
        self._fixed_views = {
            name: CAMERAS[name].view_matrix() for name in self.names if isinstance(CAMERAS[name], FixedCamera)
        }

    def render_all(self, ee_position: np.ndarray) -> dict[str, np.ndarray]:
        return {name: self.render(name, ee_position) for name in self.names}

    def render(self, name: str, ee_position: np.ndarray, size: int | None = None) -> np.ndarray:
        rgb = render_view(self._client, self._view(name, ee_position), self._projection, size or self.image_size)
        return blur(rgb) if self.blurred else rgb

    def render_with_mask(self, name: str, ee_position: np.ndarray, body: int) -> tuple[np.ndarray, np.ndarray]:
        """The camera's image and an HxW bool mask of the pixels where `body` is visible."""
        rgb, segmentation = render_segmented_view(
            self._client, self._view(name, ee_position), self._projection, self.image_size
        )
        return (blur(rgb) if self.blurred else rgb), segmentation == body

    def _view(self, name: str, ee_position: np.ndarray) -> tuple[float, ...]:
        return self._fixed_views.get(name) or CAMERAS[name].view_matrix(ee_position)


def render_view(client, view_matrix, projection, size: int) -> np.ndarray:
    """One TinyRenderer image as an HxWx3 uint8 array (no segmentation mask: it costs time)."""
    return _tiny_render(client, view_matrix, projection, size, pybullet.ER_NO_SEGMENTATION_MASK)[0]


def render_segmented_view(client, view_matrix, projection, size: int) -> tuple[np.ndarray, np.ndarray]:
    """The image of `render_view` and its HxW segmentation buffer (the body id seen at each
    pixel, -1 for none), for checks; observations use `render_view` and skip the mask."""
    return _tiny_render(client, view_matrix, projection, size, 0)


def _tiny_render(client, view_matrix, projection, size: int, flags: int) -> tuple[np.ndarray, np.ndarray | None]:
    _, _, rgba, _, segmentation = client.getCameraImage(
        width=size,
        height=size,
        viewMatrix=view_matrix,
        projectionMatrix=projection,
        renderer=pybullet.ER_TINY_RENDERER,
        flags=flags,
        shadow=0,
        lightDirection=LIGHT_DIRECTION,
    )
    rgb = np.asarray(rgba, dtype=np.uint8).reshape(size, size, 4)[:, :, :3].copy()
    masked = flags & pybullet.ER_NO_SEGMENTATION_MASK
    return rgb, None if masked else np.asarray(segmentation, dtype=np.int64).reshape(size, size)
