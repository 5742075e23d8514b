"""The artefacts of a grid, found again by name under `work_dir`: a dataset by its recipe, an
encoder by its dataset (each task's default collection: `encoder_root`), camera and steps, a
training run by its cell and seed; a finished run's result file under `results/<name>/runs/`.

Datasets and encoders are built here when missing (`ensure_dataset`, `ensure_encoder`; a job
that finds another building one waits for it, locking.py). The encoders a grid trains are
kept beside the results (`results/encoders/`, committed), since a VQ-VAE trained again on
another machine is another draw: `keep_encoders` copies them there, `fetch_kept_encoders`
back into a fresh work dir, and a run records each encoder's fingerprint.
"""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

from lerobot_murm.checkpointing import write_atomic
from lerobot_murm.collection import CollectConfig, collect
from lerobot_murm.collection.dataset import episode_successes
from lerobot_murm.collection.prefixes import cut_from_larger, noise_donors, start_from_smaller
from lerobot_murm.collection.shards import is_complete
from lerobot_murm.device import resolve_device
from lerobot_murm.env import CAMERA_NAMES
from lerobot_murm.env.murm_env import SCENE_VERSION
from lerobot_murm.experiments.configuration_reproduce import CellSpec, ReproduceConfig
from lerobot_murm.expert import default_noise_std
from lerobot_murm.locking import exclusive
from lerobot_murm.vqvae import VQVAEConfig
from lerobot_murm.vqvae.configuration_vqvae import LATENT_DISTANCE_FILE
from lerobot_murm.vqvae.encoder_files import (
    CONFIG_FILE,
    METRICS_FILE,
    WEIGHTS_FILE,
    encoder_fingerprint as fingerprint,
    save_encoder_files,
)
from lerobot_murm.vqvae.latent_cache import build_latent_cache
from lerobot_murm.vqvae.latent_distance import (
    QUANTILE_KEY,
    distance_statistics,
    read_statistics,
    save_beside_encoder,
)
from lerobot_murm.vqvae.object_pixels import OBJECT_PIXELS_FILE, check_encoders
from lerobot_murm.vqvae.train import train_vqvae


def dataset_root(config: ReproduceConfig, task: str, cell: CellSpec | None = None) -> Path:
    """Where the cell's demonstrations live (no cell: the collection's default recipe)."""
    c = config.collection
    episodes, noisy = config.cell_episodes(cell), config.cell_noisy_fraction(cell)
    std = config.cell_noise_std(task, cell)
    std = default_noise_std(task) if std is None else std
    name = f"{task}-scene{SCENE_VERSION}-{episodes}ep-std{std:g}-noisy{noisy:g}-seed{c.seed}-{c.image_size}px"
    return Path(config.work_dir) / "datasets" / name


def collect_config(config: ReproduceConfig, task: str, cell: CellSpec | None = None) -> CollectConfig:
    root = dataset_root(config, task, cell)
    c = config.collection
    return CollectConfig(
        task=task,
        root=root,
        episodes=config.cell_episodes(cell),
        workers=c.workers,
        cameras=CAMERA_NAMES,
        image_size=c.image_size,
        seed=c.seed,
        noise_std=config.cell_noise_std(task, cell),  # None: the task's std
        noisy_fraction=config.cell_noisy_fraction(cell),
    )


def ensure_dataset(collect_config: CollectConfig) -> Path:
    """The dataset: already there, cut from a finished larger collection of its recipe, or
    collected (carrying a finished smaller one on, or resuming whatever ran before, on
    whichever machine; copying the episodes the all-clean and all-noisy collections hold).
    A job that finds another building it waits for it (locking.py)."""
    root = collect_config.root
    if is_complete(collect_config):
        return root
    with exclusive(root, wait=True):
        if is_complete(collect_config) or (not root.exists() and cut_from_larger(collect_config)):
            return root
        collect_config = start_from_smaller(collect_config)
        collect(replace(collect_config, resume=root.exists()), donors=noise_donors(collect_config))
    return root


def encoder_is_finished(out: Path, steps: int) -> bool:
    """A checkpoint trained to the end for `steps` (an interrupted one is trained again)."""
    if not (out / METRICS_FILE).exists():
        return False
    metrics = json.loads((out / METRICS_FILE).read_text())
    return not metrics["interrupted"] and metrics["steps"] == steps


def encoder_steps(config: ReproduceConfig, camera: str) -> int:
    return config.vqvae.camera_steps.get(camera, config.vqvae.steps)


def encoder_dir(config: ReproduceConfig, root: Path) -> Path:
    return Path(config.work_dir) / "vqvae" / f"{root.name}-{config.vqvae.steps}steps"


def encoder_root(config: ReproduceConfig, task: str) -> Path:
    """The dataset a task's encoders learn from: the default collection, whatever the cell's
    demonstrations. The paper trains one VQ-VAE per camera once (4.2) and encodes every
    experiment's states and goals with it (4.3); Table 7 varies what the policy learns from,
    not the encoders."""
    return dataset_root(config, task)


