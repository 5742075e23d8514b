"""A camera's frames and goal images, decoded once from a LeRobotDataset into uint8 arrays.

Any RGB stream under `observation.images.` is a camera: PNGs in the parquet files (what
`murm collect` writes) or video (what `lerobot-record` writes), decoded by OpenCV and by
LeRobot's own `decode_video_frames` respectively, in a background thread a few chunks ahead
of whoever consumes them, and brought to the encoder's side by `resize.fit_images`.
A camera's goal images are its `<camera>_goal` stream, one per episode; a dataset without
that stream has hindsight goals: each episode's own last frame.

Memory: 48 x 48 x 3 bytes = 6.9 KB a frame, so 100,000 frames take 0.69 GB per camera
(goal images add one frame per episode).
"""

from __future__ import annotations

import hashlib
import json
import re
from collections import deque
from collections.abc import Callable, Iterator
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from functools import partial
from pathlib import Path

import cv2
import numpy as np
import pyarrow as pa
import torch
from datasets.exceptions import DatasetGenerationError
from lerobot.datasets.lerobot_dataset import LeRobotDataset
from lerobot.datasets.video_utils import decode_video_frames

from lerobot_murm.features import IMAGES_PREFIX, goal_image_key, image_cameras, image_key, is_goal
from lerobot_murm.vqvae.resize import encoder_side, fit_images


@dataclass
class CameraFrames:
    camera: str
    images: np.ndarray  # (N, S, S, 3) uint8, every frame of the dataset in order, at the encoder's side S
    goals: np.ndarray  # (E, S, S, 3) uint8, one goal image per episode; none (0, S, S, 3) with hindsight goals
    episode_index: np.ndarray  # (N,) int
    frame_index: np.ndarray  # (N,) int


REPO_ID = re.compile(r"[A-Za-z0-9][\w.-]*/[\w.-]+")
VIDEO_BACKEND = "pyav"  # torchcodec finds no FFmpeg libraries on a machine without ffmpeg installed


class UnreadableDataset(RuntimeError):
    """A dataset folder whose files cannot be read (torn by a hard stop, or not a LeRobotDataset)."""


def dataset_location(value: str) -> tuple[str, Path | None]:
    """`--dataset` values: a local dataset folder or a Hub repo id -> (repo_id, root).

    A value that is no folder here and cannot be a repo id (`user/name`) is a missing folder."""
    path = Path(value)
    if path.exists():
        return f"local/{path.name}", path
    if not REPO_ID.fullmatch(value):
        raise FileNotFoundError(f"dataset folder {value} does not exist (and {value!r} is no Hub repo id user/name)")
    return value, None


def open_dataset(repo_id: str, root: Path | str | None) -> LeRobotDataset:
    """The dataset; a one-line `UnreadableDataset` naming the folder if its files cannot be read."""
    if root is not None and not (Path(root) / "meta" / "info.json").is_file():
        raise UnreadableDataset(f"{root} is not a LeRobotDataset (no meta/info.json)")
    try:
        return LeRobotDataset(repo_id, root=root, video_backend=VIDEO_BACKEND)
    except (DatasetGenerationError, pa.ArrowException, json.JSONDecodeError) as error:
        cause = error.__cause__ or error
        raise UnreadableDataset(
            f"cannot read the dataset at {root or repo_id}: {str(cause).splitlines()[0]} "
            "(an interrupted `murm collect` is repaired by running it again with --resume)"
        ) from error


def dataset_cameras(dataset: LeRobotDataset) -> list[str]:
    return image_cameras(dataset.meta.camera_keys)


def dataset_fingerprint(dataset: LeRobotDataset) -> str:
    """A hash of every data and metadata file: any change to the dataset changes it."""
    digest = hashlib.sha256()
    root = Path(dataset.root)
    for path in sorted(list(root.glob("data/**/*.parquet")) + list(root.glob("meta/**/*"))):
        if path.is_file() and path.name != "murm_collection.json":
            digest.update(str(path.relative_to(root)).encode())
            digest.update(path.read_bytes())
    return digest.hexdigest()


DECODE_CHUNK = 2048
DECODE_AHEAD = 3  # chunks decoded ahead of the consumer


