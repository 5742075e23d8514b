"""The LeRobotDataset layout of MURM demonstrations: features, episodes, and the collection summary.

Images are stored as PNG inside the parquet files (LeRobot's `image` dtype), not as
video: at 48x48 PNG is smaller on disk than AV1 and about 25x cheaper to read per
sample (see BENCHMARKS.md).

Writing is split so that the expensive part runs in the collection workers:
`stage_episode` (worker) encodes an episode's PNGs as LeRobot's image writer would (its
PIL conversion and compression level), into a staging folder under the dataset's
`images/` (which `push_to_hub` never uploads); `save_staged_episode` (main process)
hands them to `LeRobotDataset.save_episode` as a pre-built episode, which embeds them
in parquet and computes the statistics. A goal image is encoded once per episode.
"""

from __future__ import annotations

import json
import shutil
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
from lerobot.datasets.image_writer import image_array_to_pil_image
from lerobot.datasets.lerobot_dataset import LeRobotDataset

from lerobot_murm.checkpointing import write_atomic
from lerobot_murm.collection.durability import snapshot
from lerobot_murm.collection.episodes import Episode, EpisodeRecipe
from lerobot_murm.env.murm_env import CONTROL_FPS
from lerobot_murm.features import ACTION, ENVIRONMENT_STATE, REWARD, STATE, goal_image_key, image_key

SUMMARY_FILE = "meta/murm_collection.json"
STAGING_DIR = "images/murm-staging"
PNG_COMPRESS_LEVEL = 6  # what LeRobot's writer uses for `image` features
IMAGE_NAMES = ["height", "width", "channels"]


def dataset_features(cameras: tuple[str, ...], image_size: int) -> dict:
    image = {"dtype": "image", "shape": (image_size, image_size, 3), "names": IMAGE_NAMES}
    features = {}
    for camera in cameras:
        features[image_key(camera)] = image
        features[goal_image_key(camera)] = image
    return features | {
        STATE: {"dtype": "float32", "shape": (4,), "names": ["ee_x", "ee_y", "ee_z", "finger_width"]},
        ENVIRONMENT_STATE: {
            "dtype": "float32",
            "shape": (6,),
            "names": ["object_x", "object_y", "object_z", "goal_x", "goal_y", "goal_z"],
        },
        ACTION: {"dtype": "float32", "shape": (4,), "names": ["dx", "dy", "dz", "gripper"]},
        REWARD: {"dtype": "float32", "shape": (1,), "names": None},
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
        use_videos=False,  # no image writer either: workers stage the PNGs (stage_episode)
        video_backend="pyav",  # no videos to decode; naming it spares LeRobot's noisy torchcodec probe
    )


@dataclass
class StagedEpisode:
    """An episode whose images are PNG files on disk: what a worker sends to the writer."""

    images: dict[str, list[str]]  # feature key -> one PNG path per frame
    state: np.ndarray
    environment_state: np.ndarray
    action: np.ndarray
    success: np.ndarray
    folder: str

    @property
    def succeeded(self) -> bool:
        return bool(self.success.any())


def staging_root(dataset_root: Path) -> Path:
    return Path(dataset_root) / STAGING_DIR


def episode_staging_folder(dataset_root: Path, index: int) -> Path:
    """Where episode `index` is staged before the writer takes it."""
    return staging_root(dataset_root) / f"episode-{index:06d}"


def stage_camera[T](
    folder: Path, camera: str, frames: Sequence[T], goal: T, write: Callable[[T, Path], None]
) -> dict[str, list[str]]:
    """Write one camera's frames and goal image into the staging folder with `write(image, path)`;
    the paths by feature key, the goal's repeated for every frame as the writer wants it. `T` is an
    image as it comes: pixels to encode, or PNG bytes."""
    paths = [folder / camera / f"frame-{t:06d}.png" for t in range(len(frames))]
    paths[0].parent.mkdir(parents=True, exist_ok=True)
    for frame, path in zip(frames, paths, strict=True):
        write(frame, path)
    goal_path = folder / f"{camera}_goal.png"
    write(goal, goal_path)
    return {image_key(camera): [str(p) for p in paths], goal_image_key(camera): [str(goal_path)] * len(frames)}


