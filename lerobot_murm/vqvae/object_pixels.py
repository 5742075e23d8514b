"""Does a camera's encoder keep the object? Reconstruction error on the object's pixels.

A 48x48 view where the object covers a few pixels can reconstruct at a high PSNR with the
object gone (the table and the arm are most of the image), and a reward on latent
distances is then blind to the object. So the held-out frames of each encoder are
scored on the object's pixels alone, beside the whole image.

Datasets store images, not masks, so the held-out episodes are simulated again: an
episode is fully determined by the collection recipe and its index (`run_episode`), and
a segmentation render (`MurmEnv.object_views`) gives the task's object mask of every
frame and goal image. A re-rendered frame must equal the stored one pixel for pixel (PNG
is lossless); frames that do not (a dataset made by other code) are left out and counted.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import torch

from lerobot_murm.checkpointing import write_atomic
from lerobot_murm.collection import read_recipe, run_episode
from lerobot_murm.device import resolve_device
from lerobot_murm.progress import progress
from lerobot_murm.vqvae.frames import decode_pngs, open_dataset, read_camera_pngs
from lerobot_murm.vqvae.modeling_vqvae import VQVAE
from lerobot_murm.vqvae.train import heldout_episodes, save_reconstructions

OBJECT_PIXELS_FILE = "object_pixels.json"
OBJECT_FIGURE_FILE = "object_reconstructions.png"
MIN_VISIBLE_PIXELS = 4  # an object covering fewer pixels of a 48x48 view counts as not visible


@dataclass
class ObjectFrames:
    """One camera's goal images and frames of some episodes, with the object's mask."""

    camera: str
    images: np.ndarray  # (N, H, W, 3) uint8, as re-rendered
    masks: np.ndarray  # (N, H, W) bool, the task's object
    episode_index: np.ndarray  # (N,): per episode its goal image, then its frames in order


def resimulate_object_frames(root: Path, episodes: list[int], cameras: list[str]) -> dict[str, ObjectFrames]:
    """Simulate the dataset's `episodes` again and render every frame and goal of `cameras`
    with the object's mask."""
    recipe = read_recipe(Path(root))
    if recipe is None:
        raise ValueError(
            f"{root} has no collection recipe (meta/murm_collection.json): only a dataset made by "
            "`murm collect` can be simulated again"
        )
    missing = [c for c in cameras if c not in recipe.cameras]
    if missing:
        raise ValueError(f"the dataset at {root} has no camera(s) {missing}; its cameras: {list(recipe.cameras)}")
    recipe = replace(recipe, cameras=tuple(cameras))  # rendering does not change the physics
    views: dict[str, list] = {c: [] for c in cameras}
    episode_index: list[int] = []

    def observe(env, t: int) -> None:
        if t == 0:  # the goal images are rendered at reset, before the first frame
            record(env.object_views(at_goal=True))
        record(env.object_views())

    def record(object_views: dict) -> None:
        for camera in cameras:
            views[camera].append(object_views[camera])

    for episode in progress(iterable=episodes, desc="simulate held-out episodes", unit="ep"):
        run_episode(recipe, int(episode), observe)
        episode_index += [int(episode)] * (len(views[cameras[0]]) - len(episode_index))
    return {
        c: ObjectFrames(
            c, np.stack([v[0] for v in views[c]]), np.stack([v[1] for v in views[c]]), np.array(episode_index)
        )
        for c in cameras
    }


def stored_images(dataset, camera: str, frames: ObjectFrames) -> np.ndarray:
    """The dataset's own images for the rows of `frames` (episode frames in order, goal first)."""
    pngs = read_camera_pngs(dataset, camera)
    selected = []
    for episode in dict.fromkeys(frames.episode_index.tolist()):
        selected.append(pngs.goals[episode])
        selected += [pngs.frames[i] for i in np.flatnonzero(pngs.episode_index == episode)]
    return decode_pngs(selected)


@torch.no_grad()
def pixel_errors(model: VQVAE, images: np.ndarray, device: torch.device, batch: int = 1024) -> np.ndarray:
    """(N, H, W) squared reconstruction error per pixel (mean over colour), images in [0, 1]."""
    model.eval()
    errors = []
    for start in range(0, len(images), batch):
        x = torch.from_numpy(images[start : start + batch]).to(device)
        target = model.postprocess(model.preprocess(x))
        reconstruction = model.postprocess(model(x)["reconstruction"])
        errors.append((reconstruction - target).pow(2).mean(dim=1).cpu().numpy())
    return np.concatenate(errors)


