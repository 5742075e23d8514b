"""The LeRobotDataset layout of MURM demonstrations: features, frames, and the collection summary.

Images are stored as PNG inside the parquet files (LeRobot's `image` dtype), not as
video: at 48x48 PNG is smaller on disk than AV1 and about 25x cheaper to read per
sample (see BENCHMARKS.md).
"""

from __future__ import annotations

import json
from dataclasses import asdict
from pathlib import Path

import numpy as np
from lerobot.datasets.lerobot_dataset import LeRobotDataset

from lerobot_murm.collection.episodes import Episode, EpisodeRecipe
from lerobot_murm.env import goal_key
from lerobot_murm.env.murm_env import CONTROL_FPS

SUMMARY_FILE = "meta/murm_collection.json"
IMAGE_NAMES = ["height", "width", "channels"]


def image_key(camera: str) -> str:
    return f"observation.images.{camera}"


def goal_image_key(camera: str) -> str:
    return f"observation.images.{goal_key(camera)}"


def dataset_features(cameras: tuple[str, ...], image_size: int) -> dict:
    image = {"dtype": "image", "shape": (image_size, image_size, 3), "names": IMAGE_NAMES}
    features = {}
    for camera in cameras:
        features[image_key(camera)] = image
        features[goal_image_key(camera)] = image
    return features | {
        "observation.state": {"dtype": "float32", "shape": (4,), "names": ["ee_x", "ee_y", "ee_z", "finger_width"]},
        "observation.environment_state": {
            "dtype": "float32",
            "shape": (6,),
            "names": ["object_x", "object_y", "object_z", "goal_x", "goal_y", "goal_z"],
        },
        "action": {"dtype": "float32", "shape": (4,), "names": ["dx", "dy", "dz", "gripper"]},
        "next.reward": {"dtype": "float32", "shape": (1,), "names": None},
        "next.done": {"dtype": "bool", "shape": (1,), "names": None},
        "next.success": {"dtype": "bool", "shape": (1,), "names": None},
    }


def create_dataset(repo_id: str, root: Path, recipe: EpisodeRecipe) -> LeRobotDataset:
    return LeRobotDataset.create(
        repo_id=repo_id,
        fps=CONTROL_FPS,
        features=dataset_features(recipe.cameras, recipe.image_size),
        root=root,
        robot_type="franka_panda",
        use_videos=False,
        image_writer_threads=2,
    )


def append_episode(dataset: LeRobotDataset, episode: Episode, task_description: str) -> None:
    steps = len(episode.action)
    for t in range(steps):
        frame = {image_key(c): episode.images[c][t] for c in episode.images}
        frame |= {goal_image_key(c): image for c, image in episode.goal_images.items()}
        frame |= {
            "observation.state": episode.state[t],
            "observation.environment_state": episode.environment_state[t],
            "action": episode.action[t],
            "next.reward": np.array([float(episode.success[t])], np.float32),
            "next.done": np.array([t == steps - 1]),
            "next.success": np.array([episode.success[t]]),
            "task": task_description,
        }
        dataset.add_frame(frame)
    dataset.save_episode()


def episode_successes(repo_id: str, root: Path) -> np.ndarray:
    """Per-episode success (at any step) read back from a finished dataset."""
    dataset = LeRobotDataset(repo_id, root=root, video_backend="pyav")
    columns = dataset.hf_dataset.with_format("numpy").select_columns(["episode_index", "next.success"])[:]
    successes = np.zeros(dataset.meta.total_episodes, bool)
    np.logical_or.at(successes, columns["episode_index"], columns["next.success"].reshape(-1))
    return successes


def write_summary(root: Path, recipe: EpisodeRecipe, successes: np.ndarray, requested: int) -> dict:
    summary = {
        "recipe": asdict(recipe),
        "episodes": int(len(successes)),
        "requested_episodes": requested,
        "success_rate": float(successes.mean()) if len(successes) else None,
    }
    (root / SUMMARY_FILE).write_text(json.dumps(summary, indent=2) + "\n")
    return summary


def read_recipe(root: Path) -> EpisodeRecipe | None:
    path = root / SUMMARY_FILE
    if not path.exists():
        return None
    recipe = json.loads(path.read_text())["recipe"]
    return EpisodeRecipe(**{**recipe, "cameras": tuple(recipe["cameras"])})