# the files beside an encoder's weights and config, `metrics.json` (what `encoder_is_finished` reads) copied last
BESIDE_ENCODER = (LATENT_DISTANCE_FILE, OBJECT_PIXELS_FILE, METRICS_FILE)


def kept_encoder_dir(config: ReproduceConfig, root: Path) -> Path:
    """Where a grid keeps the encoders it trained, beside its results (committed): a later
    sitting on a fresh machine encodes with the very same weights. A VQ-VAE trained again on
    another CPU is another draw (its latents and suggested epsilon differ), which would make
    the cells of one table differ by more than their recipes."""
    return Path(config.results_dir) / "encoders" / encoder_dir(config, root).name


def copy_encoder(source: Path, target: Path) -> None:
    with exclusive(target, wait=True):
        save_encoder_files(target, (source / WEIGHTS_FILE).read_bytes(), (source / CONFIG_FILE).read_bytes())
        for name in BESIDE_ENCODER:
            if (source / name).exists():
                write_atomic(target / name, (source / name).read_bytes())


def encoder_fingerprint(folder: Path) -> str | None:
    """What a run records of an encoder: the first 16 hex digits of its weights' sha256; None
    where there is no encoder."""
    return fingerprint(folder)[:16] if (folder / WEIGHTS_FILE).exists() else None


def fetch_kept_encoders(config: ReproduceConfig, encoders: list[tuple[Path, str]]) -> None:
    """Into the work dir, each kept encoder that is not trained there (before `ensure_encoder`)."""
    for root, camera in encoders:
        out, kept = encoder_dir(config, root) / camera, kept_encoder_dir(config, root) / camera
        steps = encoder_steps(config, camera)
        if not encoder_is_finished(out, steps) and encoder_is_finished(kept, steps):
            copy_encoder(kept, out)


def keep_encoders(config: ReproduceConfig, encoders: list[tuple[Path, str]]) -> None:
    """Beside the results, each finished encoder of the work dir not kept there yet (a kept
    encoder is never replaced: the runs that record its fingerprint were trained on it)."""
    for root, camera in encoders:
        out, kept = encoder_dir(config, root) / camera, kept_encoder_dir(config, root) / camera
        steps = encoder_steps(config, camera)
        if encoder_is_finished(out, steps) and not encoder_is_finished(kept, steps):
            copy_encoder(out, kept)


def current_encoders(config: ReproduceConfig, task: str, cameras: list[str]) -> dict[str, str] | None:
    """The fingerprints of the encoders a run of `task` on `cameras` would encode with now
    (the work dir's, else the kept ones); None while one of them is yet to be trained."""
    root, found = encoder_root(config, task), {}
    for camera in cameras:
        trained = [
            folder / camera
            for folder in (encoder_dir(config, root), kept_encoder_dir(config, root))
            if encoder_is_finished(folder / camera, encoder_steps(config, camera))
        ]
        if not trained:
            return None
        found[camera] = encoder_fingerprint(trained[0])
    return found


def ensure_encoder(config: ReproduceConfig, root: Path, camera: str) -> Path:
    """A camera's VQ-VAE in `<encoder_dir>/<camera>`, with its epsilon statistics and its object
    check (`murm check-encoders`) beside it. A job that finds another making it waits for it
    (locking.py), then finishes what is left."""
    out = encoder_dir(config, root) / camera
    steps = encoder_steps(config, camera)
    checked = (out / OBJECT_PIXELS_FILE).exists() or not config.object_check_episodes
    if encoder_is_finished(out, steps) and _has_statistics(out) and checked:
        return out
    device = str(resolve_device(config.device))
    repo_id = f"local/{root.name}"
    with exclusive(out, wait=True):
        if not encoder_is_finished(out, steps):
            vq_config = replace(VQVAEConfig(), steps=steps, batch_size=config.vqvae.batch_size)
            train_vqvae(repo_id, root, camera, out, vq_config, device=device)
            (out / OBJECT_PIXELS_FILE).unlink(missing_ok=True)  # it was about the encoder trained before
        if not _has_statistics(out):
            cache = build_latent_cache(repo_id, root, out, Path(config.work_dir) / "latent_cache", device=device)
            save_beside_encoder(distance_statistics(cache, episode_successes(repo_id, root)), out)
        if not (out / OBJECT_PIXELS_FILE).exists() and config.object_check_episodes:
            try:
                check_encoders(repo_id, root, [out], config.object_check_episodes, device=device)
            except ValueError as error:  # a diagnostic: the grid goes on without it
                print(f"object check of {camera} skipped: {error}")
    return out


def _has_statistics(encoder: Path) -> bool:
    """`murm encode`'s epsilon statistics beside the encoder, of the current kind."""
    return (encoder / LATENT_DISTANCE_FILE).exists() and QUANTILE_KEY in read_statistics(encoder)


def run_dir(config: ReproduceConfig, task: str, cell: CellSpec, seed: int) -> Path:
    return Path(config.work_dir) / "runs" / config.name / task / cell.label / f"seed{seed}"


def result_path(config: ReproduceConfig, task: str, cell: CellSpec, seed: int) -> Path:
    return Path(config.results_dir) / config.name / "runs" / f"{task}__{cell.label}__seed{seed}.json"
