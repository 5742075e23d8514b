"""`murm status`: where a grid stands, read from its folders while it runs."""

import sys
from pathlib import Path

import yaml

from lerobot_murm.checkpointing import append_rows
from lerobot_murm.training.run_folder import EVAL_COLUMNS, LOG_COLUMNS, SITTINGS_COLUMNS, SITTINGS_FILE

sys.path.insert(0, str(Path(__file__).parent / "helpers"))
from commands import run_command
from one_line import murm_error

MURM = Path(sys.executable).parent / "murm"

GRID = {
    "name": "status_grid",
    "tasks": ["place_in_box"],
    "seeds": [0, 1],
    "budget": {"cap": 40_000, "every": 10_000, "episodes": 2},
    "cells": [
        {"method": "single", "cameras": ["global"]},
        {"method": "single", "cameras": ["adjacent"]},
        {"method": "separated_q", "cameras": ["global", "adjacent"]},
    ],
}


def write_run(
    run: Path, steps: list[int], successes: list[float], rate: float | list[float], eval_s: float | list[float]
) -> None:
    """A run folder as the trainer leaves it mid-training (its own row writers); `rate` and
    `eval_s` are the training rate and validation seconds it logged at each step, or at all."""
    run.mkdir(parents=True)
    rates = rate if isinstance(rate, list) else [rate] * len(steps)
    seconds = eval_s if isinstance(eval_s, list) else [eval_s] * len(steps)
    logged = [
        dict.fromkeys(LOG_COLUMNS, 0.5) | {"step": s, "steps_per_s": r} for s, r in zip(steps, rates, strict=True)
    ]
    append_rows(run / "log.csv", LOG_COLUMNS, logged)
    points = [
        {
            "step": s,
            "mask_p": 0.0,
            "success_rate": r,
            "episodes": 2,
            "seconds": t,
            "split": "validation",
            "mask_mode": "paper",
        }
        for s, r, t in zip(steps, successes, seconds, strict=True)
    ]
    append_rows(run / "eval.csv", EVAL_COLUMNS, points)


def murm_status(tmp_path: Path, grid: dict = GRID) -> str:
    """`murm status` of `grid` on tmp_path's work and results folders, its figure to curves.png."""
    config = tmp_path / "grid.yaml"
    config.write_text(yaml.safe_dump(grid))
    folders = [f"--work_dir={tmp_path / 'work'}", f"--results_dir={tmp_path / 'results'}"]
    return run_command([MURM, "status", "--config", config, *folders, "--plot", tmp_path / "curves.png"], tmp_path)


def status_rows(out: str, task: str = "place_in_box") -> dict[str, list[str]]:
    """The status table's rows of `task`, by cell label: its columns after the label."""
    cells = (line.split("|") for line in out.splitlines() if line.startswith(f"| {task} |"))
    return {c[2].strip(): [x.strip() for x in c[3:-1]] for c in cells}


def test_status_reads_each_cells_step_validation_and_time_left_from_a_running_grid(tmp_path):
    runs = tmp_path / "work" / "runs" / "status_grid" / "place_in_box"
    write_run(runs / "single-global" / "seed0", [10_000, 20_000], [0.5, 1.0], rate=2.0, eval_s=900.0)
    write_run(runs / "single-global" / "seed1", [10_000, 20_000], [0.0, 0.5], rate=2.0, eval_s=900.0)
    with (runs / "single-global" / "seed1" / "log.csv").open("a") as f:
        f.write("30000,0.4")  # the trainer is writing this row right now: not read
    out = murm_status(tmp_path)
    rows = status_rows(out)
    # 20,000 of 40,000 updates at 2 updates/s, and two validation points of 900 s still to come: 3.3 h
    assert rows["single-global"] == ["training", "20,000", "40,000", "75.0 % (20,000)", "3.3"]
    # costed like the started single-view cell (6.6 h); no single-view rate for separated Q
    assert rows["single-adjacent"] == ["not started", "0", "40,000", "", "6.6"]
    assert rows["separated_q-global+adjacent"][0] == "not started" and rows["separated_q-global+adjacent"][-1] == "?"
    assert "0 of 3 cells finished" in out and "1 cell with no rate to go by" in out
    assert (tmp_path / "curves.png").stat().st_size > 0


