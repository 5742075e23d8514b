"""A table's one budget, chosen on validation curves before any test episode is run.

Study v2's rule (REPORT.md, "Study v2: the protocol"): every run of the table trains to a cap
and is evaluated every `every` updates on the same validation episodes. A cell's curve on a
task and masking level is its seeds' mean; it flattens at the first point after which no
later point is clearly higher (`flattening.flattens_at`, with the seeds' episodes pooled).
The budget is the latest flattening point over cells, tasks and masking levels, rounded up
to `every`; a curve whose flattening point is its last (still rising at the cap) doubles
the cap for the whole table. The runs are then tested at the budget only.
"""

from __future__ import annotations

import math
from collections import defaultdict

from lerobot_murm.experiments.configuration_reproduce import BudgetSpec
from lerobot_murm.experiments.flattening import flattens_at


def mean_curves(runs: list[dict]) -> dict[tuple[str, str, float], list[tuple[int, float]]]:
    """(cell, task, masking level) -> the seeds' mean validation curve [(step, success 0-1)];
    every seed of a cell must have been evaluated at the same steps."""
    by_seed: dict[tuple[str, str, float], dict[int, dict[int, float]]] = defaultdict(dict)
    for run in runs:
        for step, mask_p, rate in run["curve"]:
            by_seed[(run["cell"], run["task"], mask_p)].setdefault(run["seed"], {})[int(step)] = rate
    curves = {}
    for key, seeds in sorted(by_seed.items()):
        steps = {tuple(sorted(points)) for points in seeds.values()}
        if len(steps) != 1:
            raise ValueError(
                f"{key[0]} on {key[1]}: its seeds were evaluated at different steps; train them to one cap"
            )
        curves[key] = [(step, sum(points[step] for points in seeds.values()) / len(seeds)) for step in steps.pop()]
    return curves


def choose_budget(spec: BudgetSpec, runs: list[dict], cap: int, seeds: int) -> dict:
    """The budget the rule gives runs trained to `cap` (their result dicts, each with its
    validation `curve`), with where every mean curve flattens. `flat` is false where a curve
    still rises at the cap (the caller doubles it); the budget is then the cap."""
    episodes = spec.episodes * seeds  # the pooled episodes behind each mean point
    points, flat = [], True
    for (cell, task, mask_p), curve in mean_curves(runs).items():
        last = curve[-1][0]
        if last != cap:
            raise ValueError(f"{cell} on {task}: its curve ends at {last:,} updates, not at the cap {cap:,}")
        at = flattens_at(curve, episodes)
        flat &= at < last
        points.append(
            {
                "cell": cell,
                "task": task,
                "mask_p": mask_p,
                "flattens_at": at,
                "rising_at_cap": at == last,
                "curve": [[step, round(rate, 4)] for step, rate in curve],
            }
        )
    latest = max(p["flattens_at"] for p in points)
    budget = cap if not flat else math.ceil(latest / spec.every) * spec.every
    if spec.at_least and not (spec.unless_flat_before and latest < spec.unless_flat_before):
        budget = max(budget, min(spec.at_least, cap))
    return {
        "cap": cap,
        "budget": budget,
        "flat": flat,
        "seeds": seeds,
        "pooled_episodes": episodes,
        "rule": {"every": spec.every, "at_least": spec.at_least, "unless_flat_before": spec.unless_flat_before},
        "flattening": points,
    }


def budget_markdown(decision: dict) -> str:
    """Where each mean validation curve flattens, and the budget that gives."""
    lines = [
        f"Budget: **{decision['budget']:,} updates** (cap {decision['cap']:,}; each point the mean of "
        f"{decision['seeds']} seeds, {decision['pooled_episodes']} validation episodes pooled).",
        "",
    ]
    if not decision["flat"]:
        lines += ["Some curve still rises at the cap, the largest this grid allows: the table trains to the cap.", ""]
    lines += ["| task | cell | masking | flattens at |", "|---|---|---:|---:|"]
    for p in decision["flattening"]:
        at = f"still rising at {p['flattens_at']:,}" if p["rising_at_cap"] else f"{p['flattens_at']:,}"
        lines.append(f"| {p['task']} | {p['cell']} | {p['mask_p']:.0%} | {at} |")
    return "\n".join(lines) + "\n"
