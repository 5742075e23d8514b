"""The three MURM tasks (paper 4.1): scene layout, goal sampling and success from simulator state.

A task builds its bodies into a freshly reset simulator, draws its goal from the
episode's random generator, says where the object and the end-effector are when the
goal is reached (for the goal images), and judges success from privileged state.
"""

from __future__ import annotations

from abc import ABC, abstractmethod

import numpy as np

from lerobot_murm.env import objects
from lerobot_murm.env.objects import SHAPES, Shape

# Where the end-effector (the point between the fingertips) may go, in metres.
WORKSPACE_LOW = np.array([0.28, -0.34, 0.012])
WORKSPACE_HIGH = np.array([0.80, 0.40, 0.40])
# Graspable objects start in this strip, in front of the trays.
OBJECT_SPAWN_LOW = np.array([0.38, -0.26])
OBJECT_SPAWN_HIGH = np.array([0.70, -0.08])
HOVER_ABOVE_GOAL = 0.07  # end-effector height above a placed object in the goal image


class Task(ABC):
    """One episode's scene: `object_body` is the object the goal is about."""

    name: str
    success_radius: float

    def __init__(self) -> None:
        self.object_body: int = -1
        self.object_shape: Shape = SHAPES["cube"]
        self.goal_position = np.zeros(3)
        self.initial_object_position = np.zeros(3)

    @abstractmethod
    def build(self, client, rng: np.random.Generator) -> None:
        """Create this task's bodies and draw the goal."""

    def goal_ee_position(self) -> np.ndarray:
        """Where the end-effector is in the goal image."""
        return self.goal_position + np.array([0.0, 0.0, HOVER_ABOVE_GOAL])

    def goal_finger_width(self) -> float:
        return 0.08

    def object_position(self, client) -> np.ndarray:
        return objects.body_position(client, self.object_body)

    def is_success(self, client) -> bool:
        return bool(np.linalg.norm(self.object_position(client) - self.goal_position) < self.success_radius)

    def _spawn_cube_for(self, client, rng: np.random.Generator, goal_tray: np.ndarray) -> None:
        """The placing tasks' red cube, in the spawn strip; its goal rests on the tray's floor."""
        self.object_shape = SHAPES["cube"]
        self.goal_position = goal_tray + np.array([0.0, 0.0, self.object_shape.half_height])
        xy = rng.uniform(OBJECT_SPAWN_LOW, OBJECT_SPAWN_HIGH)
        self.object_body = self._spawn_object(client, rng, self.object_shape, xy, "red")
        self.initial_object_position = self.object_position(client)

    def _spawn_object(self, client, rng: np.random.Generator, shape: Shape, xy: np.ndarray, colour) -> int:
        position = np.array([xy[0], xy[1], shape.half_height])
        yaw = rng.uniform(-np.pi, np.pi) if shape.name == "cylinder" else rng.uniform(-0.3, 0.3)
        return objects.create_object(client, shape, position, yaw, objects.OBJECT_COLOURS[colour])


class PlaceInBox(Task):
    """Task 1: put the cube into the goal box, one of nine on a 3x3 grid (success within 3 cm)."""

    name = "place_in_box"
    success_radius = 0.03
    TRAY_XS = (0.43, 0.555, 0.68)
    TRAY_YS = (0.05, 0.175, 0.30)

    def build(self, client, rng: np.random.Generator) -> None:
        centres = [np.array([x, y, objects.TRAY_FLOOR]) for x in self.TRAY_XS for y in self.TRAY_YS]
        for centre in centres:
            objects.create_tray(client, centre)
        goal_tray = centres[int(rng.integers(len(centres)))]
        self._spawn_cube_for(client, rng, goal_tray)


class PlaceInRandomBox(Task):
    """Task 2: put the cube into a single box at a random 3-D position (success within 5 cm)."""

    name = "place_in_random_box"
    success_radius = 0.05
    TRAY_LOW = np.array([0.42, 0.04, 0.0])
    TRAY_HIGH = np.array([0.70, 0.30, 0.15])

    def build(self, client, rng: np.random.Generator) -> None:
        centre = rng.uniform(self.TRAY_LOW, self.TRAY_HIGH) + np.array([0.0, 0.0, objects.TRAY_FLOOR])
        if centre[2] > 2 * objects.TRAY_FLOOR:  # raised: stand it on a column
            under_floor = centre - np.array([0.0, 0.0, objects.TRAY_FLOOR])
            objects.create_pedestal(client, under_floor, objects.TRAY_INNER / 2 + objects.TRAY_WALL)
        objects.create_tray(client, centre)
        self._spawn_cube_for(client, rng, centre)


class PickUp(Task):
    """Task 3: among objects of several shapes scattered at random, lift the target 5 cm."""

    name = "pick_up"
    lift_success = 0.05
    goal_lift = 0.10  # the goal image shows the target held this high
    n_objects = 3
    SCATTER_LOW = np.array([0.36, -0.26])
    SCATTER_HIGH = np.array([0.72, 0.30])
    MIN_SEPARATION = 0.11

    def build(self, client, rng: np.random.Generator) -> None:
        names = list(SHAPES)
        chosen = [names[i] for i in rng.choice(len(names), size=self.n_objects, replace=False)]
        colours = list(objects.OBJECT_COLOURS)
        positions = self._scatter(rng)
        bodies = [
            self._spawn_object(client, rng, SHAPES[name], xy, colours[i])
            for i, (name, xy) in enumerate(zip(chosen, positions, strict=True))
        ]
        self.object_body, self.object_shape = bodies[0], SHAPES[chosen[0]]
        self.initial_object_position = self.object_position(client)
        self.goal_position = self.initial_object_position + np.array([0.0, 0.0, self.goal_lift])

    def _scatter(self, rng: np.random.Generator) -> list[np.ndarray]:
        """Rejection-sample object positions at least MIN_SEPARATION apart."""
        positions: list[np.ndarray] = []
        while len(positions) < self.n_objects:
            xy = rng.uniform(self.SCATTER_LOW, self.SCATTER_HIGH)
            if all(np.linalg.norm(xy - other) >= self.MIN_SEPARATION for other in positions):
                positions.append(xy)
        return positions

    def goal_ee_position(self) -> np.ndarray:
        return self.goal_position.copy()

    def goal_finger_width(self) -> float:
        size = self.object_shape.size
        return 2 * size[0] if len(size) == 2 else 2 * size[1]

    def is_success(self, client) -> bool:
        lift = self.object_position(client)[2] - self.initial_object_position[2]
        return bool(lift >= self.lift_success)


TASKS: dict[str, type[Task]] = {task.name: task for task in (PlaceInBox, PlaceInRandomBox, PickUp)}
TASK_NAMES: tuple[str, ...] = tuple(TASKS)


def make_task(name: str) -> Task:
    if name not in TASKS:
        raise ValueError(f"unknown task {name!r}; valid tasks: {list(TASK_NAMES)}")
    return TASKS[name]()
