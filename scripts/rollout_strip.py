"""A picture of trained policies on one evaluation episode, one row per policy.

The stock `lerobot-eval` runs each checkpoint for one episode on the same seed (so the same
scene and goal), and the overview frames of its rollout video at the chosen steps go into a
row under the policy's label:

    RUNS=outputs/murm/runs/table4/place_in_box; LAST=seed0/checkpoints/last/pretrained_model
    .venv/bin/python scripts/rollout_strip.py --task place_in_box --seed 200000 \\
        --policy "concatenation, training seed 0=$RUNS/concat-global+adjacent/$LAST" \\
        --policy "MURM dropout, training seed 0=$RUNS/dropout-global+adjacent/$LAST" \\
        --out results/table4/rollouts_concat_vs_dropout.png

Use a validation seed (200,000-200,099): a picture is something to look at, and nothing is
looked at on the test episodes before the numbers are reported.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import av
import numpy as np
from PIL import Image, ImageDraw

OVERVIEW = 256  # the video frame's left square: the scene from the front (env/video_frame.py)
LABEL_HEIGHT = 18


def rollout_frames(
    checkpoint: Path, task: str, seed: int, steps: list[int], image_size: int = 48
) -> tuple[list[np.ndarray], bool]:
    """The overview frames at `steps` of one `lerobot-eval` episode, and whether it succeeded."""
    cameras = json.loads((checkpoint / "config.json").read_text())["cameras"]
    with tempfile.TemporaryDirectory() as out:
        evaluated = subprocess.run(
            [
                str(Path(sys.executable).parent / "lerobot-eval"),
                f"--policy.path={checkpoint}",
                "--env.type=murm",
                f"--env.task={task}",
                f"--env.cameras=[{','.join(cameras)}]",
                f"--env.image_size={image_size}",
                "--eval.n_episodes=1",
                "--eval.batch_size=1",
                f"--seed={seed}",
                f"--output_dir={out}",
            ],
            capture_output=True,
            text=True,
            env={**os.environ, "HF_HUB_OFFLINE": "1"},
        )
        if evaluated.returncode != 0:
            last = (evaluated.stderr.strip().splitlines() or ["(no output)"])[-1]
            sys.exit(f"rollout_strip: lerobot-eval failed on {checkpoint}: {last}")
        overall = json.loads((Path(out) / "eval_info.json").read_text())["overall"]
        with av.open(overall["video_paths"][0]) as container:
            frames = [frame.to_ndarray(format="rgb24") for frame in container.decode(video=0)]
    picked = [frames[min(step, len(frames) - 1)][:, :OVERVIEW] for step in steps]
    return picked, overall["pc_success"] > 0


def strip(rows: list[tuple[str, list[np.ndarray]]]) -> Image.Image:
    """Rows of frames, each under its label."""
    width = sum(frame.shape[1] for frame in rows[0][1])
    height = OVERVIEW + LABEL_HEIGHT
    picture = Image.new("RGB", (width, height * len(rows)), "white")
    draw = ImageDraw.Draw(picture)
    for r, (label, frames) in enumerate(rows):
        draw.text((4, r * height + 3), label, fill="black")
        x = 0
        for frame in frames:
            picture.paste(Image.fromarray(frame), (x, r * height + LABEL_HEIGHT))
            x += frame.shape[1]
    return picture


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--task", required=True)
    parser.add_argument(
        "--seed", type=int, default=200_000, help="the episode's seed (default: the first validation seed)"
    )
    parser.add_argument(
        "--policy",
        action="append",
        required=True,
        metavar="LABEL=CHECKPOINT",
        help="a label and a pretrained_model folder; once per row",
    )
    parser.add_argument("--steps", type=int, nargs="+", default=[0, 15, 30, 50, 75, 99])
    parser.add_argument("--image-size", type=int, default=48, help="the cameras' size the policies were trained on")
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args()
    rows = []
    for entry in args.policy:
        label, separator, checkpoint = entry.rpartition("=")
        if not separator or not (Path(checkpoint) / "config.json").exists():
            parser.error(f"--policy {entry!r}: expected LABEL=CHECKPOINT, a folder with a config.json")
        frames, success = rollout_frames(Path(checkpoint), args.task, args.seed, args.steps, args.image_size)
        steps = "/".join(map(str, args.steps))
        outcome = "success" if success else "failure"
        rows.append((f"{label}: episode seed {args.seed}, steps {steps}, {outcome}", frames))
        print(f"{label}: {'success' if success else 'failure'}", flush=True)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    partial = args.out.with_name(f".{args.out.name}.partial")
    strip(rows).save(partial, format="PNG")
    partial.replace(args.out)  # a kill while saving leaves the picture that was there whole
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
