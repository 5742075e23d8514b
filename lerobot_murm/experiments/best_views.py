"""Cells whose cameras another grid chooses: the views that did best alone, paired.

The paper builds its multi-view methods on "the views with the highest success rates" of its
single-view table (section 5.2). Study v2 does the same with its own Table 3 (REPORT.md,
"Table 4's extra rows"): the single views are ranked by their seeds' mean unmasked
*validation* success at that table's final budget on one task; validation chooses, test
reports. A cell with `best_views` gets its cameras when its grid runs, so that a study run
grid after grid needs no hand between them; a choice another cell of the grid already trains
(the paper's global + adjacent) adds no cell.
"""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

from lerobot_murm.env import CAMERA_NAMES
from lerobot_murm.experiments.configuration_reproduce import (
    BestViewsSpec,
    ReproduceConfig,
    load_reproduce_config,
)

CHOICES = "best_views.json"  # in a grid's results folder: what each best_views cell was given, and why


class ViewsNotChosenYet(ValueError):
    """The ranking grid has no final budget yet: its single views cannot be ranked."""


def view_ranking(results_dir: Path, spec: BestViewsSpec) -> dict:
    """The ranking grid's single views, best first, by mean unmasked validation success at its
    final budget on `spec.task` (ties: the cameras' usual order)."""
    folder = Path(results_dir) / spec.grid
    decision_file, record = folder / "budget.json", folder / "config.yaml"
    if not decision_file.exists() or not record.exists():
        raise ViewsNotChosenYet(f"{spec.grid} has no budget yet ({decision_file}): run {spec.grid} first")
    decision, ranking_grid = json.loads(decision_file.read_text()), load_reproduce_config(record)
    if ranking_grid.budget is None:
        raise ValueError(f"{spec.grid} is not a budget grid: it has no budget to rank its views at")
    if not (decision["flat"] or decision["cap"] >= ranking_grid.budget.max_cap):
        raise ViewsNotChosenYet(
            f"{spec.grid}'s budget is not final yet (a curve still rises at {decision['cap']:,}): run {spec.grid} on"
        )
    singles = {c.label: c.cameras[0] for c in ranking_grid.cells if c.method == "single" and len(c.cameras) == 1}
    budget, success = decision["budget"], {}
    for point in decision["flattening"]:
        if point["task"] == spec.task and point["mask_p"] == 0 and point["cell"] in singles:
            success[singles[point["cell"]]] = {int(step): rate for step, rate in point["curve"]}[budget]
    if len(success) < spec.count:
        raise ValueError(
            f"{spec.grid} has {len(success)} single views on {spec.task}, fewer than the {spec.count} to choose"
        )
    ranked = sorted(success, key=lambda camera: (-success[camera], CAMERA_NAMES.index(camera)))
    return {
        "grid": spec.grid,
        "task": spec.task,
        "budget": budget,
        "ranking": [{"camera": camera, "validation_success": success[camera]} for camera in ranked],
    }


def choose_views(config: ReproduceConfig) -> tuple[ReproduceConfig, dict[str, dict], dict[str, str]]:
    """The grid with each `best_views` cell given its cameras (in the cameras' usual order,
    so that global + adjacent is the paper's cell's label); a chosen cell equal to another
    cell of the grid is left out. Also what each was given ({label: ranking, chosen, cell, added}) and
    the cells whose views cannot be chosen yet ({label: why}): `murm reproduce` refuses to
    start with those, `murm status` shows them waiting."""
    cells, choices, waiting = [], {}, {}
    named = [cell for cell in config.cells if cell.best_views is None]
    for cell in config.cells:
        if cell.best_views is None:
            cells.append(cell)
            continue
        try:
            ranking = view_ranking(Path(config.results_dir), cell.best_views)
        except ViewsNotChosenYet as why:
            waiting[cell.label] = str(why)
            continue
        best = {entry["camera"] for entry in ranking["ranking"][: cell.best_views.count]}
        own_label = "" if cell.label == cell.default_label() else cell.label  # "": the chosen cameras' label
        chosen = replace(cell, cameras=[c for c in CAMERA_NAMES if c in best], best_views=None, label=own_label)
        twin = next((other for other in named if other.label == chosen.label), None)
        if twin is not None and twin != chosen:
            raise ValueError(
                f"cell {cell.label}: its views make it {chosen.label}, a label another cell with other settings has"
            )
        choices[cell.label] = ranking | {"chosen": chosen.cameras, "cell": chosen.label, "added": twin is None}
        if twin is None:
            cells.append(chosen)
    return replace(config, cells=cells), choices, waiting


def choices_markdown(choices: dict[str, dict]) -> str:
    """What each `best_views` cell of a grid was given, and the ranking it came from."""
    lines = []
    for label, choice in choices.items():
        ranking = ", ".join(f"{r['camera']} {100 * r['validation_success']:.1f} %" for r in choice["ranking"])
        given = f"cell `{choice['cell']}`" if choice["added"] else f"`{choice['cell']}`, a cell the grid has anyway"
        lines.append(
            f"- `{label}`: {' + '.join(choice['chosen'])} ({given}). {choice['grid']}'s single views on "
            f"{choice['task']}, by their seeds' mean unmasked validation success at its budget of "
            f"{choice['budget']:,} updates: {ranking}."
        )
    return "\n".join(lines) + "\n"