@dataclass
class CameraStream:
    """Where a camera's frames and goal images are in a dataset, and the rows they belong to."""

    camera: str  # the short name: `laptop` for `observation.images.laptop`
    key: str  # the frames' feature key
    goal_key: str | None  # the goal images' key; None: hindsight goals, each episode's last frame
    size: tuple[int, int]  # (height, width) of the frames
    episode_index: np.ndarray  # (N,) per row, rows in dataset order
    frame_index: np.ndarray  # (N,)
    timestamp: np.ndarray  # (N,) seconds into the episode, where video frames are looked up

    def side(self, image_size: int) -> int:
        """The side of the square images an encoder of `image_size` sees of this stream."""
        return encoder_side(*self.size, image_size)


def episode_last_rows(episode_index: np.ndarray) -> np.ndarray:
    """Each episode's last row (rows sorted by episode), in episode order."""
    return np.flatnonzero(np.append(episode_index[1:] != episode_index[:-1], True))


def camera_stream(dataset: LeRobotDataset, camera: str) -> CameraStream:
    """`camera`, a short name (`laptop`) or a full key (`observation.images.laptop`), of `dataset`.

    A one-line ValueError where it is no camera of the dataset, no RGB image or video stream,
    or where an episode has a single frame (no transition to learn from, and its own goal)."""
    features, cameras = dataset.meta.features, dataset_cameras(dataset)
    key = camera if camera.startswith(IMAGES_PREFIX) else image_key(camera)
    if key not in features or is_goal(key):
        if camera in features and not is_goal(camera):
            raise ValueError(
                f"{camera} in {dataset.root} is no camera stream (MURM's cameras are the RGB image or video "
                f"streams under {IMAGES_PREFIX}); its cameras: {cameras}"
            )
        raise ValueError(f"the dataset at {dataset.root} has no camera {camera!r}; its cameras: {cameras}")
    short, feature = key[len(IMAGES_PREFIX) :], features[key]
    if feature["dtype"] not in ("image", "video"):
        raise ValueError(
            f"{key} in {dataset.root} is not an image or video stream (dtype {feature['dtype']}); "
            f"its cameras: {cameras}"
        )
    shape, names = feature["shape"], feature.get("names") or []
    height, width, channels = (
        shape if len(names) == 3 and names[2] in ("channel", "channels") else shape[1:] + shape[:1]
    )
    if channels != 3 or (feature.get("info") or {}).get("is_depth_map"):
        raise ValueError(f"{key} in {dataset.root} is not an RGB stream ({channels} channels); its cameras: {cameras}")
    table = dataset.hf_dataset.with_format("arrow").select_columns(["episode_index", "frame_index", "timestamp"])[:]
    episode_index = table["episode_index"].to_numpy()
    single = np.flatnonzero(np.bincount(episode_index) == 1)
    if len(single):
        raise ValueError(
            f"episode {single[0]} of {dataset.root} has a single frame: MURM learns from transitions, "
            "so every episode needs two frames or more"
        )
    goal = goal_image_key(short)
    return CameraStream(
        camera=short,
        key=key,
        goal_key=goal if goal in features else None,
        size=(int(height), int(width)),
        episode_index=episode_index,
        frame_index=table["frame_index"].to_numpy(),
        timestamp=table["timestamp"].to_numpy(),
    )


def decoded_rows(
    dataset: LeRobotDataset, stream: CameraStream, key: str, rows: np.ndarray, side: int
) -> Iterator[np.ndarray]:
    """(n, side, side, 3) uint8 chunks of the images of `key` (the stream's frames or goals) at
    `rows`, in order, decoded a few chunks ahead of the consumer."""
    if dataset.meta.features[key]["dtype"] == "image":
        column = dataset.hf_dataset.with_format("arrow").select_columns([key])[:][key]
        pngs = [item["bytes"] for item in column.take(rows).to_pylist()]
        jobs = [partial(decode_pngs, pngs[s : s + DECODE_CHUNK], side) for s in range(0, len(pngs), DECODE_CHUNK)]
    else:
        jobs = []
        episodes = stream.episode_index[rows]
        for episode in dict.fromkeys(episodes.tolist()):  # rows are sorted by episode
            ours = rows[episodes == episode]
            start = dataset.meta.episodes[episode][f"videos/{key}/from_timestamp"]
            path = Path(dataset.root) / dataset.meta.get_video_file_path(episode, key)
            for s in range(0, len(ours), DECODE_CHUNK):
                times = [start + float(t) for t in stream.timestamp[ours[s : s + DECODE_CHUNK]]]
                jobs.append(partial(_decode_video, path, times, dataset.tolerance_s, side))
    return decode_ahead(jobs)


