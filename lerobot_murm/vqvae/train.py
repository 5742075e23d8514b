"""`murm train-vqvae`: fit one camera's VQ-VAE on its frames and goal images (any camera
stream of a LeRobotDataset, brought to the encoder's side by `resize.py`).

Whole episodes are held out for validation. The checkpoint folder gets the weights and
config (safetensors + JSON), `metrics.json` (held-out MSE and PSNR, codebook usage,
training speed) and `reconstructions.png` (held-out originals over reconstructions,
the paper's Figure 4).
"""

from __future__ import annotations

import json
from dataclasses import asdict, replace
from pathlib import Path

import numpy as np
import torch
from matplotlib.figure import Figure

from lerobot_murm.checkpointing import CheckpointError, load_state, save_state, write_atomic
from lerobot_murm.device import resolve_device
from lerobot_murm.locking import exclusive
from lerobot_murm.training_loop import TrainingInterrupted, TrainingLoop
from lerobot_murm.vqvae.configuration_vqvae import VQVAEConfig
from lerobot_murm.vqvae.encoder_files import METRICS_FILE
from lerobot_murm.vqvae.frames import (
    CameraFrames,
    camera_stream,
    dataset_fingerprint,
    load_camera_frames,
    open_dataset,
)
from lerobot_murm.vqvae.modeling_vqvae import VQVAE

LOG_EVERY = 50
CHECKPOINT_EVERY = 250  # steps between resume states (about 30 s of training on 2 cores)
STATE_FILE = "training_state.pt"


def heldout_episodes(episode_index: np.ndarray, fraction: float, seed: int) -> np.ndarray:
    """The whole episodes kept out of an encoder's training (none if there is only one)."""
    episodes = np.unique(episode_index)
    n_held = max(1, round(fraction * len(episodes))) if len(episodes) > 1 else 0
    return np.random.default_rng(seed).choice(episodes, size=n_held, replace=False)


