"""`murm demo`: look at the simulator and the demonstrations before anything is trained.

Writes `cameras.png` (for each task: the five camera images at reset over the five
goal images) and `rollout_<task>.png` (frames of one seeded scripted-expert episode),
prints each episode's outcome, and collects a small demonstration dataset
(`demonstrations/`, rebuilt on every run) with `murm collect`'s own code.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
from matplotlib.figure import Figure

from lerobot_murm.collection import CollectConfig, collect
from lerobot_murm.env import CAMERA_NAMES, EPISODE_STEPS, TASK_NAMES, MurmEnv
from lerobot_murm.expert import ScriptedExpert
from lerobot_murm.features import goal_key

ROLLOUT_FRAMES = 8
DEMO_EPISODES = 10


def save_camera_grid(path: Path, seed: int, image_size: int = 48) -> None:
    """One row of current images and one of goal images per task."""
    fig = Figure(figsize=(2.0 * len(CAMERA_NAMES), 4.2 * len(TASK_NAMES)))
    axes = fig.subplots(2 * len(TASK_NAMES), len(CAMERA_NAMES))
    for row, task in enumerate(TASK_NAMES):
        env = MurmEnv(task=task, image_size=image_size)
        obs, _ = env.reset(seed=seed)
        env.close()
        for col, camera in enumerate(CAMERA_NAMES):
            for offset, key, label in ((0, camera, "now"), (1, goal_key(camera), "goal")):
                ax = axes[2 * row + offset, col]
                ax.imshow(obs["pixels"][key], interpolation="nearest")
                ax.set_xticks([]), ax.set_yticks([])
                ax.set_title(f"{task}\n{camera} ({label})" if col == 0 else f"{camera} ({label})", fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def run_expert_episode(task: str, seed: int, frames_path: Path) -> dict:
    """One seeded expert episode; saves evenly spaced `render()` frames as a strip."""
    env = MurmEnv(task=task, render_views=False)  # the scene alone: the camera grid is cameras.png
    expert = ScriptedExpert(task)
    obs, _ = env.reset(seed=seed)
    keep = set(np.linspace(0, EPISODE_STEPS - 1, ROLLOUT_FRAMES).astype(int).tolist())
    frames, success, first_success = [], False, None
    start = time.perf_counter()
    for step in range(EPISODE_STEPS):
        obs, _, _, _, info = env.step(expert.act(obs))
        if step in keep:
            frames.append((step, env.render()))
        success = info["is_success"]
        if success and first_success is None:
            first_success = step
    elapsed = time.perf_counter() - start
    env.close()

    fig = Figure(figsize=(2.0 * len(frames), 2.3))
    axes = fig.subplots(1, len(frames))
    for ax, (step, frame) in zip(axes, frames, strict=True):
        ax.imshow(frame)
        ax.set_xticks([]), ax.set_yticks([])
        ax.set_title(f"step {step}", fontsize=8)
    fig.suptitle(f"{task}, seed {seed}: {'success' if success else 'failure'}", fontsize=10)
    fig.tight_layout()
    fig.savefig(frames_path, dpi=100)
    return {
        "task": task,
        "seed": seed,
        "success": success,
        "first_success_step": first_success,
        "steps_per_s": EPISODE_STEPS / elapsed,
    }


def run_demo(out_dir: Path, seed: int = 0) -> list[dict]:
    out_dir.mkdir(parents=True, exist_ok=True)
    save_camera_grid(out_dir / "cameras.png", seed)
    print(f"wrote {out_dir / 'cameras.png'}")
    results = []
    for task in TASK_NAMES:
        result = run_expert_episode(task, seed, out_dir / f"rollout_{task}.png")
        results.append(result)
        print(
            f"{task:<22} seed {seed}  success={result['success']!s:<5}  "
            f"first success at step {result['first_success_step']}  "
            f"({result['steps_per_s']:.0f} env steps/s, 5 cameras + goals)"
        )
    dataset = out_dir / "demonstrations"
    summary = collect(
        CollectConfig(task="place_in_box", root=dataset, episodes=DEMO_EPISODES, workers=2, overwrite=True)
    )
    print(
        f"collected {summary['episodes']} place_in_box episodes into {dataset} "
        f"(expert success {summary['success_rate']:.0%})"
    )
    return results