def object_metrics(errors: np.ndarray, masks: np.ndarray) -> dict:
    """Reconstruction error on the whole image, on the object's pixels and on the rest, and how
    much of the object the camera sees."""
    counts = masks.sum(axis=(1, 2))

    def summary(selected: np.ndarray) -> dict:
        mse = float(errors[selected].mean()) if selected.any() else float("nan")
        return {"mse": mse, "psnr_db": float(10 * np.log10(1 / mse)) if selected.any() else float("nan")}

    return {
        "images": len(errors),
        "object_visible_fraction": float((counts >= MIN_VISIBLE_PIXELS).mean()),
        "object_pixels_mean": float(counts.mean()),
        "whole_image": summary(np.ones_like(masks)),
        "object": summary(masks),
        "background": summary(~masks),
    }


def check_encoders(
    repo_id: str, root: Path | None, encoder_dirs: list[Path], max_episodes: int | None = None, device: str = "cpu"
) -> list[dict]:
    """For each encoder, its held-out episodes' object-pixel metrics, written with a figure
    beside the checkpoint (`object_pixels.json`, `object_reconstructions.png`)."""
    device = resolve_device(device)
    models = {Path(d): VQVAE.load(Path(d), device=device) for d in encoder_dirs}  # a torn encoder fails first
    dataset = open_dataset(repo_id, root)
    all_episodes = np.arange(dataset.meta.total_episodes)
    held = {
        d: heldout_episodes(all_episodes, m.config.holdout_fraction, m.config.seed)[:max_episodes]
        for d, m in models.items()
    }
    episodes = sorted({int(e) for chosen in held.values() for e in chosen})
    cameras = list(dict.fromkeys(m.config.camera for m in models.values()))
    frames = resimulate_object_frames(Path(dataset.root), episodes, cameras)
    results = []
    for directory, model in models.items():
        camera_frames = _rows(frames[model.config.camera], held[directory])
        stored = stored_images(dataset, model.config.camera, camera_frames)
        reproduced = (stored == camera_frames.images).all(axis=(1, 2, 3))
        if not reproduced.any():
            raise ValueError(
                f"no {model.config.camera} frame simulated again equals the dataset's: {dataset.root} "
                "was collected by other code (scene, cameras or expert changed since)"
            )
        errors = pixel_errors(model, stored[reproduced], device)
        metrics = {
            "camera": model.config.camera,
            "dataset": str(dataset.root),
            "task": read_recipe(Path(dataset.root)).task,
            "episodes": [int(e) for e in held[directory]],
            "min_visible_pixels": MIN_VISIBLE_PIXELS,
            "reproduced_fraction": float(reproduced.mean()),
        } | object_metrics(errors, camera_frames.masks[reproduced])
        write_atomic(directory / OBJECT_PIXELS_FILE, (json.dumps(metrics, indent=2) + "\n").encode())
        save_object_reconstructions(
            model.cpu(), stored[reproduced], camera_frames.masks[reproduced], directory / OBJECT_FIGURE_FILE
        )
        results.append(metrics)
    return results


def _rows(frames: ObjectFrames, episodes: np.ndarray) -> ObjectFrames:
    keep = np.isin(frames.episode_index, episodes)
    return ObjectFrames(frames.camera, frames.images[keep], frames.masks[keep], frames.episode_index[keep])


def save_object_reconstructions(model: VQVAE, images: np.ndarray, masks: np.ndarray, path: Path) -> None:
    """Held-out frames where the object is visible (all frames if it never is) over their
    reconstructions, the object's outline drawn on both."""
    visible = masks.sum(axis=(1, 2)) >= MIN_VISIBLE_PIXELS
    if visible.any():
        images, masks = images[visible], masks[visible]
    title = "held-out frames, object outlined" if visible.any() else "held-out frames: the object is never visible"
    save_reconstructions(model, images, path, masks=masks, title=title)


def object_pixels_table(results: list[dict]) -> str:
    """One row per task and camera, as BENCHMARKS.md shows them."""
    lines = [
        "| task | camera | images | object visible | object pixels (mean) | PSNR whole image | PSNR object | "
        "PSNR background | reproduced |",
        "|---|---|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for r in results:
        lines.append(
            f"| {r['task']} | {r['camera']} | {r['images']} | {r['object_visible_fraction']:.0%} | "
            f"{r['object_pixels_mean']:.1f} | {r['whole_image']['psnr_db']:.1f} dB | "
            f"{r['object']['psnr_db']:.1f} dB | {r['background']['psnr_db']:.1f} dB | "
            f"{r['reproduced_fraction']:.0%} |"
        )
    return "\n".join(lines) + "\n"