def _encode_png(image: np.ndarray, path: Path) -> None:
    """LeRobot's `write_image`, less its `except`: that logs a failed write (one line per image
    on a full disk) and goes on, where the collection must stop and say why."""
    image_array_to_pil_image(image).save(path, compress_level=PNG_COMPRESS_LEVEL)


def stage_episode(episode: Episode, dataset_root: Path) -> StagedEpisode:
    folder = episode_staging_folder(dataset_root, episode.index)
    images: dict[str, list[str]] = {}
    for camera, frames in episode.images.items():
        images |= stage_camera(folder, camera, frames, episode.goal_images[camera], _encode_png)
    return StagedEpisode(
        images,
        episode.state,
        episode.environment_state,
        episode.action,
        episode.success,
        str(folder),
    )


def save_staged_episode(dataset: LeRobotDataset, episode: StagedEpisode, task_description: str) -> None:
    """Append one episode through `LeRobotDataset.save_episode`, then drop its staged PNGs."""
    steps = len(episode.action)
    last = np.zeros((steps, 1), bool)
    last[-1] = True
    dataset.save_episode(
        {
            "size": steps,
            "task": [task_description] * steps,
            "episode_index": dataset.meta.total_episodes,
            "index": [],  # index and task_index are filled in by save_episode
            "task_index": [],
            "frame_index": np.arange(steps),
            "timestamp": np.arange(steps, dtype=np.float32) / dataset.meta.fps,
            **episode.images,
            STATE: episode.state,
            ENVIRONMENT_STATE: episode.environment_state,
            ACTION: episode.action,
            REWARD: episode.success.astype(np.float32).reshape(steps, 1),
            "next.done": last,
            "next.success": episode.success.reshape(steps, 1),
        }
    )
    shutil.rmtree(episode.folder)


def episode_successes(repo_id: str, root: Path) -> np.ndarray:
    """Per-episode success (at any step) read back from a finished dataset. A dataset without
    a success column (a robot's own recording) counts every episode as successful: each reached
    its own last frame, the goal it has without goal images (hindsight)."""
    dataset = LeRobotDataset(repo_id, root=root, video_backend="pyav")
    if "next.success" not in dataset.meta.features:
        return np.ones(dataset.meta.total_episodes, bool)
    columns = dataset.hf_dataset.with_format("numpy").select_columns(["episode_index", "next.success"])[:]
    successes = np.zeros(dataset.meta.total_episodes, bool)
    np.logical_or.at(successes, columns["episode_index"], columns["next.success"].reshape(-1))
    return successes


def write_summary(root: Path, recipe: EpisodeRecipe, successes: np.ndarray, requested: int) -> dict:
    """The collection summary, written last and atomically after a `finalize()`: with the
    snapshot `durability.restore` repairs a hard stop from (see durability.py)."""
    summary = {
        "recipe": asdict(recipe),
        "episodes": len(successes),
        "requested_episodes": requested,
        "success_rate": float(successes.mean()) if len(successes) else None,
        "episode_success": [bool(s) for s in successes],
        "flushed": snapshot(root, SUMMARY_FILE),
    }
    write_atomic(root / SUMMARY_FILE, (json.dumps(summary, indent=2) + "\n").encode())
    return summary


def read_summary(root: Path) -> dict | None:
    path = root / SUMMARY_FILE
    return json.loads(path.read_text()) if path.exists() else None


def read_recipe(root: Path) -> EpisodeRecipe | None:
    summary = read_summary(root)
    if summary is None:
        return None
    return recipe_from_summary(summary["recipe"])


def recipe_from_summary(stored: dict) -> EpisodeRecipe:
    """The recipe a collection summary stores. Older summaries: `scene` 1 (before versions),
    and the noise's scale in two knobs, `noise_k` times `noise_std` (the collections all
    used k = 1, so their std reads unchanged)."""
    recipe = {"scene": 1, **stored, "cameras": tuple(stored["cameras"])}
    k = recipe.pop("noise_k", 1.0)
    if k != 1.0:
        recipe["noise_std"] = k * recipe["noise_std"]
    return EpisodeRecipe(**recipe)
