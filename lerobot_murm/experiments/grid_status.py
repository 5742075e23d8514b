"""Where a grid stands, read from its folders while it runs (`murm status`): each cell's state,
step, latest validation success and the time left at the rates its runs have shown.

A study's grids run for days over many sittings; this is the look at them between sittings
or beside a running one. It only reads: the run folders' `log.csv` and `eval.csv` (a row the
trainer is writing at that moment is skipped, `read_run_csv`), the grid's stored curves and
results, and its `budget.json`. Time left is one job's: training at the median of the rates
the run has logged (a sitting shared with other work slows a few of them, not the median) plus
the validation points still to come at the median seconds its points took (one paused for a
measurement counts its pause); a cell not started yet is costed like a started cell of the same
method and camera count that trains as many seeds in one job, in this grid or in the others
`murm status` was given (a study's later grids by its earlier ones), its validation seconds
scaled to the cell's masking levels, episodes and seeds. A budget grid's test at its budget,
after every run reached the cap, is not counted; nor is a run a later grid will start from an
earlier grid's (`reuse.py`), which counts in both.
"""

from __future__ import annotations

import json
import statistics
from dataclasses import dataclass, field
from pathlib import Path

from lerobot_murm.experiments.artifacts import result_path, run_dir
from lerobot_murm.experiments.configuration_reproduce import CellSpec, ReproduceConfig
from lerobot_murm.experiments.results import plot_curves, read_result
from lerobot_murm.experiments.reuse import kept_as_finished, ready_to_test, run_recipe, same_run, tested_at_budget
from lerobot_murm.training.learning_curve import read_run_csv, validation_curve
from lerobot_murm.training.run_folder import read_sittings

NOT_STARTED, TRAINING, AT_CAP, FINISHED = "not started", "training", "at the cap", "finished"


@dataclass
class CellStatus:
    task: str
    cell: CellSpec
    state: str
    seed_steps: list[int]  # the step each seed has logged
    target: int  # the cap (a budget grid) or the cell's updates
    validation: tuple[int, float] | None  # (step, seeds' mean success 0-1) unmasked, at the latest step all share
    steps_per_s: float | None  # the median logged training rate of its slowest seed (evaluations left out)
    eval_s: float | None  # median seconds of its validation points (all masking levels of one)
    seeds_per_job: int  # seeds one job trains together (a stack), 1 where each trains alone
    episodes_per_point: int  # a validation point's episodes: masking levels x episodes x seeds_per_job
    curves: list[dict] = field(default_factory=list)  # per seed: {"task", "cell", "curve"} as plot_curves reads

    @property
    def step(self) -> int:
        """The step every seed has logged (the slowest seed's)."""
        return min(self.seed_steps)

    @property
    def family(self) -> tuple[str, int, int]:
        """Cells that train at about the same rate: one method on as many cameras, as many seeds a job."""
        return self.cell.method, len(self.cell.cameras), self.seeds_per_job


def _stored(path: Path) -> dict | None:
    return read_result(path) if path.exists() else None


def cell_status(config: ReproduceConfig, task: str, cell: CellSpec, cap: int) -> CellStatus:
    """One cell's state, judged as the grid judges it: a stored result or curve counts only if
    its recipe is the cell's (an earlier study's run of the same name does not)."""
    runs = [run_dir(config, task, cell, seed) for seed in config.seeds]
    target = cap if config.budget else config.cell_steps(cell)
    recipes = [run_recipe(config, task, cell, seed) for seed in config.seeds]
    if config.budget is None:  # as the grid keeps a stored run (an earlier study's is trained again)
        results = [_stored(result_path(config, task, cell, seed)) for seed in config.seeds]
        finished = all(
            r is not None and kept_as_finished(r.get("recipe"), rc) for r, rc in zip(results, recipes, strict=True)
        )
    else:
        finished = all(tested_at_budget(config, task, cell, seed) for seed in config.seeds)
    curves_dir = Path(config.results_dir) / config.name / "curves"
    stored_curves = [_stored(curves_dir / result_path(config, task, cell, seed).name) for seed in config.seeds]
    at_cap = config.budget is not None and all(
        c is not None
        and same_run(c.get("recipe"), rc)
        and c["steps"] >= cap
        and ready_to_test(config, task, cell, seed, cap)  # as the grid judges it: else it trains again
        for seed, c, rc in zip(config.seeds, stored_curves, recipes, strict=True)
    )
    logs = [read_run_csv(run / "log.csv") for run in runs]
    evals = [validation_curve(read_run_csv(run / "eval.csv")) for run in runs]
    seed_steps = [int(rows[-1]["step"]) if rows else 0 for rows in logs]
    if finished or at_cap:
        seed_steps = [max(s, target) for s in seed_steps]
    rates = [statistics.median(r["steps_per_s"] for r in rows) for rows in logs if rows]
    unmasked = [{int(r["step"]): r["success_rate"] for r in points if r["mask_p"] == 0} for points in evals]
    shared = set.intersection(*(set(points) for points in unmasked))
    validation = None
    if shared:
        latest = max(shared)
        validation = (latest, statistics.fmean(points[latest] for points in unmasked))
    per_point: dict[int, float] = {}  # a validation point's seconds, all its masking levels
    for r in evals[0]:
        per_point[r["step"]] = per_point.get(r["step"], 0.0) + r["seconds"]
    eval_s = statistics.median(per_point.values()) if per_point else None
    state = FINISHED if finished else AT_CAP if at_cap else TRAINING if any(logs) else NOT_STARTED
    curves = [
        {"task": task, "cell": cell.label, "curve": [[r["step"], r["mask_p"], r["success_rate"]] for r in points]}
        for points in evals
        if points
    ]
    together = len(config.seeds) if config.stack_seeds and not config.timed else 1
    # as the latest sitting trained them: on a CPU without native bf16 a job's seeds train one
    # after another (seed_stack.stacking_pays)
    sittings = [row for run in runs for row in read_sittings(run)]
    if sittings:
        together = max(sittings, key=lambda row: row["started"])["seeds_together"]
    episodes = config.budget.episodes if config.budget else config.train.eval_episodes
    rate = min(rates) if rates else None
    per_point = len(cell.eval_mask_p) * episodes * together
    return CellStatus(task, cell, state, seed_steps, target, validation, rate, eval_s, together, per_point, curves)