def test_time_left_goes_by_the_runs_usual_rates_not_a_last_slowed_or_paused_one(tmp_path):
    """A test suite beside the grid slowed its last logged steps tenfold, and its last
    validation point was paused for a measurement; the estimate keeps to the rate and the
    validation time the run has shown most of the time."""
    runs = tmp_path / "work" / "runs" / "status_grid" / "place_in_box"
    steps = [5_000, 10_000, 15_000, 20_000]
    rates, seconds = [2.0, 2.0, 2.0, 0.2], [900.0, 900.0, 900.0, 9000.0]
    for seed in (0, 1):
        write_run(runs / "single-global" / f"seed{seed}", steps, [0.0, 0.5, 0.5, 1.0], rates, seconds)
    time_left = status_rows(murm_status(tmp_path))["single-global"][-1]
    assert time_left == "3.3"  # as at 2 updates/s and 900 s a point (28.3 h at the last rate, 7.8 h at the last point)


def test_time_left_counts_seeds_that_train_one_after_another_as_their_sittings_record(tmp_path):
    """On a CPU without native bf16 a job's seeds train one after another (their sittings say
    so): seed 0 half way and seed 1 not started is one and a half runs left, not half of one."""
    runs = tmp_path / "work" / "runs" / "status_grid" / "place_in_box"
    write_run(runs / "single-global" / "seed0", [10_000, 20_000], [0.5, 1.0], rate=2.0, eval_s=900.0)
    sitting = {"step": 0, "precision": "fp32", "seeds_together": 1, "machine": "AMD EPYC", "started": "2026-12-08"}
    append_rows(runs / "single-global" / "seed0" / SITTINGS_FILE, SITTINGS_COLUMNS, [sitting])
    # seed 0: 20,000 updates at 2 updates/s and two points of 900 s; seed 1: 40,000 and four (stacked: 3.3 h)
    assert status_rows(murm_status(tmp_path))["single-global"] == ["training", "0", "40,000", "", "9.8"]


def test_status_of_a_grid_with_no_run_yet_says_so_and_draws_nothing(tmp_path):
    out = murm_status(tmp_path)
    assert out.count("| not started |") == 3 and "3 cells with no rate to go by yet, so no estimate" in out
    assert " h of one job's time left" not in out  # not "about 0.0 h"
    assert "no validation point yet" in out and not (tmp_path / "curves.png").exists()


def test_status_of_a_grid_that_only_prepares_says_it_trains_nothing(tmp_path):
    out = murm_status(tmp_path, GRID | {"prepare_only": True})
    assert "no training run" in out and "| place_in_box" not in out


LATER_GRID = GRID | {  # a study's later grid: other cells, nothing run yet
    "name": "later_grid",
    "cells": [
        {"method": "single", "cameras": ["top"], "eval_mask_p": [0.0, 0.5]},
        {"method": "concat", "cameras": ["global", "adjacent"]},
    ],
}


def test_status_of_a_studys_grids_costs_a_later_grids_cells_by_an_earlier_ones_and_sums_them(tmp_path):
    """A study's later grids have not started: their cells are costed like the earlier grid's
    cells of the same method and camera count (validation by the episode: two masking levels
    take twice one level's time), and the time left is summed over every grid."""
    runs = tmp_path / "work" / "runs" / "status_grid" / "place_in_box"
    for seed in (0, 1):
        write_run(runs / "single-global" / f"seed{seed}", [10_000, 20_000], [0.5, 1.0], rate=2.0, eval_s=900.0)
    configs = []
    for grid in (GRID, LATER_GRID):
        configs += ["--config", tmp_path / f"{grid['name']}.yaml"]
        (tmp_path / f"{grid['name']}.yaml").write_text(yaml.safe_dump(grid))
    folders = [f"--work_dir={tmp_path / 'work'}", f"--results_dir={tmp_path / 'results'}"]
    out = run_command([MURM, "status", *configs, *folders], tmp_path)
    assert "status_grid: 0 of 3 cells finished" in out and "later_grid: 0 of 2 cells finished" in out
    # 40,000 updates at 2 updates/s and four points of 1,800 s (900 s for one masking level): 7.6 h
    assert status_rows(out)["single-top"] == ["not started", "0", "40,000", "", "7.6"]
    assert status_rows(out)["concat-global+adjacent"][-1] == "?"  # no run of its kind anywhere
    # 3.3 + 6.6 (status_grid's single views) + 7.6 h, unrounded 17.4; two cells with no rate
    assert "all 2 grids: about 17.4 h of one job's time left, and 2 cells with no rate to go by" in out


def test_status_draws_one_grids_curves_only(tmp_path, capsys):
    for grid in (GRID, LATER_GRID):
        (tmp_path / f"{grid['name']}.yaml").write_text(yaml.safe_dump(grid))
    code, line = murm_error(
        [
            "status",
            "--config",
            tmp_path / "status_grid.yaml",
            "--config",
            tmp_path / "later_grid.yaml",
            "--plot",
            "x.png",
        ],
        capsys,
    )
    assert code == 2 and line.startswith("murm status: --plot draws one grid's curves: give one --config with it")
