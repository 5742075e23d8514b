"""Evaluation time with each simulator held once its episode has succeeded (`HeldAfterSuccess`,
as `Evaluator` does) against simulating every step of every episode (as it did before session
12), same process, alternating.

Not a test. Give it trained policies (`pretrained_model` folders, one per seed of a stack) and
copy the lines into BENCHMARKS.md:

    .venv/bin/python benchmarks/bench_eval_held.py CHECKPOINT [CHECKPOINT ...] [--task place_in_box] \\
        [--episodes 12] [--mask-p 0.0 0.1] [--repeats 3]

The policies are evaluated as one stack (4 simulators per seed, as a stacked cell evaluates) on
validation episodes with one torch thread (a grid job's share of a 2-core machine, so the
simulators step in this process); both ways must give the same successes at every masking level.
"""

from __future__ import annotations

import argparse
import statistics
import time

import torch

from lerobot_murm.policy.modeling_murm import MurmPolicy
from lerobot_murm.policy.precision import cpu_description
from lerobot_murm.training.evaluate import VALIDATION_SEED, Evaluator, evaluation_seeds


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("checkpoints", nargs="+")
    parser.add_argument("--task", default="place_in_box")
    parser.add_argument("--episodes", type=int, default=12)
    parser.add_argument("--mask-p", type=float, nargs="+", default=[0.0, 0.1])
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    torch.set_num_threads(1)
    policies = [MurmPolicy.from_pretrained(checkpoint) for checkpoint in args.checkpoints]
    episodes = evaluation_seeds(args.episodes, VALIDATION_SEED)
    image_size = policies[0].config.encoder_config(policies[0].cameras[0]).image_size
    print(
        f"cameras {'+'.join(policies[0].cameras)}, {len(policies)} seeds x {args.episodes} episodes, "
        f"1 torch thread, {cpu_description()}"
    )
    with Evaluator(args.task, policies[0].cameras, image_size, 4, len(policies)) as evaluator:
        for mask_p in args.mask_p:
            seconds: dict[bool, list[float]] = {False: [], True: []}
            successes: dict[bool, set] = {False: set(), True: set()}
            for _ in range(args.repeats):
                for held in seconds:
                    evaluator.hold_succeeded = held
                    start = time.perf_counter()
                    results = evaluator.evaluate(policies, episodes, mask_p)
                    seconds[held].append(time.perf_counter() - start)
                    successes[held].add(tuple(tuple(r.successes) for r in results))
            if successes[True] != successes[False] or len(successes[True]) != 1:
                raise SystemExit(f"mask_p {mask_p}: the two ways gave different successes: {successes}")
            rate = statistics.mean(s for seed in next(iter(successes[True])) for s in seed)
            every, held = statistics.median(seconds[False]), statistics.median(seconds[True])
            print(
                f"mask_p {mask_p}: success {rate:.0%} (the same both ways); every step simulated "
                f"{[round(s, 1) for s in seconds[False]]} s; held after success "
                f"{[round(s, 1) for s in seconds[True]]} s; median ratio {held / every:.2f}"
            )


if __name__ == "__main__":
    main()
