"""Episodes copied out of a finished collection instead of simulated again.

Episode i of a recipe draws its noise flag first from its own generator
(`EpisodeRecipe.episode_start`), so at any noisy fraction it is, frame for frame, either
episode i of the recipe's all-clean collection (noisy fraction 0) or episode i of its
all-noisy one (1). Table 7's 25 % and 50 % collections are therefore assembled from those
two: each episode's stored PNGs are written into the staging folder a collection worker
would have filled, and the writer appends it as if it had been simulated, so the dataset
is the one a simulation would have written (tests/test_prefixes.py compares them).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc
import pyarrow.parquet as pq
from lerobot.datasets.dataset_metadata import LeRobotDatasetMetadata

from lerobot_murm.collection.dataset import StagedEpisode, episode_staging_folder, stage_camera
from lerobot_murm.features import ACTION, ENVIRONMENT_STATE, STATE, goal_image_key, image_key


@dataclass(frozen=True)
class Donor:
    """A finished collection whose episodes 0 .. episodes - 1 can stand in for simulated ones."""

    root: Path
    episodes: int


_OPEN: dict[Path, tuple[LeRobotDatasetMetadata, Path | None, pa.Table | None]] = {}


def _episode_rows(donor: Path, index: int) -> pa.Table:
    """The frames of the donor's episode `index`, keeping the last parquet file read per donor
    open (episodes are asked for in order, so each file is read once)."""
    meta, path, table = _OPEN.get(donor) or (LeRobotDatasetMetadata("local/donor", root=donor), None, None)
    wanted = donor / meta.get_data_file_path(index)
    if wanted != path:
        path, table = wanted, pq.read_table(wanted)
    _OPEN[donor] = (meta, path, table)
    return table.filter(pc.equal(table["episode_index"], index))


def stage_from_donor(donor: Path, index: int, dataset_root: Path, cameras: tuple[str, ...]) -> StagedEpisode:
    """Episode `index` of the donor, staged for `dataset_root` as `dataset.stage_episode` would."""
    rows = _episode_rows(donor, index)
    folder = episode_staging_folder(dataset_root, index)
    images: dict[str, list[str]] = {}
    for camera in cameras:
        frames = [frame["bytes"] for frame in rows.column(image_key(camera)).to_pylist()]
        goal = rows.column(goal_image_key(camera))[0].as_py()["bytes"]
        images |= stage_camera(folder, camera, frames, goal, lambda png, path: path.write_bytes(png))

    def array(key: str, dtype: type) -> np.ndarray:
        return np.asarray(rows.column(key).to_pylist(), dtype)

    return StagedEpisode(
        images,
        array(STATE, np.float32),
        array(ENVIRONMENT_STATE, np.float32),
        array(ACTION, np.float32),
        array("next.success", bool).reshape(-1),
        str(folder),
    )
