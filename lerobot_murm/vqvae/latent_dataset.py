"""Latent datasets: demonstrations whose camera streams are replaced by the frozen VQ-VAEs' codes.

A latent dataset is an ordinary LeRobotDataset (v3): the source's actions, rewards, robot
state and episodes (not the privileged object/goal state, which no policy may see), and per
chosen camera `observation.latent.<camera>` and
`observation.latent.<camera>_goal`, the codebook indices of the frame and of the episode's
goal image (grid x grid row-major; with hindsight goals, a dataset without goal images, the
codes of the episode's last frame), packed several to an int64 (`code_packing`), with no
image streams. Indices rather than the 720 floats they stand for: a latent is a lookup in
the encoder's codebook (bit-identical to encoding the image), and the files are 10x
smaller; packed, because LeRobot's data loader turns every number of a row into Python
objects one row at a time, and fewer numbers read faster (BENCHMARKS.md). The codebooks, the
encoders' fingerprints, the source dataset and where the goals come from ("goals":
"rendered" goal images or "hindsight") are in `meta/murm_latents.json`; a policy refuses
codes made by other encoders than its own.

It is written with LeRobot's own `dataset_tools.modify_features` (one pass: add the code
columns, drop the images) from the latent caches `murm encode` builds anyway.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
from lerobot.datasets.dataset_tools import modify_features
from lerobot.datasets.lerobot_dataset import LeRobotDataset

from lerobot_murm.features import ENVIRONMENT_STATE, latent_goal_key, latent_key
from lerobot_murm.vqvae.code_packing import code_bits, codes_per_number, pack_codes, unpack_codes
from lerobot_murm.vqvae.configuration_vqvae import VQVAEConfig
from lerobot_murm.vqvae.encoder_files import CONFIG_FILE, encoder_fingerprint
from lerobot_murm.vqvae.frames import dataset_fingerprint
from lerobot_murm.vqvae.latent_cache import HINDSIGHT, LatentCache

LATENTS_FILE = "meta/murm_latents.json"


def write_latent_dataset(
    dataset: LeRobotDataset,
    caches: list[LatentCache],
    encoder_dirs: list[Path],
    out: Path,
    repo_id: str,
    command: str = "",
) -> LeRobotDataset:
    """`dataset` with each cache's camera as codes and every image stream removed, written to `out`;
    `command` (what made it) goes into the description for the dataset card."""
    table = dataset.hf_dataset.with_format("arrow").select_columns(["episode_index", "frame_index"])[:]
    episode_index = table["episode_index"].to_numpy()
    for cache in caches:
        if not (
            np.array_equal(cache.episode_index, episode_index)
            and np.array_equal(cache.frame_index, table["frame_index"].to_numpy())
        ):
            raise ValueError(f"the {cache.camera} latent cache does not match the rows of {dataset.root}")
    goal_sources = {cache.goals for cache in caches}
    if len(goal_sources) > 1:
        raise ValueError(f"{dataset.root} has goal images of some of these cameras only: encode them separately")
    added = {}
    for cache in caches:
        size = len(cache.codebook)
        frames, goals = pack_codes(cache.indices, size), pack_codes(cache.goal_indices, size)[episode_index]
        codes = {"dtype": "int64", "shape": [frames.shape[1]], "names": None}
        added[latent_key(cache.camera)] = (frames, codes)
        added[latent_goal_key(cache.camera)] = (goals, codes)
    # every column costs LeRobot's loader time per row: keep only what a policy may use
    removed = list(dataset.meta.camera_keys)
    if ENVIRONMENT_STATE in dataset.meta.features:
        removed.append(ENVIRONMENT_STATE)
    latent = modify_features(dataset, add_features=added, remove_features=removed, output_dir=out, repo_id=repo_id)
    description = {
        "source": {"repo_id": dataset.repo_id, "fingerprint": dataset_fingerprint(dataset)},
        "command": command,
        "goals": goal_sources.pop(),
        "cameras": {
            cache.camera: {
                "encoder": json.loads((Path(encoder_dir) / CONFIG_FILE).read_text()),
                "encoder_fingerprint": encoder_fingerprint(Path(encoder_dir)),
                "codebook": cache.codebook.tolist(),
                "code_bits": code_bits(len(cache.codebook)),  # `code_packing`: indices per int64 and their width
                "codes_per_number": codes_per_number(len(cache.codebook)),
            }
            for cache, encoder_dir in zip(caches, encoder_dirs, strict=True)
        },
    }
    (Path(out) / LATENTS_FILE).write_text(json.dumps(description) + "\n")
    return latent


def read_latent_caches(
    dataset: LeRobotDataset, cameras: list[str], encoder_fingerprints: dict[str, str] | None = None
) -> list[LatentCache]:
    """The cameras' codes of every row, as the latent caches the replay reads.

    With `encoder_fingerprints`, codes made by other encoders than these are refused.
    """
    written = json.loads((Path(dataset.root) / LATENTS_FILE).read_text())
    description = written["cameras"]
    missing = [c for c in cameras if c not in description]
    if missing:
        raise ValueError(
            f"the latent dataset at {dataset.root} has no codes of {missing}; it has {sorted(description)}"
        )
    table = dataset.hf_dataset.with_format("arrow")
    columns = [k for c in cameras for k in (latent_key(c), latent_goal_key(c))]
    table = table.select_columns([*columns, "episode_index", "frame_index", "index"])[:]
    if not np.array_equal(table["index"].to_numpy(), np.arange(len(table))):
        raise ValueError(f"the rows of {dataset.root} are not in index order")
    episode_index, frame_index = table["episode_index"].to_numpy(), table["frame_index"].to_numpy()
    caches = []
    for camera in cameras:
        info = description[camera]
        expected = (encoder_fingerprints or {}).get(camera, info["encoder_fingerprint"])
        if expected != info["encoder_fingerprint"]:
            raise ValueError(f"the {camera} codes in {dataset.root} come from another encoder than the policy's")
        grid, codebook = VQVAEConfig(**info["encoder"]).grid_size, np.asarray(info["codebook"], np.float32)
        caches.append(
            LatentCache(
                camera=camera,
                indices=_codes(table, latent_key(camera), grid, len(codebook)),
                goal_indices=_codes(table, latent_goal_key(camera), grid, len(codebook))[
                    np.flatnonzero(frame_index == 0)
                ],
                codebook=codebook,
                episode_index=episode_index,
                frame_index=frame_index,
                hindsight=written.get("goals") == HINDSIGHT,  # absent: written before hindsight goals
            )
        )
    return caches


def _codes(table, column: str, grid: int, codebook_size: int) -> np.ndarray:
    packed = table[column].combine_chunks().flatten().to_numpy().reshape(len(table), -1)
    return unpack_codes(packed, codebook_size, grid * grid).reshape(-1, grid, grid)
