"""Cells whose cameras another grid chooses: Table 4's MURM rows on the two views that did best
alone in Table 3, by validation success at Table 3's budget (the paper's section 5.2)."""

import io
import json
import sys
from dataclasses import replace
from pathlib import Path

import draccus
import pytest

from lerobot_murm.cli import main
from lerobot_murm.experiments.best_views import choices_markdown, choose_views
from lerobot_murm.experiments.budget import choose_budget
from lerobot_murm.experiments.configuration_reproduce import load_reproduce_config

sys.path.insert(0, str(Path(__file__).parent / "helpers"))
from one_line import murm_error

REPO = Path(__file__).parents[1]
TABLE4 = REPO / "configs/reproduce/table4.yaml"
EVERY, POINTS = 10_000, 10

# place_in_box: active is best alone and side second at the budget (30,000), where every
# curve has flattened; top ends above side at the cap, by less than the seeds can tell
PLACE_IN_BOX = {
    "global": [0.2, 0.5] + [0.5] * 8,
    "adjacent": [0.2, 0.4] + [0.4] * 8,
    "side": [0.2, 0.5, 0.7] + [0.7] * 7,
    "top": [0.2, 0.5, 0.68, 0.68, 0.68] + [0.72] * 5,
    "active": [0.2, 0.6, 0.8] + [0.8] * 7,
}
PICK_UP = dict.fromkeys(PLACE_IN_BOX, [0.1] * POINTS) | {"top": [0.9] * POINTS, "adjacent": [0.85] * POINTS}


def write_table3(results: Path, rates: dict[str, list[float]], cap: int = EVERY * POINTS) -> dict:
    """Table 3's results folder as its budget grid leaves it: the grid's record and budget.json."""
    table3 = load_reproduce_config(REPO / "configs/reproduce/table3.yaml", [f"--results_dir={results}"])
    runs = [
        {
            "cell": f"single-{camera}",
            "task": task,
            "seed": seed,
            "curve": [[EVERY * (i + 1), 0.0, rate] for i, rate in enumerate(curve[: cap // EVERY])],
        }
        for task, by_camera in (("place_in_box", rates), ("pick_up", PICK_UP))
        for camera, curve in by_camera.items()
        for seed in table3.seeds
    ]
    decision = choose_budget(table3.budget, runs, cap, len(table3.seeds))
    (results / "table3").mkdir(parents=True, exist_ok=True)
    (results / "table3" / "budget.json").write_text(json.dumps(decision))
    record = io.StringIO()
    draccus.dump(table3, record)
    (results / "table3" / "config.yaml").write_text(record.getvalue())
    return decision


def test_table4_pairs_the_two_best_single_views_by_validation_at_table3s_budget_on_place_in_box(tmp_path):
    assert write_table3(tmp_path, PLACE_IN_BOX)["budget"] == 30_000
    table4 = load_reproduce_config(TABLE4, [f"--results_dir={tmp_path}"])
    chosen, choices, waiting = choose_views(table4)
    assert waiting == {}
    labels = [cell.label for cell in chosen.cells]
    named = [cell.label for cell in table4.cells if cell.best_views is None]
    assert labels == [*named, "separated_q-side+active", "dropout-side+active"]  # not top (best at the cap)
    extra = chosen.cells[-2]
    assert extra.cameras == ["side", "active"] and extra.best_views is None and extra.eval_mask_p == [0.0, 0.5]
    choice = choices["separated_q-best2-of-table3"]
    assert choice["budget"] == 30_000 and choice["added"] and choice["chosen"] == ["side", "active"]
    assert [r["camera"] for r in choice["ranking"]] == ["active", "side", "top", "global", "adjacent"]
    assert choices_markdown(choices).startswith(
        "- `separated_q-best2-of-table3`: side + active (cell `separated_q-side+active`). table3's single views "
        "on place_in_box, by their seeds' mean unmasked validation success at its budget of 30,000 updates: "
        "active 80.0 %, side 70.0 %, top 68.0 %, global 50.0 %, adjacent 40.0 %.\n"
    )


def test_no_cell_is_added_when_the_best_views_are_the_papers_global_and_adjacent(tmp_path):
    write_table3(tmp_path, PLACE_IN_BOX | {"global": [0.9] * POINTS, "adjacent": [0.85] * POINTS})
    table4 = load_reproduce_config(TABLE4, [f"--results_dir={tmp_path}"])
    chosen, choices, _ = choose_views(table4)
    assert chosen.cells == [cell for cell in table4.cells if cell.best_views is None]
    assert choices["dropout-best2-of-table3"]["cell"] == "dropout-global+adjacent"
    assert not choices["dropout-best2-of-table3"]["added"]
    assert "(`dropout-global+adjacent`, a cell the grid has anyway)" in choices_markdown(choices)


def test_a_chosen_cell_that_clashes_with_another_cell_of_that_label_is_refused(tmp_path):
    write_table3(tmp_path, PLACE_IN_BOX | {"global": [0.9] * POINTS, "adjacent": [0.85] * POINTS})
    table4 = load_reproduce_config(TABLE4, [f"--results_dir={tmp_path}"])
    cells = [replace(c, eval_mask_p=[0.0]) if c.label == "dropout-global+adjacent" else c for c in table4.cells]
    with pytest.raises(ValueError, match="a label another cell with other settings has"):
        choose_views(replace(table4, cells=cells))


def test_table4_will_not_start_before_table3_has_a_final_budget_and_status_shows_its_cells_waiting(tmp_path, capsys):
    folders = [f"--work_dir={tmp_path / 'work'}", f"--results_dir={tmp_path / 'results'}"]
    code, line = murm_error(["reproduce", "--config", TABLE4, *folders], capsys)
    assert code != 0 and "separated_q-best2-of-table3" in line and "table3 has no budget yet" in line
    assert not (tmp_path / "work" / "datasets").exists()  # refused before any collection

    rising = {camera: [0.1 * (i + 1) for i in range(POINTS)] for camera in PLACE_IN_BOX}
    decision = write_table3(tmp_path / "results", rising, cap=40_000)  # still rising at a cap it will double
    assert not decision["flat"]
    code, line = murm_error(["reproduce", "--config", TABLE4, *folders], capsys)
    assert "table3's budget is not final yet (a curve still rises at 40,000)" in line

    main(["status", "--config", str(TABLE4), *folders])
    out = capsys.readouterr().out
    assert "0 of 15 cells finished" in out and "best2" not in out.split("\n\n")[1]  # not in the table
    assert "dropout-best2-of-table3: not in the table yet, its cameras are not chosen: table3's budget" in out


@pytest.mark.parametrize(
    ("cell", "message"),
    [
        ({"method": "dropout", "cameras": ["global"], "best_views": {}}, "leave cameras out"),
        ({"method": "dropout"}, "no cameras"),
        ({"method": "dropout", "best_views": {"count": 6}}, "best_views.count must be 1 to 5"),
        ({"method": "dropout", "best_views": {"task": "stack"}}, "unknown task 'stack'"),
        ({"method": "dropout", "best_views": {}, "epsilon": [1.0, 1.0]}, "need named cameras"),
    ],
)
def test_a_bad_best_views_cell_is_refused_when_the_config_loads(tmp_path, cell, message):
    path = tmp_path / "grid.yaml"
    path.write_text(json.dumps({"name": "g", "cells": [cell]}))
    with pytest.raises(Exception) as error:
        load_reproduce_config(path)
    assert message in str(error.value.__cause__ or error.value)
