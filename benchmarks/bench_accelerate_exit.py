"""Does a two-process `accelerate launch ... lerobot-train --policy.type=murm` on the CPU always end?

Not a test (ten two-rank runs cost minutes). It builds the tiny pipeline of the tests with the
`murm` commands (6 place_in_box episodes, two 16x16 cameras, small VQ-VAEs, a latent dataset),
then launches the data-parallel training `--runs` times in a row (gloo, 3 steps, a checkpoint)
and counts the runs whose processes were still alive `--grace` seconds after rank 0 printed
"End of training": those hung at exit. A hung run's processes are dumped with py-spy when it is
installed, then killed with everything they started (tests/helpers/processes.py).

    .venv/bin/python benchmarks/bench_accelerate_exit.py [--runs 10] [--grace 60] [--keep DIR]
"""

from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).parents[1] / "tests" / "helpers"))
from processes import TAG_VARIABLE, kill_tagged, new_tag, tagged_processes

BIN = Path(sys.executable).parent
CAMERAS = ("global", "adjacent")
OFFLINE = {"HF_HUB_OFFLINE": "1", "WANDB_MODE": "disabled"}
PY_SPY = shutil.which("py-spy", path=f"{BIN}{os.pathsep}{os.environ.get('PATH', '')}")


def murm(*args) -> None:
    subprocess.run(
        [str(BIN / "murm"), *map(str, args)],
        check=True,
        env=os.environ | OFFLINE,
        stdout=subprocess.DEVNULL,
        timeout=900,
    )


def build_latents(base: Path) -> tuple[Path, Path]:
    demos, encoders = base / "demos", base / "vqvae"
    if not (base / "latents").exists():
        murm(
            "collect",
            "--task",
            "place_in_box",
            "--root",
            demos,
            "--episodes",
            6,
            "--workers",
            1,
            "--cameras",
            ",".join(CAMERAS),
            "--image-size",
            16,
            "--noise-std",
            0.1,
            "--overwrite",
        )
        for camera in CAMERAS:
            murm(
                "train-vqvae",
                "--dataset",
                demos,
                "--camera",
                camera,
                "--steps",
                30,
                "--batch-size",
                32,
                "--out",
                encoders / camera,
                "--device",
                "cpu",
            )
        murm(
            "encode",
            "--dataset",
            demos,
            "--encoders",
            *(encoders / c for c in CAMERAS),
            "--cache-dir",
            base / "cache",
            "--to-dataset",
            base / "latents",
        )
    return base / "latents", encoders


def launch(latents: Path, encoders: Path, out: Path, grace: float) -> tuple[bool, float, str]:
    """One two-rank training; (hung, seconds, py-spy dump of the hung processes)."""
    tag = new_tag()
    log = out.with_suffix(".log")
    args = [
        BIN / "accelerate",
        "launch",
        "--multi_gpu",
        "--num_processes",
        "2",
        "--num_machines",
        "1",
        "--mixed_precision",
        "no",
        "--dynamo_backend",
        "no",
        BIN / "lerobot-train",
        "--policy.type=murm",
        "--policy.method=dropout",
        f"--policy.cameras=[{','.join(CAMERAS)}]",
        f"--policy.encoder_dir={encoders}",
        "--dataset.repo_id=local/latents",
        f"--dataset.root={latents}",
        "--wandb.enable=false",
        "--batch_size=16",
        "--num_workers=0",
        "--steps=3",
        "--save_freq=3",
        "--log_freq=1",
        f"--output_dir={out}",
    ]
    start = time.monotonic()
    with open(log, "w") as sink:
        process = subprocess.Popen(
            [str(a) for a in args],
            env=os.environ | OFFLINE | {TAG_VARIABLE: tag},
            stdout=sink,
            stderr=subprocess.STDOUT,
        )
        ended_at = None
        while process.poll() is None or tagged_processes(tag):
            if ended_at is None and "End of training" in log.read_text():
                ended_at = time.monotonic()
            if (ended_at and time.monotonic() - ended_at > grace) or time.monotonic() - start > 600:
                dump = (
                    "".join(
                        subprocess.run(
                            [PY_SPY, "dump", "--native", "--pid", str(p.pid)], capture_output=True, text=True
                        ).stdout
                        for p in tagged_processes(tag)
                    )
                    if PY_SPY
                    else ""
                )
                kill_tagged(tag)
                process.wait()
                return True, time.monotonic() - start, dump
            time.sleep(0.5)
    if process.returncode != 0:
        raise SystemExit(f"run failed (exit {process.returncode}); see {log}")
    return False, time.monotonic() - start, ""


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=10)
    parser.add_argument(
        "--grace", type=float, default=60.0, help="seconds after 'End of training' before a run counts as hung"
    )
    parser.add_argument(
        "--keep", type=Path, help="build (or reuse) the tiny pipeline here instead of a temporary folder"
    )
    args = parser.parse_args()
    base = args.keep or Path(tempfile.mkdtemp(prefix="murm-accelerate-exit-"))
    latents, encoders = build_latents(base)
    hung = 0
    for run in range(1, args.runs + 1):
        out = base / f"run{run}"
        shutil.rmtree(out, ignore_errors=True)
        was_hung, seconds, dump = launch(latents, encoders, out, args.grace)
        hung += was_hung
        print(f"run {run}: {'HUNG at exit' if was_hung else 'ended'} ({seconds:.0f} s)", flush=True)
        if dump:
            print(dump, flush=True)
    print(f"{hung} of {args.runs} two-process runs hung at exit")
    if not args.keep:
        shutil.rmtree(base, ignore_errors=True)


if __name__ == "__main__":
    main()
