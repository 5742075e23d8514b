"""Where a validation learning curve stops rising: the rule that sets each method's updates.

A choosing grid (`choose_updates: true`, e.g. `updates`, `updates_dropout`) trains longer
than the tables and evaluates every `eval_every` updates on the same validation episodes.
A curve *flattens at* the first evaluation after which no later point is clearly higher
(by more than two standard errors of the difference, binomial over the episodes: the
claims' rule for one seed). A cell takes the latest of its masking levels' points; a curve
whose only such point is its last has not been seen to flatten.
"""

from __future__ import annotations

import math


def clearly_higher(later: float, earlier: float, episodes: int) -> bool:
    """Whether success rate `later` (0-1) beats `earlier` by more than two standard errors."""
    variance = (later * (1 - later) + earlier * (1 - earlier)) / episodes
    return later - earlier > 2 * math.sqrt(variance)


def flattens_at(curve: list[tuple[int, float]], episodes: int) -> int:
    """The first step of `curve` ((step, success rate) pairs) after which no later point is
    clearly higher; the last step when every earlier one is beaten later."""
    points = sorted(curve)
    if not points:
        raise ValueError("an empty learning curve has no flattening point")
    return next(step for i, (step, rate) in enumerate(points)
                if not any(clearly_higher(later, rate, episodes) for _, later in points[i + 1:]))


def flattening_table(runs: list[dict], episodes: int) -> str:
    """Markdown: per task, cell and masking level, where each run's validation curve
    flattens, and the update count the rule gives the cell (the latest of its levels)."""
    lines = ["| task | cell | seed | masking | flattens at | the cell's updates |", "|---|---|---:|---:|---:|---:|"]
    for run in runs:
        levels = sorted({mask_p for _, mask_p, _ in run["curve"]})
        last = int(max(step for step, _, _ in run["curve"]))
        found = {p: flattens_at([(int(s), r) for s, m, r in run["curve"] if m == p], episodes) for p in levels}
        chosen = max(found.values())
        for p, step in found.items():
            at = f"{step:,}" if step < last else f"not seen ({last:,} is the last point)"
            cell_choice = f"{chosen:,}" if chosen < last else "more than measured"
            lines.append(f"| {run['task']} | {run['cell']} | {run['seed']} | {p:.0%} | {at} | {cell_choice} |")
    return "\n".join(lines) + "\n"