def split_episodes(frames: CameraFrames, fraction: float, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Training and held-out image arrays; held-out = all frames and goals of a few whole episodes."""
    held = heldout_episodes(frames.episode_index, fraction, seed)
    n_held = len(held)
    in_held = np.isin(frames.episode_index, held)
    goal_held = np.isin(np.arange(len(frames.goals)), held)
    train = np.concatenate([frames.images[~in_held], frames.goals[~goal_held]])
    holdout = np.concatenate([frames.images[in_held], frames.goals[goal_held]]) if n_held else frames.images[:0]
    return train, holdout


def codebook_usage(indices: torch.Tensor, codebook_size: int) -> tuple[float, int]:
    """Perplexity of the code distribution and the number of codes never used."""
    counts = torch.bincount(indices.reshape(-1), minlength=codebook_size).float()
    probs = counts / counts.sum()
    perplexity = torch.exp(-(probs[probs > 0] * probs[probs > 0].log()).sum()).item()
    return perplexity, int((counts == 0).sum())


@torch.no_grad()
def evaluate(model: VQVAE, images: np.ndarray, device: torch.device, batch: int = 1024) -> dict:
    model.eval()
    squared, indices = [], []
    for start in range(0, len(images), batch):
        x = torch.from_numpy(images[start : start + batch]).to(device)
        out = model(x)
        target = model.postprocess(model.preprocess(x))
        squared.append((model.postprocess(out["reconstruction"]) - target).pow(2).mean(dim=(1, 2, 3)).cpu())
        indices.append(out["indices"].cpu())
    mse = torch.cat(squared)
    perplexity, dead = codebook_usage(torch.cat(indices), model.config.codebook_size)
    model.train()
    return {
        "mse": float(mse.mean()),
        "psnr_db": float(10 * torch.log10(1.0 / mse.mean())),
        "perplexity": perplexity,
        "unused_codes": dead,
        "images": len(images),
    }


def save_reconstructions(
    model: VQVAE,
    images: np.ndarray,
    path: Path,
    count: int = 12,
    masks: np.ndarray | None = None,
    title: str = "held-out episodes",
) -> None:
    """Originals over reconstructions; `masks` (N, H, W), if given, are outlined on both."""
    chosen = np.linspace(0, len(images) - 1, count).astype(int)
    picks = images[chosen]
    with torch.no_grad():
        model.eval()
        recon = model.postprocess(model(torch.from_numpy(picks))["reconstruction"]).permute(0, 2, 3, 1).numpy()
        model.train()
    fig = Figure(figsize=(1.2 * count, 2.7))
    axes = fig.subplots(2, count)
    for i in range(count):
        for row, image in ((0, picks[i]), (1, recon[i])):
            axes[row, i].imshow(image, interpolation="nearest")
            if masks is not None and masks[chosen[i]].any():
                axes[row, i].contour(masks[chosen[i]], levels=[0.5], colors="cyan", linewidths=0.7)
            axes[row, i].set_xticks([]), axes[row, i].set_yticks([])
    axes[0, 0].set_ylabel("original", fontsize=8)
    axes[1, 0].set_ylabel("VQ-VAE", fontsize=8)
    fig.suptitle(f"{model.config.camera} camera, {title}", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def _save_state(
    path: Path, model: VQVAE, optimizer, schedule, rng: np.random.Generator, step: int, elapsed_s: float
) -> None:
    """Everything a stopped run needs to continue exactly where it was (written atomically)."""
    state = {
        "step": step,
        "config": asdict(model.config),
        "model": model.state_dict(),
        "optimizer": optimizer.state_dict(),
        "schedule": schedule.state_dict(),
        "rng": rng.bit_generator.state,
        "torch_rng": torch.get_rng_state(),
        "elapsed_s": elapsed_s,
    }
    save_state(state, path)


def _check_interrupted_has_state(out_dir: Path, state_path: Path) -> None:
    """An interrupted encoder without its resume state is an error, not a silent restart."""
    metrics = out_dir / METRICS_FILE
    if metrics.exists() and not state_path.exists() and json.loads(metrics.read_text()).get("interrupted"):
        raise CheckpointError(
            f"{out_dir} holds an interrupted encoder but its resume state {state_path.name} is missing; "
            f"move {out_dir} away to train afresh"
        )


def train_vqvae(
    repo_id: str, root: Path | None, camera: str, out_dir: Path, config: VQVAEConfig | None = None, device: str = "auto"
) -> dict:
    """Train, evaluate and save; returns the metrics.

    Ctrl-C / SIGTERM stop after the current step: the encoder so far is saved (marked
    `interrupted` in metrics.json) with `training_state.pt`, and `TrainingInterrupted` is
    raised; the same call later resumes from that state and ends with the same weights as
    an uninterrupted run. The state is also written every CHECKPOINT_EVERY steps. One
    writer per encoder folder (locking.py).
    """
    with exclusive(Path(out_dir)):
        return _train_vqvae(repo_id, root, camera, Path(out_dir), config, device)


def _train_vqvae(
    repo_id: str, root: Path | None, camera: str, out_dir: Path, config: VQVAEConfig | None, device: str
) -> dict:
    device = resolve_device(device)
    dataset = open_dataset(repo_id, root)
    stream = camera_stream(dataset, camera)
    config = config or VQVAEConfig()
    side = stream.side(config.image_size)
    frames = load_camera_frames(dataset, stream, side)
    config = replace(
        config,
        camera=stream.camera,
        image_size=side,
        dataset={"repo_id": repo_id, "root": str(dataset.root), "fingerprint": dataset_fingerprint(dataset)},
        source_key=stream.key,
        source_size=list(stream.size),
    )
    train_images, holdout = split_episodes(frames, config.holdout_fraction, config.seed)
    torch.manual_seed(config.seed)
    rng = np.random.default_rng(config.seed)
    model = VQVAE(config).to(device)
    optimizer = torch.optim.Adam(model.parameters(), lr=config.learning_rate)
    schedule = torch.optim.lr_scheduler.CosineAnnealingLR(optimizer, T_max=config.steps)

    out_dir.mkdir(parents=True, exist_ok=True)
    state_path = out_dir / STATE_FILE
    done, earlier_s = 0, 0.0
    _check_interrupted_has_state(out_dir, state_path)
    if state_path.exists():
        state = load_state(state_path, device)
        if state["config"] == asdict(config):
            model.load_state_dict(state["model"])
            optimizer.load_state_dict(state["optimizer"])
            schedule.load_state_dict(state["schedule"])
            rng.bit_generator.state = state["rng"]
            torch.set_rng_state(state["torch_rng"])
            done, earlier_s = state["step"], state["elapsed_s"]
            print(f"vq-vae {config.camera}: resuming from step {done} ({state_path})")
        else:
            print(f"vq-vae {config.camera}: {state_path} is from other settings or data; starting afresh")
    loop = TrainingLoop(config.steps, start=done, earlier_s=earlier_s, desc=f"vq-vae {config.camera}")
    with loop:
        while loop.running():
            batch = torch.from_numpy(train_images[rng.integers(0, len(train_images), config.batch_size)]).to(device)
            out = model(batch)
            optimizer.zero_grad(set_to_none=True)
            out["loss"].backward()
            optimizer.step()
            schedule.step()
            if loop.every(LOG_EVERY):
                perplexity, dead = codebook_usage(out["indices"], config.codebook_size)
                mse = out["recon_loss"].item()  # on the [-0.5, 0.5] range = MSE on [0, 1]
                loop.show(mse=f"{mse:.5f}", psnr=f"{10 * np.log10(1 / mse):.1f}", ppl=f"{perplexity:.0f}", dead=dead)
            loop.advance()
            if loop.every(CHECKPOINT_EVERY) and not loop.finished:
                _save_state(state_path, model, optimizer, schedule, rng, loop.step, loop.elapsed())
    if loop.interrupted:
        _save_state(state_path, model, optimizer, schedule, rng, loop.step, loop.elapsed())

    model.save(out_dir)
    metrics = {
        "camera": config.camera,
        "steps": loop.step,
        "interrupted": loop.interrupted,
        "train_seconds": loop.elapsed(),
        "train_images_per_s": loop.steps_per_s() * config.batch_size,
        "train_images": len(train_images),
        "heldout": evaluate(model, holdout if len(holdout) else train_images[:1024], device),
        "device": str(device),
    }
    write_atomic(out_dir / METRICS_FILE, (json.dumps(metrics, indent=2) + "\n").encode())
    save_reconstructions(model.cpu(), holdout if len(holdout) else train_images, out_dir / "reconstructions.png")
    if loop.interrupted:
        raise TrainingInterrupted(
            f"stopped at step {loop.step} of {config.steps} (the encoder so far is saved in {out_dir}); "
            "run the same command again to resume"
        )
    state_path.unlink(missing_ok=True)
    return metrics
