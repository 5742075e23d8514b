"""Where a validation learning curve stops rising: the rule that sets each method's updates.

A choosing grid (`choose_updates: true`, e.g. `updates`, `updates_dropout`) trains longer
than the tables and evaluates every `eval_every` updates on the same validation episodes.
A curve *flattens at* the first evaluation after which no later point is clearly higher
(by more than two standard errors of the difference, binomial over the episodes: the
claims' rule for one seed). A cell takes the latest such point over its tasks and masking
levels; a curve whose only such point is its last has not been seen to flatten.
"""

from __future__ import annotations

from lerobot_murm.experiments.claims import Cell, clearly_below


def clearly_higher(later: float, earlier: float, episodes: int) -> bool:
    """Whether success rate `later` (0-1) beats `earlier` by more than two standard errors:
    the claims' `clearly_below` for one seed of `episodes` episodes each."""

    def one_seed(rate: float) -> Cell:
        return Cell(100 * rate, None, 1, episodes, 0.0)

    return clearly_below(one_seed(earlier), one_seed(later))


def flattens_at(curve: list[tuple[int, float]], episodes: int) -> int:
    """The first step of `curve` ((step, success rate) pairs) after which no later point is
    clearly higher; the last step when every earlier one is beaten later."""
    points = sorted(curve)
    if not points:
        raise ValueError("an empty learning curve has no flattening point")
    return next(
        step
        for i, (step, rate) in enumerate(points)
        if not any(clearly_higher(later, rate, episodes) for _, later in points[i + 1 :])
    )


def run_flattening(run: dict, episodes: int) -> dict[float, int]:
    """Where a run's validation curve flattens, per masking level."""
    levels = sorted({mask_p for _, mask_p, _ in run["curve"]})
    return {p: flattens_at([(int(s), r) for s, m, r in run["curve"] if m == p], episodes) for p in levels}


def flattening_table(runs: list[dict], episodes: int) -> str:
    """Markdown: where each run's validation curve flattens per masking level, then the
    updates the rule gives each cell: the latest point over its tasks and masking levels
    (each method trains until it is flat on every task), or more than the grid measured."""
    lines = ["| task | cell | seed | masking | flattens at |", "|---|---|---:|---:|---:|"]
    chosen: dict[str, int | None] = {}
    for run in runs:
        last = int(max(step for step, _, _ in run["curve"]))
        for p, step in run_flattening(run, episodes).items():
            at = f"{step:,}" if step < last else f"not seen ({last:,} is the last point)"
            lines.append(f"| {run['task']} | {run['cell']} | {run['seed']} | {p:.0%} | {at} |")
            earlier = chosen.get(run["cell"], 0)
            chosen[run["cell"]] = None if earlier is None or step == last else max(earlier, step)
    lines += ["", "| cell | updates by the rule |", "|---|---:|"]
    lines += [f"| {cell} | {'more than measured' if step is None else f'{step:,}'} |" for cell, step in chosen.items()]
    return "\n".join(lines) + "\n"
