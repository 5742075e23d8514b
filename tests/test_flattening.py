"""Where a validation curve flattens: the rule that sets each method's update count."""

import json
import sys
from pathlib import Path

import draccus
import pytest

from lerobot_murm.experiments.configuration_reproduce import load_reproduce_config
from lerobot_murm.experiments.flattening import flattens_at
from lerobot_murm.experiments.report import write_report

sys.path.insert(0, str(Path(__file__).parent / "helpers"))
from stored_run import stored_run

REPO = Path(__file__).resolve().parents[1]


def test_a_curve_flattens_where_no_later_point_is_clearly_higher():
    rising_then_flat = [(10_000, 0.10), (20_000, 0.50), (30_000, 0.55), (40_000, 0.50)]
    assert flattens_at(rising_then_flat, episodes=100) == 20_000
    # a dip that comes back does not move it (place_in_box's separated Q: 59 / 42 / 62 %) ...
    assert flattens_at([(10_000, 0.3), (20_000, 0.59), (30_000, 0.42), (40_000, 0.62)], episodes=100) == 20_000
    # ... a clear rise after it does
    assert flattens_at([(10_000, 0.3), (20_000, 0.45), (30_000, 0.42), (40_000, 0.62)], episodes=100) == 40_000
    # order of the points does not matter; a gain within two standard errors is not called
    assert flattens_at([(20_000, 0.25), (10_000, 0.14)], episodes=100) == 10_000
    assert flattens_at([(20_000, 0.25), (10_000, 0.14)], episodes=400) == 20_000  # more episodes: called
    with pytest.raises(ValueError, match="empty learning curve"):
        flattens_at([], episodes=100)


def test_a_choosing_grids_report_says_where_each_curve_flattens_and_what_the_cell_gets(tmp_path):
    grid = tmp_path / "results" / "updates"
    (grid / "runs").mkdir(parents=True)
    config = load_reproduce_config(REPO / "configs/reproduce/updates.yaml", ["--tasks=[place_in_box,pick_up]"])
    assert config.choose_updates and config.train.eval_episodes == 100
    draccus.dump(config, (grid / "config.yaml").open("w"))
    curves = [
        (
            "place_in_box",
            "single-global",
            [[10000, 0.0, 0.3], [20000, 0.0, 0.7], [30000, 0.0, 0.7], [40000, 0.0, 0.71]],
        ),
        ("pick_up", "single-global", [[10000, 0.0, 0.1], [20000, 0.0, 0.1], [30000, 0.0, 0.3], [40000, 0.0, 0.3]]),
        (
            "place_in_box",
            "dropout-global+adjacent",
            [
                [10000, 0.0, 0.0],
                [20000, 0.0, 0.06],
                [30000, 0.0, 0.08],
                [40000, 0.0, 0.29],
                [10000, 0.5, 0.0],
                [20000, 0.5, 0.3],
                [30000, 0.5, 0.3],
                [40000, 0.5, 0.3],
            ],
        ),
    ]
    for task, cell, curve in curves:
        run = stored_run(task, cell, cell.split("-")[0], ["global"], steps=40000, curve=curve)
        (grid / "runs" / f"{task}__{cell}__seed0.json").write_text(json.dumps(run))

    report = write_report(tmp_path / "results", tmp_path / "REPORT.md").read_text()
    assert "| place_in_box | single-global | 0 | 0% | 20,000 |" in report
    assert "| place_in_box | dropout-global+adjacent | 0 | 0% | not seen (40,000 is the last point) |" in report
    assert "| place_in_box | dropout-global+adjacent | 0 | 50% | 20,000 |" in report
    # a cell gets the latest point over its tasks and masking levels; still rising anywhere:
    # beyond what the grid measured
    assert "| pick_up | single-global | 0 | 0% | 30,000 |" in report
    assert "| single-global | 30,000 |" in report
    assert "| dropout-global+adjacent | more than measured |" in report