def decode_ahead(jobs: list[Callable[[], np.ndarray]]) -> Iterator[np.ndarray]:
    """The jobs' results in order, computed by a background thread a few jobs ahead.

    Decoding holds one core and releases the GIL, so a consumer that encodes with torch
    overlaps with it (about 20 % faster than decode-then-encode on 2 cores).
    """
    with ThreadPoolExecutor(1) as pool:
        pending = deque(pool.submit(job) for job in jobs[:DECODE_AHEAD])
        for job in jobs[DECODE_AHEAD:]:
            yield pending.popleft().result()
            pending.append(pool.submit(job))
        while pending:
            yield pending.popleft().result()


def decode_pngs(pngs: list[bytes], side: int | None = None) -> np.ndarray:
    """(n, H, W, 3) RGB, or (n, side, side, 3) by `resize.fit_images`. OpenCV decodes these tiny
    PNGs twice as fast as Pillow (same pixels)."""
    decoded = [cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR) for data in pngs]
    images = np.stack(decoded)[..., ::-1].copy()  # BGR -> RGB
    if side is None or images.shape[1:3] == (side, side):
        return images
    return _fit(torch.from_numpy(images).permute(0, 3, 1, 2), side)


def _decode_video(path: Path, timestamps: list[float], tolerance_s: float, side: int) -> np.ndarray:
    """LeRobot's own decoding of a video's frames at `timestamps`, at the encoder's side."""
    frames = decode_video_frames(path, timestamps, tolerance_s, VIDEO_BACKEND, return_uint8=True)
    return _fit(frames, side)


def _fit(images: torch.Tensor, side: int) -> np.ndarray:
    """(n, 3, H, W) uint8 -> (n, side, side, 3) uint8 array."""
    return np.ascontiguousarray(fit_images(images, side).permute(0, 2, 3, 1).numpy())


@dataclass
class CameraPNGs:
    """A camera's encoded frames and goal images, straight from a `murm collect` dataset's parquet files."""

    camera: str
    frames: list[bytes]
    goals: list[bytes]  # one per episode, in episode order
    episode_index: np.ndarray
    frame_index: np.ndarray


def read_camera_pngs(dataset: LeRobotDataset, camera: str) -> CameraPNGs:
    available = dataset_cameras(dataset)
    if camera not in available:
        raise ValueError(f"the dataset at {dataset.root} has no camera {camera!r}; its cameras: {available}")
    table = dataset.hf_dataset.with_format("arrow")
    columns = table.select_columns([image_key(camera), goal_image_key(camera), "episode_index", "frame_index"])[:]
    frame_index = columns["frame_index"].to_numpy()
    goal_column = columns[goal_image_key(camera)]
    return CameraPNGs(
        camera=camera,
        frames=[item["bytes"] for item in columns[image_key(camera)].to_pylist()],
        goals=[goal_column[int(i)].as_py()["bytes"] for i in np.flatnonzero(frame_index == 0)],
        episode_index=columns["episode_index"].to_numpy(),
        frame_index=frame_index,
    )


def decoded_frames(dataset: LeRobotDataset, stream: CameraStream, side: int) -> Iterator[np.ndarray]:
    """Every frame of the camera in row order, as (n, side, side, 3) uint8 chunks."""
    return decoded_rows(dataset, stream, stream.key, np.arange(len(stream.episode_index)), side)


def decoded_goals(dataset: LeRobotDataset, stream: CameraStream, side: int) -> np.ndarray | None:
    """(E, side, side, 3): each episode's goal image (the goal stream at its first row); None for hindsight goals."""
    if stream.goal_key is None:
        return None
    first_rows = np.flatnonzero(stream.frame_index == 0)
    return np.concatenate(list(decoded_rows(dataset, stream, stream.goal_key, first_rows, side)))


def load_camera_frames(dataset: LeRobotDataset, stream: CameraStream, side: int) -> CameraFrames:
    images = np.concatenate(list(decoded_frames(dataset, stream, side)))
    goals = decoded_goals(dataset, stream, side)
    return CameraFrames(
        stream.camera, images, images[:0] if goals is None else goals, stream.episode_index, stream.frame_index
    )
