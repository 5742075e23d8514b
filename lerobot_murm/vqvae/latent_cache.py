"""The latent cache the RL trainer reads: every frame and goal image of a camera, encoded once.

A camera without a goal stream has hindsight goals: each episode's goal is the codes of its
own last frame (every episode reached its last frame), so a robot's own recordings, which
have no goal images, train a goal-conditioned policy as well.

It stores codebook indices (12x12 uint16 per image) and the codebook, so that
`latents()` returns exactly the vectors the frozen encoder produces (a table lookup,
bit-identical) in a tenth of the space. A cache file is named by the dataset's and
the encoder's fingerprints: a changed dataset or encoder never gets a stale cache.
"""

from __future__ import annotations

import os
from collections.abc import Iterable
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import torch

from lerobot_murm.progress import progress
from lerobot_murm.vqvae.encoder_files import encoder_fingerprint
from lerobot_murm.vqvae.frames import (
    camera_stream,
    dataset_fingerprint,
    decoded_frames,
    decoded_goals,
    episode_last_rows,
    open_dataset,
)
from lerobot_murm.vqvae.modeling_vqvae import VQVAE

ENCODE_BATCH = 1024
HINDSIGHT, RENDERED = "hindsight", "rendered"  # where goals come from: episodes' last frames, or goal images


@dataclass
class LatentCache:
    camera: str
    indices: np.ndarray  # (N, g, g) uint16, one per dataset frame, in dataset order
    goal_indices: np.ndarray  # (E, g, g) uint16, one per episode
    codebook: np.ndarray  # (K, D) float32
    episode_index: np.ndarray  # (N,)
    frame_index: np.ndarray  # (N,)
    hindsight: bool = False  # the goals are each episode's last frame, not goal images

    @property
    def goals(self) -> str:
        return HINDSIGHT if self.hindsight else RENDERED

    def with_hindsight_goals(self) -> LatentCache:
        """The same frames with each episode's last frame as its goal."""
        return replace(self, goal_indices=self.indices[episode_last_rows(self.episode_index)], hindsight=True)

    def latents(self, rows: np.ndarray | slice = slice(None)) -> np.ndarray:
        """(n, D*g*g) float32 latents of the frames `rows`, laid out as the encoder's output."""
        return _lookup(self.codebook, self.indices[rows])

    def goal_latents(self, episodes: np.ndarray | slice = slice(None)) -> np.ndarray:
        return _lookup(self.codebook, self.goal_indices[episodes])


def _lookup(codebook: np.ndarray, indices: np.ndarray) -> np.ndarray:
    vectors = codebook[indices.astype(np.int64)]  # (n, g, g, D)
    return np.ascontiguousarray(vectors.transpose(0, 3, 1, 2)).reshape(len(indices), -1)


def cache_path(cache_dir: Path, camera: str, dataset_fp: str, encoder_fp: str) -> Path:
    return Path(cache_dir) / f"{camera}-data{dataset_fp[:16]}-enc{encoder_fp[:16]}.npz"


@torch.inference_mode()
def encode_images(
    model: VQVAE, chunks: Iterable[np.ndarray], total: int, device: torch.device, desc: str | None = None
) -> np.ndarray:
    """Chunks of uint8 (n, H, W, 3) images, `total` in all -> uint16 (total, g, g) codebook indices."""
    out = np.empty((total, model.config.grid_size, model.config.grid_size), np.uint16)
    start = 0
    with progress(total=total, desc=desc, unit="img", disable=desc is None) as bar:
        for chunk in chunks:
            for batch in torch.from_numpy(chunk).split(ENCODE_BATCH):
                out[start : start + len(batch)] = model.encode_indices(batch.to(device)).cpu().numpy()
                start += len(batch)
            bar.update(len(chunk))
    if start != total:
        raise ValueError(f"expected {total} images, got {start}")
    return out


def build_latent_cache(
    repo_id: str, root: Path | None, encoder_dir: Path, cache_dir: Path | None, device: str = "cpu"
) -> LatentCache:
    """Load the cache for (dataset, encoder), building it first if it does not exist yet;
    without `cache_dir`, build it in memory only."""
    model = VQVAE.load(encoder_dir, device=device)
    camera = model.config.camera
    dataset = open_dataset(repo_id, root)
    path = cache_dir and cache_path(cache_dir, camera, dataset_fingerprint(dataset), encoder_fingerprint(encoder_dir))
    if path and path.exists():
        with np.load(path) as data:
            stored = {k: data[k] for k in data.files}
        return LatentCache(camera, **stored | {"hindsight": bool(stored.get("hindsight", False))})
    stream = camera_stream(dataset, camera)
    trained_on = tuple(model.config.source_size or (model.config.image_size, model.config.image_size))
    if stream.size != trained_on:
        raise ValueError(
            f"the {camera} VQ-VAE in {encoder_dir} was trained on {trained_on[0]}x{trained_on[1]} frames; "
            f"the dataset's {stream.key} has {stream.size[0]}x{stream.size[1]}"
        )
    device, side = torch.device(device), model.config.image_size
    frames = decoded_frames(dataset, stream, side)
    indices = encode_images(model, frames, len(stream.episode_index), device, desc=f"encode {camera}")
    goals = decoded_goals(dataset, stream, side)
    cache = LatentCache(
        camera=camera,
        indices=indices,
        goal_indices=(
            indices[episode_last_rows(stream.episode_index)]
            if goals is None
            else encode_images(model, [goals], len(goals), device)
        ),
        codebook=model.quantizer.codebook.detach().cpu().numpy().astype(np.float32),
        episode_index=stream.episode_index,
        frame_index=stream.frame_index,
        hindsight=goals is None,
    )
    if path is None:
        return cache
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f"{path.stem}.{os.getpid()}.tmp.npz")
    fields = ("indices", "goal_indices", "codebook", "episode_index", "frame_index", "hindsight")
    np.savez(tmp, **{k: getattr(cache, k) for k in fields})
    tmp.replace(path)  # atomic: an interrupted build leaves no half cache
    return cache
