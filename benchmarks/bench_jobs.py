"""Whole-grid wall time of `murm reproduce` with `--jobs 1` and `--jobs N`, same grid slice.

Not a test. Run it on an otherwise idle machine and copy the table into BENCHMARKS.md:

    .venv/bin/python benchmarks/bench_jobs.py [--jobs 2] [--runs 2] [--steps 1000] [--repeats 2] \\
        [--final-eval-episodes 2]

The slice: the smoke grid's single-view cell on `--runs` seeds (48x48 images, batch 256,
the final evaluation cut to 2 episodes so that training dominates). The dataset and the
encoder are built once before timing; each timed sitting then trains every run of the
slice from scratch (the runs and results of the previous sitting are deleted) and
includes the executor's start-up. Sittings alternate between 1 and N jobs so that both
see the same machine noise; the medians are reported, and their ratio.
"""

from __future__ import annotations

import argparse
import json
import shutil
import statistics
import subprocess
import tempfile
import time
from pathlib import Path

from lerobot_murm.experiments.configuration_reproduce import load_reproduce_config
from lerobot_murm.experiments.executors import make_executor, threads_per_job
from lerobot_murm.experiments.reproduce import reproduce

REPO = Path(__file__).parents[1]


def sitting(config, jobs: int) -> tuple[float, list[float]]:
    """The grid's wall time and each run's median updates/s."""
    shutil.rmtree(Path(config.work_dir) / "runs", ignore_errors=True)
    shutil.rmtree(Path(config.results_dir), ignore_errors=True)
    start = time.perf_counter()
    executor = make_executor("local", jobs)
    try:
        reproduce(config, executor)
    finally:
        executor.close()
    wall = time.perf_counter() - start
    runs = sorted((Path(config.results_dir) / config.name / "runs").glob("*.json"))
    return wall, [json.loads(p.read_text())["train_steps_per_s"] for p in runs]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--jobs", type=int, default=2)
    parser.add_argument("--runs", type=int, default=2, help="training runs in the slice (seeds 0, 1, ...)")
    parser.add_argument("--steps", type=int, default=1000, help="updates per run")
    parser.add_argument("--repeats", type=int, default=2)
    parser.add_argument(
        "--final-eval-episodes",
        type=int,
        default=2,
        help="test episodes per run (a grid's runs evaluate 100; the simulator is single-threaded)",
    )
    args = parser.parse_args()

    with tempfile.TemporaryDirectory() as tmp:
        config = load_reproduce_config(
            REPO / "configs/reproduce/smoke.yaml",
            [
                f"--work_dir={tmp}/work",
                f"--results_dir={tmp}/results",
                f"--seeds={list(range(args.runs))}",
                "--collection.episodes=10",
                "--vqvae.steps=50",
                f"--train.steps={args.steps}",
                f"--train.eval_every={args.steps}",
                f"--train.log_every={args.steps // 4}",
                f"--train.final_eval_episodes={args.final_eval_episodes}",
                "--train.eval_envs=1",
            ],
        )
        config.cells = [cell for cell in config.cells if cell.method == "single"]
        config.cells[0].eval_mask_p = [0.0]
        sitting(config, 1)  # untimed: collects the dataset and trains the encoder (and warms the caches)
        times: dict[int, list[float]] = {1: [], args.jobs: []}
        rates: dict[int, list[float]] = {1: [], args.jobs: []}
        for _ in range(args.repeats):
            for jobs in times:
                wall, run_rates = sitting(config, jobs)
                times[jobs].append(wall)
                rates[jobs] += run_rates
                print(f"jobs {jobs}: {wall:.1f} s, updates/s per run {run_rates}")
    model = subprocess.run("lscpu | grep 'Model name'", shell=True, capture_output=True, text=True).stdout.strip()
    print(
        f"\n{model}\n{args.runs} runs of {args.steps} updates and {args.final_eval_episodes} test episodes, "
        f"single view, batch 256; {args.repeats} sittings each"
    )
    print("| jobs | torch threads per run | grid wall time (median) | all sittings | updates/s per run (median) |")
    print("|---:|---:|---:|---|---:|")
    for jobs, seconds in times.items():
        threads = threads_per_job(jobs) if jobs > 1 else "all"
        print(
            f"| {jobs} | {threads} | {statistics.median(seconds):.1f} s | {', '.join(f'{s:.1f}' for s in seconds)} "
            f"| {statistics.median(rates[jobs]):.1f} |"
        )
    print(f"--jobs {args.jobs} over --jobs 1: {statistics.median(times[1]) / statistics.median(times[args.jobs]):.2f}x")


if __name__ == "__main__":
    main()
