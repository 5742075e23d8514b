"""Evaluation time with the simulators in worker processes against in the evaluating process,
one evaluation alone, `--jobs` at once (as `murm reproduce --jobs N` runs them), and one
beside a busy one-thread process (a grid's other job, training).

Not a test. Give it a trained policy (a `pretrained_model` folder) and copy the lines into
BENCHMARKS.md:

    .venv/bin/python benchmarks/bench_eval_processes.py CHECKPOINT [--task place_in_box] \\
        [--episodes 12] [--seeds 3] [--mask-p 0.1] [--jobs 2] [--repeats 2]

The policy is evaluated as a stack of `--seeds` copies with 4 simulators per seed (a stacked
cell's evaluation) on validation episodes, every evaluation process with one torch thread
(a grid job's share on a machine with as many cores as jobs). Both ways must give the same
successes.
"""

from __future__ import annotations

import argparse
import statistics
import time
from concurrent.futures import ProcessPoolExecutor
from multiprocessing import get_context

import torch

from lerobot_murm.policy.modeling_murm import MurmPolicy
from lerobot_murm.policy.precision import cpu_description
from lerobot_murm.training.evaluate import VALIDATION_SEED, Evaluator, evaluation_seeds


def evaluate(checkpoint: str, task: str, episodes: int, seeds: int, mask_p: float, processes: bool) -> tuple:
    """One stacked evaluation in this process: its seconds and every seed's successes."""
    torch.set_num_threads(1)
    policies = [MurmPolicy.from_pretrained(checkpoint) for _ in range(seeds)]
    image_size = policies[0].config.encoder_config(policies[0].cameras[0]).image_size
    with Evaluator(task, policies[0].cameras, image_size, 4, seeds, processes=processes) as evaluator:
        start = time.perf_counter()
        results = evaluator.evaluate(policies, evaluation_seeds(episodes, VALIDATION_SEED), mask_p)
        seconds = time.perf_counter() - start
    return seconds, tuple(tuple(r.successes) for r in results)


def busy(seconds: float) -> float:
    """A trainer's stand-in: one thread of 256x1024 @ 1024x1024 matmuls for `seconds`; their rate."""
    torch.set_num_threads(1)
    a, b = torch.randn(256, 1024), torch.randn(1024, 1024)
    start, n = time.perf_counter(), 0
    while time.perf_counter() - start < seconds:
        a @ b
        n += 1
    return n / (time.perf_counter() - start)


def beside_busy(pool: ProcessPoolExecutor, job: tuple, processes: bool) -> tuple:
    """One evaluation while a busy process runs: its seconds and successes, and the busy rate."""
    seconds, outcome = pool.submit(evaluate, *job, processes).result()  # warm: how long to keep busy
    rate = pool.submit(busy, seconds)
    seconds, outcome = pool.submit(evaluate, *job, processes).result()
    return seconds, outcome, rate.result()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("checkpoint")
    parser.add_argument("--task", default="place_in_box")
    parser.add_argument("--episodes", type=int, default=12)
    parser.add_argument("--seeds", type=int, default=3)
    parser.add_argument("--mask-p", type=float, default=0.1)
    parser.add_argument("--jobs", type=int, default=2)
    parser.add_argument("--repeats", type=int, default=2)
    args = parser.parse_args()
    job = (args.checkpoint, args.task, args.episodes, args.seeds, args.mask_p)
    ways = {"worker processes": True, "in process": False}
    seconds = {(way, n): [] for way in ways for n in (1, args.jobs)}
    successes = set()
    with ProcessPoolExecutor(args.jobs, mp_context=get_context("spawn")) as pool:
        for _ in range(args.repeats):
            for way, processes in ways.items():
                for n in (1, args.jobs):  # n evaluations at once, each in its own process
                    for s, outcome in pool.map(evaluate, *zip(*[(*job, processes)] * n, strict=True)):
                        seconds[(way, n)].append(s)
                        successes.add(outcome)
        alone = pool.submit(busy, 10.0).result()
        beside = {way: beside_busy(pool, job, processes) for way, processes in ways.items()}
        successes |= {outcome for _, outcome, _ in beside.values()}
    if len(successes) != 1:
        raise SystemExit(f"the two ways gave different successes: {successes}")
    median = {key: statistics.median(values) for key, values in seconds.items()}
    print(
        f"{args.seeds} seeds x {args.episodes} episodes, masking {args.mask_p:g}, 4 simulators per seed, "
        f"1 torch thread per evaluation, {cpu_description()}"
    )
    for n in (1, args.jobs):
        workers, here = median[("worker processes", n)], median[("in process", n)]
        rounded = {way: [round(s, 1) for s in seconds[(way, n)]] for way in ways}
        print(
            f"{n} at once: worker processes {rounded['worker processes']} s, in process {rounded['in process']} s; "
            f"median ratio in process / worker processes {here / workers:.2f}"
        )
    for way, (s, _, rate) in beside.items():
        print(f"beside a busy process, {way}: evaluation {s:.1f} s, the busy one at {rate / alone:.2f} of its rate")


if __name__ == "__main__":
    main()
