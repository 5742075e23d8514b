"""The five MURM cameras (paper 4.2): every camera parameter lives in this module.

Four cameras are fixed to the world and described by pybullet's yaw/pitch/distance
convention around a target point on the table; the `active` camera rides on the
end-effector (the gripper always points down with a fixed yaw, so a world-frame
offset from the end-effector is the same as a hand-frame offset).

All cameras use a 69 degree vertical field of view (an Intel RealSense D435, as in
the authors' set-up) and render with PyBullet's CPU TinyRenderer, which gives the
same pixels on every machine.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pybullet

FIELD_OF_VIEW_DEG = 69.0
NEAR_PLANE_M = 0.01
FAR_PLANE_M = 5.0


@dataclass(frozen=True)
class FixedCamera:
    """A camera fixed to the world at `eye`, looking at `target`; `up` is the image's up."""

    eye: tuple[float, float, float]
    target: tuple[float, float, float]
    up: tuple[float, float, float] = (0.0, 0.0, 1.0)

    def view_matrix(self) -> tuple[float, ...]:
        return pybullet.computeViewMatrix(self.eye, self.target, self.up)


@dataclass(frozen=True)
class EndEffectorCamera:
    """A camera mounted on the hand: eye and target are offsets from the end-effector.

    The eye sits a little behind and above the fingers (never on a joint origin, where
    TinyRenderer is known to hang) and looks down-forward past the fingertips.
    """

    eye_offset: tuple[float, float, float]
    target_offset: tuple[float, float, float]

    def view_matrix(self, ee_position: np.ndarray) -> tuple[float, ...]:
        eye = np.asarray(ee_position) + np.asarray(self.eye_offset)
        target = np.asarray(ee_position) + np.asarray(self.target_offset)
        return pybullet.computeViewMatrix(eye.tolist(), target.tolist(), [1.0, 0.0, 0.0])


CAMERAS: dict[str, FixedCamera | EndEffectorCamera] = {
    # In front of the robot, facing it from above the table edge: the whole workspace and arm.
    "global": FixedCamera(eye=(0.95, 0.03, 0.42), target=(0.50, 0.03, 0.0)),
    # The global camera swung 45 degrees round the workspace: sees depth the global view flattens.
    "adjacent": FixedCamera(eye=(0.82, 0.40, 0.42), target=(0.50, 0.03, 0.0)),
    # From the robot's right, low over the table: heights are easy to read.
    "side": FixedCamera(eye=(0.56, -0.58, 0.20), target=(0.56, 0.05, 0.03)),
    # Above the table, 0.64 m up and tilted 24 degrees from vertical towards the robot, which
    # hangs in from the top of the image: the whole tray grid, the spawn strip and the hand,
    # a 4 cm cube 2-3 pixels across. (It was straight down from 0.95 m: the cube was about
    # one pixel and the arm hid it, so top-view policies failed on every task.)
    "top": FixedCamera(eye=(0.80, 0.03, 0.64), target=(0.52, 0.03, 0.0), up=(-1.0, 0.0, 0.0)),
    # On the hand, 10 cm ahead of the fingers, looking down and back at the grasp.
    "active": EndEffectorCamera(eye_offset=(0.10, 0.0, 0.08), target_offset=(0.02, 0.0, -0.14)),
}

CAMERA_NAMES: tuple[str, ...] = tuple(CAMERAS)


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


class CameraRig:
    """Renders a set of cameras of one PyBullet client into HxWx3 uint8 arrays."""

    def __init__(self, client, names: tuple[str, ...], image_size: int):
        self._client = client
        self.names = validate_camera_names(names)
        self.image_size = image_size
        self._projection = projection_matrix()
        self._fixed_views = {
            name: CAMERAS[name].view_matrix() for name in self.names if isinstance(CAMERAS[name], FixedCamera)
        }

    def render_all(self, ee_position: np.ndarray) -> dict[str, np.ndarray]:
        return {name: self.render(name, ee_position) for name in self.names}

    def render(self, name: str, ee_position: np.ndarray, size: int | None = None) -> np.ndarray:
        return render_view(self._client, self._view(name, ee_position), self._projection, size or self.image_size)

    def render_with_mask(self, name: str, ee_position: np.ndarray, body: int) -> tuple[np.ndarray, np.ndarray]:
        """The camera's image and an HxW bool mask of the pixels where `body` is visible."""
        rgb, segmentation = render_segmented_view(self._client, self._view(name, ee_position), self._projection,
                                                  self.image_size)
        return rgb, segmentation == body

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
    )
    rgb = np.asarray(rgba, dtype=np.uint8).reshape(size, size, 4)[:, :, :3].copy()
    masked = flags & pybullet.ER_NO_SEGMENTATION_MASK
    return rgb, None if masked else np.asarray(segmentation, dtype=np.int64).reshape(size, size)
