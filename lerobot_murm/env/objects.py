"""Primitive bodies the scenes are built from: table, trays, pedestals and graspable shapes.

Everything is made of PyBullet primitives (boxes, cylinders) rather than mesh files:
they render in a fraction of a millisecond with TinyRenderer and need no assets.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pybullet

TABLE_RGBA = (0.72, 0.58, 0.42, 1.0)
TRAY_RGBA = (0.35, 0.45, 0.75, 1.0)
PEDESTAL_RGBA = (0.55, 0.55, 0.55, 1.0)

TRAY_INNER = 0.10  # paper 4.1: a square box with 10 cm width
TRAY_WALL = 0.008
TRAY_WALL_HEIGHT = 0.03
TRAY_FLOOR = 0.006


def create_table(client) -> int:
    """A 2 m x 2 m slab whose top face is the plane z = 0 (the robot stands on it)."""
    half = [1.0, 1.0, 0.02]
    col = client.createCollisionShape(pybullet.GEOM_BOX, halfExtents=half)
    vis = client.createVisualShape(pybullet.GEOM_BOX, halfExtents=half, rgbaColor=TABLE_RGBA)
    body = client.createMultiBody(0, col, vis, basePosition=[0.5, 0.0, -0.02])
    client.changeDynamics(body, -1, lateralFriction=1.0)
    return body


def create_tray(client, centre: np.ndarray, rgba=TRAY_RGBA) -> int:
    """A static open box: `centre` is the middle of its floor's top face."""
    inner, wall, height, floor = TRAY_INNER, TRAY_WALL, TRAY_WALL_HEIGHT, TRAY_FLOOR
    outer_half = inner / 2 + wall
    parts = [  # (half extents, offset from the floor's top-face centre)
        ([outer_half, outer_half, floor / 2], [0, 0, -floor / 2]),
        ([wall / 2, outer_half, height / 2], [inner / 2 + wall / 2, 0, height / 2]),
        ([wall / 2, outer_half, height / 2], [-inner / 2 - wall / 2, 0, height / 2]),
        ([inner / 2, wall / 2, height / 2], [0, inner / 2 + wall / 2, height / 2]),
        ([inner / 2, wall / 2, height / 2], [0, -inner / 2 - wall / 2, height / 2]),
    ]
    halves = [p[0] for p in parts]
    offsets = [p[1] for p in parts]
    col = client.createCollisionShapeArray(
        shapeTypes=[pybullet.GEOM_BOX] * len(parts), halfExtents=halves, collisionFramePositions=offsets
    )
    vis = client.createVisualShapeArray(
        shapeTypes=[pybullet.GEOM_BOX] * len(parts),
        halfExtents=halves,
        visualFramePositions=offsets,
        rgbaColors=[rgba] * len(parts),
    )
    return client.createMultiBody(0, col, vis, basePosition=list(centre))


def create_pedestal(client, top_centre: np.ndarray, half_width: float) -> int:
    """A static column from the table up to `top_centre` (under a raised tray)."""
    height = float(top_centre[2])
    half = [half_width, half_width, height / 2]
    col = client.createCollisionShape(pybullet.GEOM_BOX, halfExtents=half)
    vis = client.createVisualShape(pybullet.GEOM_BOX, halfExtents=half, rgbaColor=PEDESTAL_RGBA)
    centre = [float(top_centre[0]), float(top_centre[1]), height / 2]
    return client.createMultiBody(0, col, vis, basePosition=centre)


@dataclass(frozen=True)
class Shape:
    """A graspable object: `half_height` is the distance from its centre to the table."""

    name: str
    geometry: int
    size: tuple[float, ...]  # half extents for boxes, (radius, height) for cylinders
    half_height: float


SHAPES: dict[str, Shape] = {
    "cube": Shape("cube", pybullet.GEOM_BOX, (0.02, 0.02, 0.02), 0.02),
    "cuboid": Shape("cuboid", pybullet.GEOM_BOX, (0.035, 0.018, 0.018), 0.018),
    "cylinder": Shape("cylinder", pybullet.GEOM_CYLINDER, (0.02, 0.045), 0.0225),
    "flat_box": Shape("flat_box", pybullet.GEOM_BOX, (0.025, 0.025, 0.012), 0.012),
}

OBJECT_COLOURS = {
    "red": (0.85, 0.15, 0.12, 1.0),
    "green": (0.15, 0.7, 0.2, 1.0),
    "yellow": (0.95, 0.8, 0.1, 1.0),
    "purple": (0.6, 0.2, 0.7, 1.0),
}


def create_object(client, shape: Shape, position: np.ndarray, yaw: float, rgba, mass: float = 0.08) -> int:
    if shape.geometry == pybullet.GEOM_BOX:
        col = client.createCollisionShape(pybullet.GEOM_BOX, halfExtents=shape.size)
        vis = client.createVisualShape(pybullet.GEOM_BOX, halfExtents=shape.size, rgbaColor=rgba)
    else:
        radius, length = shape.size
        col = client.createCollisionShape(pybullet.GEOM_CYLINDER, radius=radius, height=length)
        vis = client.createVisualShape(pybullet.GEOM_CYLINDER, radius=radius, length=length, rgbaColor=rgba)
    orientation = pybullet.getQuaternionFromEuler([0.0, 0.0, yaw])
    body = client.createMultiBody(mass, col, vis, basePosition=list(position), baseOrientation=orientation)
    client.changeDynamics(body, -1, lateralFriction=1.2, spinningFriction=0.002, rollingFriction=0.0005)
    return body


def body_position(client, body: int) -> np.ndarray:
    return np.asarray(client.getBasePositionAndOrientation(body)[0], dtype=np.float64)
