"""Evaluation time with each episode's goal images encoded once (at its reset, as `Evaluator`
does) against encoded at every step (as it did before session 7), same process, alternating.

Not a test. Give it a trained policy (a `pretrained_model` folder) and copy the line into
BENCHMARKS.md:

    .venv/bin/python benchmarks/bench_eval_goals.py CHECKPOINT [--task place_in_box] \\
        [--episodes 8] [--seeds 3] [--repeats 3]

The policy is evaluated as a stack of `--seeds` copies (one pool of 4 workers per seed, as a
stacked cell evaluates) on validation episodes. "every step" replaces the evaluator's one goal
encoding per episode by the batch's goal images reaching `act_together` at every step, the
path before the change; both must give the same successes.
"""

from __future__ import annotations

import argparse
import statistics
import time

import torch

import lerobot_murm.training.evaluate as evaluate
from lerobot_murm.policy.modeling_murm import MurmPolicy
from lerobot_murm.policy.precision import cpu_description
from lerobot_murm.training.evaluate import VALIDATION_SEED, Evaluator, evaluation_seeds

ONCE = (MurmPolicy.goal_state, evaluate.act_together, Evaluator._batch)


def encode_goals(every_step: bool) -> None:
    """Switch the evaluator between encoding goals once per episode and at every step."""
    goal_state, act_together, batch = ONCE
    if not every_step:
        MurmPolicy.goal_state, evaluate.act_together, Evaluator._batch = ONCE
        return

    def act_on_goal_images(policies, observation, actors=None, goals=None):
        return act_together(policies, observation, actors, goal_state(policies[0], observation))

    MurmPolicy.goal_state = lambda self, observation: None  # the evaluator's once-per-episode call
    evaluate.act_together = act_on_goal_images
    Evaluator._batch = lambda self, observation, device, goals=True: batch(self, observation, device, True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("checkpoint")
    parser.add_argument("--task", default="place_in_box")
    parser.add_argument("--episodes", type=int, default=8)
    parser.add_argument("--seeds", type=int, default=3)
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    torch.set_num_threads(1)
    policies = [MurmPolicy.from_pretrained(args.checkpoint) for _ in range(args.seeds)]
    episodes = evaluation_seeds(args.episodes, VALIDATION_SEED)
    seconds: dict[str, list[float]] = {"every step": [], "once": []}
    successes: dict[str, set] = {"every step": set(), "once": set()}
    with Evaluator(
        args.task,
        policies[0].cameras,
        policies[0].config.encoder_config(policies[0].cameras[0]).image_size,
        4,
        args.seeds,
    ) as evaluator:
        for _ in range(args.repeats):
            for name in seconds:
                encode_goals(every_step=name == "every step")
                start = time.perf_counter()
                results = evaluator.evaluate(policies, episodes)
                seconds[name].append(time.perf_counter() - start)
                successes[name].add(tuple(tuple(r.successes) for r in results))
    encode_goals(every_step=False)
    if successes["once"] != successes["every step"] or len(successes["once"]) != 1:
        raise SystemExit(f"the two ways gave different successes: {successes}")
    every, once = statistics.median(seconds["every step"]), statistics.median(seconds["once"])
    print(
        f"cameras {'+'.join(policies[0].cameras)}, {args.seeds} seeds x {args.episodes} episodes, 1 torch thread, "
        f"{cpu_description()}"
    )
    print(
        f"goals encoded at every step: {[round(s, 1) for s in seconds['every step']]} s; once per episode: "
        f"{[round(s, 1) for s in seconds['once']]} s; median ratio {once / every:.2f}"
    )


if __name__ == "__main__":
    main()
