"""A camera's frames and goal images, decoded once from a LeRobotDataset into uint8 arrays.

Memory: 48 x 48 x 3 bytes = 6.9 KB a frame, so 100,000 frames take 0.69 GB per camera
(goal images add one frame per episode). PNG decoding runs once, in threads.
"""

from __future__ import annotations

import hashlib
import io
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from lerobot.datasets.lerobot_dataset import LeRobotDataset
from PIL import Image

from lerobot_murm.collection.dataset import goal_image_key, image_key


@dataclass
class CameraFrames:
    camera: str
    images: np.ndarray  # (N, H, W, 3) uint8, every frame of the dataset in order
    goals: np.ndarray  # (E, H, W, 3) uint8, one goal image per episode
    episode_index: np.ndarray  # (N,) int
    frame_index: np.ndarray  # (N,) int


def open_dataset(repo_id: str, root: Path | str | None) -> LeRobotDataset:
    return LeRobotDataset(repo_id, root=root, video_backend="pyav")


def dataset_cameras(dataset: LeRobotDataset) -> list[str]:
    prefix = "observation.images."
    keys = [k for k in dataset.meta.camera_keys if not k.endswith("_goal")]
    return [k[len(prefix) :] for k in keys]


def dataset_fingerprint(dataset: LeRobotDataset) -> str:
    """A hash of every data and metadata file: any change to the dataset changes it."""
    digest = hashlib.sha256()
    root = Path(dataset.root)
    for path in sorted(list(root.glob("data/**/*.parquet")) + list(root.glob("meta/**/*"))):
        if path.is_file() and path.name != "murm_collection.json":
            digest.update(str(path.relative_to(root)).encode())
            digest.update(path.read_bytes())
    return digest.hexdigest()


def load_camera_frames(dataset: LeRobotDataset, camera: str) -> CameraFrames:
    available = dataset_cameras(dataset)
    if camera not in available:
        raise ValueError(f"the dataset at {dataset.root} has no camera {camera!r}; its cameras: {available}")
    table = dataset.hf_dataset.with_format("arrow")
    columns = table.select_columns([image_key(camera), goal_image_key(camera), "episode_index", "frame_index"])[:]
    episode_index = columns["episode_index"].to_numpy()
    frame_index = columns["frame_index"].to_numpy()
    frame_bytes = [item["bytes"] for item in columns[image_key(camera)].to_pylist()]
    first_frames = np.flatnonzero(frame_index == 0)
    goal_column = columns[goal_image_key(camera)]
    goal_bytes = [goal_column[int(i)].as_py()["bytes"] for i in first_frames]
    with ThreadPoolExecutor(4) as pool:
        images = np.stack(list(pool.map(_decode_png, frame_bytes, chunksize=512)))
        goals = np.stack(list(pool.map(_decode_png, goal_bytes, chunksize=64)))
    return CameraFrames(camera, images, goals, episode_index, frame_index)


def _decode_png(data: bytes) -> np.ndarray:
    with Image.open(io.BytesIO(data)) as image:
        return np.asarray(image.convert("RGB"))
