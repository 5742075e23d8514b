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
    """A static open box: `centre` is the middle of its floor's top face.

    Collision is five boxes; the visual is one mesh of the 26 triangles a viewer can
    see (a box-per-wall visual has 60), which matters because the CPU renderer's cost
    grows with triangles and nine trays are on screen in `place_in_box`.
    """
    inner, wall, height, floor = TRAY_INNER, TRAY_WALL, TRAY_WALL_HEIGHT, TRAY_FLOOR
    outer_half = inner / 2 + wall
    parts = [  # (half extents, offset from the floor's top-face centre)
        ([outer_half, outer_half, floor / 2], [0, 0, -floor / 2]),
        ([wall / 2, outer_half, height / 2], [inner / 2 + wall / 2, 0, height / 2]),
        ([wall / 2, outer_half, height / 2], [-inner / 2 - wall / 2, 0, height / 2]),
        ([inner / 2, wall / 2, height / 2], [0, inner / 2 + wall / 2, height / 2]),
        ([inner / 2, wall / 2, height / 2], [0, -inner / 2 - wall / 2, height / 2]),
    ]
    col = client.createCollisionShapeArray(
        shapeTypes=[pybullet.GEOM_BOX] * len(parts),
        halfExtents=[p[0] for p in parts],
        collisionFramePositions=[p[1] for p in parts],
    )
    vertices, normals, indices = _tray_mesh(inner / 2, outer_half, height, floor)
    vis = client.createVisualShape(
        pybullet.GEOM_MESH, vertices=vertices, normals=normals, indices=indices, rgbaColor=rgba
    )
    return client.createMultiBody(0, col, vis, basePosition=list(centre))


def _tray_mesh(i: float, o: float, h: float, f: float) -> tuple[list[list[float]], list[list[float]], list[int]]:
    """Floor top, and per side: outer face, inner face and rim top, each facing outwards."""
    up, inward, outward = (0, 0, 1), (-1, 0, 0), (1, 0, 0)
    side = [  # the +x side; the other three are it turned about z
        ([(o, -o, -f), (o, o, -f), (o, o, h), (o, -o, h)], outward),
        ([(i, -i, 0), (i, i, 0), (i, i, h), (i, -i, h)], inward),
        ([(i, -i, h), (o, -o, h), (o, o, h), (i, i, h)], up),
    ]
    quads = [([(-i, -i, 0), (i, -i, 0), (i, i, 0), (-i, i, 0)], up)]
    for quarter in range(4):
        c, s = np.cos(quarter * np.pi / 2), np.sin(quarter * np.pi / 2)
        turn = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])
        quads += [([turn @ np.array(v) for v in corners], turn @ np.array(normal)) for corners, normal in side]
    vertices: list[list[float]] = []
    normals: list[list[float]] = []  # one per vertex, the face's own: flat shading, crisp edges
    indices: list[int] = []
    for corners, normal in quads:
        a, b, c_ = (np.array(v, dtype=float) for v in corners[:3])
        if np.dot(np.cross(b - a, c_ - a), normal) < 0:
            corners = corners[::-1]  # counter-clockwise seen from where the face looks
        base = len(vertices)
        vertices += [[float(x) for x in v] for v in corners]
        normals += [[float(x) for x in normal]] * 4
        indices += [base, base + 1, base + 2, base, base + 2, base + 3]
    return vertices, normals, indices


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