def grid_status(config: ReproduceConfig) -> list[CellStatus]:
    """Every (task, cell) of the grid, in the grid's order."""
    decision = Path(config.results_dir) / config.name / "budget.json"
    cap = config.budget.cap if config.budget else 0
    if config.budget and decision.exists():
        cap = max(cap, json.loads(decision.read_text())["cap"])  # a cap doubled by an earlier sitting
    return [cell_status(config, task, cell, cap) for task in config.tasks for cell in config.cells]


def hours_left(status: CellStatus, cells: list[CellStatus], config: ReproduceConfig) -> float | None:
    """One job's hours to bring the cell to its target; None where no run has shown a rate.
    `cells`: every cell whose rates may stand in for a cell not started (several grids' cells)."""
    if status.state in (FINISHED, AT_CAP):
        return 0.0
    alike = [c for c in cells if c.family == status.family and c.steps_per_s and c.eval_s]
    rate = status.steps_per_s or (statistics.median(c.steps_per_s for c in alike) if alike else None)
    eval_s = status.eval_s
    if eval_s is None and alike:  # by the episode: another cell may validate more masking levels or seeds
        eval_s = statistics.median(c.eval_s / c.episodes_per_point for c in alike) * status.episodes_per_point
    if rate is None or eval_s is None:
        return None
    every = config.budget.every if config.budget else config.train.eval_every
    seconds = sum(
        (status.target - s) / rate + (status.target // every - s // every) * eval_s for s in status.seed_steps
    )
    return seconds / 3600 / status.seeds_per_job


def status_markdown(
    config: ReproduceConfig,
    cells: list[CellStatus],
    left: list[float | None],
    waiting: dict[str, str] | None = None,
) -> str:
    """The status table; `left`: each cell's `hours_left`; `waiting`: cells whose cameras another
    grid has not chosen yet ({label: why})."""
    lines = [
        f"{config.name}: {sum(c.state == FINISHED for c in cells)} of {len(cells)} cells finished, "
        f"seeds {config.seeds}",
        "",
        "| task | cell | state | step | of | validation success (seeds' mean, at step) | hours left |",
        "|---|---|---|---:|---:|---:|---:|",
    ]
    for c, hours in zip(cells, left, strict=True):
        validation = f"{100 * c.validation[1]:.1f} % ({c.validation[0]:,})" if c.validation else ""
        lines.append(
            f"| {c.task} | {c.cell.label} | {c.state} | {c.step:,} | {c.target:,} | {validation} | "
            f"{'?' if hours is None else f'{hours:.1f}'} |"
        )
    total = time_left_line(left, "to the cap; the test at the budget comes after" if config.budget else "")
    notes = [
        f"{label}: not in the table yet, its cameras are not chosen: {why}" for label, why in (waiting or {}).items()
    ]
    return "\n".join(lines + ["", total, *notes]) + "\n"


def time_left_line(left: list[float | None], scope: str = "") -> str:
    """One job's hours left over cells (None: a cell with no rate to go by), in a sentence;
    `scope` says what the hours cover, in brackets."""
    known = [h for h in left if h is not None]
    unknown = len(left) - len(known)
    no_rate = f"{unknown} cell{'s' if unknown > 1 else ''} with no rate to go by"
    if not known:  # nothing has trained yet: no estimate, not "0.0 h"
        return f"{no_rate} yet, so no estimate of the time left."
    line = f"about {sum(known):.1f} h of one job's time left" + (f", and {no_rate}" if unknown else "")
    return line + (f" ({scope})" if scope else "") + "; with --jobs N, about 1/N of it."


def plot_status(cells: list[CellStatus], path: Path) -> bool:
    """The seeds' mean validation curves so far, one panel per task; False when there are none."""
    curves = [curve for c in cells for curve in c.curves]
    if not curves:
        return False
    plot_curves(curves, path)
    return True
