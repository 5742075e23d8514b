"""A table's one budget: chosen on the seeds' mean validation curves, then every run tested there."""

import json
import os
import sys
from pathlib import Path

import pytest
import yaml

from lerobot_murm.experiments.budget import budget_markdown, choose_budget
from lerobot_murm.experiments.configuration_reproduce import BudgetSpec, load_reproduce_config

sys.path.insert(0, str(Path(__file__).parent / "helpers"))
from commands import run_command

MURM = Path(sys.executable).parent / "murm"


def curve_run(cell: str, seed: int, rates: list[float], every: int = 10_000, task: str = "place_in_box") -> dict:
    return {
        "cell": cell,
        "task": task,
        "seed": seed,
        "curve": [[every * (i + 1), 0.0, rate] for i, rate in enumerate(rates)],
    }


def test_the_budget_is_the_latest_point_where_a_cells_mean_curve_flattens():
    spec = BudgetSpec(cap=60_000, every=10_000, episodes=100)
    # 200 pooled episodes: 0.55 against 0.6 is within two standard errors, 0.45 against 0.6 is not
    runs = [
        curve_run("single", 0, [0.1, 0.5, 0.6, 0.6, 0.6, 0.6]),
        curve_run("single", 1, [0.1, 0.6, 0.6, 0.6, 0.6, 0.6]),
        curve_run("murm", 0, [0.1, 0.2, 0.3, 0.5, 0.6, 0.6]),
        curve_run("murm", 1, [0.1, 0.2, 0.3, 0.6, 0.6, 0.6]),
    ]
    decision = choose_budget(spec, runs, cap=60_000, seeds=2)
    assert decision["flat"] and decision["budget"] == 40_000  # murm's mean curve flattens last
    assert {p["cell"]: p["flattens_at"] for p in decision["flattening"]} == {"murm": 40_000, "single": 20_000}
    assert "Budget: **40,000 updates**" in budget_markdown(decision)


def test_a_curve_still_rising_at_the_cap_asks_for_more_and_the_floor_applies_unless_all_flatten_early():
    spec = BudgetSpec(cap=40_000, every=10_000, episodes=100, at_least=30_000, unless_flat_before=20_000)
    rising = [curve_run("single", 0, [0.1, 0.3, 0.5, 0.8])]
    decision = choose_budget(spec, rising, cap=40_000, seeds=1)
    assert not decision["flat"] and decision["budget"] == 40_000
    assert "still rising at 40,000" in budget_markdown(decision)
    early = [curve_run("single", 0, [0.5, 0.6, 0.5, 0.55])]  # flat from the first point: no floor
    assert choose_budget(spec, early, cap=40_000, seeds=1)["budget"] == 10_000
    middle = [curve_run("single", 0, [0.1, 0.6, 0.6, 0.6])]  # flat at 20,000: the floor of 30,000 holds
    assert choose_budget(spec, middle, cap=40_000, seeds=1)["budget"] == 30_000


def test_seeds_evaluated_at_different_steps_are_refused():
    runs = [curve_run("single", 0, [0.1, 0.2]), curve_run("single", 1, [0.1, 0.2, 0.3])]
    with pytest.raises(ValueError, match="different steps"):
        choose_budget(BudgetSpec(cap=20_000, every=10_000), runs, cap=20_000, seeds=2)


@pytest.mark.parametrize(
    ("budget", "message"),
    [
        ({"cap": 25, "every": 10}, "must be a positive multiple of every"),
        ({"cap": 20, "every": 10, "max_cap": 10}, "max_cap"),
        ({"cap": 20, "every": 10, "at_least": 15}, "must be multiples of every (10): a budget is one of"),
        ({"cap": 20, "every": 10, "unless_flat_before": 5}, "must be multiples of every (10): a budget is one of"),
    ],
)
def test_a_bad_budget_is_refused_when_the_config_loads(tmp_path, budget, message):
    path = tmp_path / "grid.yaml"
    path.write_text(
        yaml.safe_dump({"name": "b", "cells": [{"method": "single", "cameras": ["global"]}], "budget": budget})
    )
    with pytest.raises(Exception) as error:
        load_reproduce_config(path)
    assert message in str(error.value.__cause__ or error.value)


@pytest.mark.slow
def test_a_budget_grid_trains_to_the_cap_on_validation_episodes_then_tests_every_run_at_the_budget(tmp_path):
    grid = {
        "name": "budget_tiny",
        "tasks": ["place_in_box"],
        "seeds": [0, 1],
        "collection": {"episodes": 4, "image_size": 16},
        "vqvae": {"steps": 20, "batch_size": 16},
        "train": {"log_every": 10, "eval_envs": 1, "batch_size": 32},
        "budget": {"cap": 20, "every": 10, "episodes": 2, "max_cap": 40},
        "cells": [{"method": "single", "cameras": ["global"]}],
    }
    config = tmp_path / "grid.yaml"
    config.write_text(yaml.safe_dump(grid))
    args = [
        MURM,
        "reproduce",
        "--config",
        config,
        f"--work_dir={tmp_path / 'work'}",
        f"--results_dir={tmp_path / 'results'}",
    ]
    env = {**os.environ, "HF_HUB_OFFLINE": "1"}
    out = run_command(args, tmp_path, env=env, timeout=900)
    results = tmp_path / "results" / "budget_tiny"
    decision = json.loads((results / "budget.json").read_text())
    budget = decision["budget"]
    assert decision["cap"] in (20, 40) and budget in (10, 20, 40) and f"budget {budget:,} updates" in out
    for seed in (0, 1):
        curve = json.loads((results / "curves" / f"place_in_box__single-global__seed{seed}.json").read_text())
        assert curve["final"] == [] and curve["steps"] == decision["cap"]  # no test episode before the budget
        assert [int(p[0]) for p in curve["curve"]] == list(range(10, decision["cap"] + 1, 10))
        tested = json.loads((results / "runs" / f"place_in_box__single-global__seed{seed}.json").read_text())
        assert tested["steps"] == tested["budget"] == budget and tested["trained_to"] == decision["cap"]
        assert [(r["split"], r["episodes"], r["step"]) for r in tested["final"]] == [("test", 2, budget)]
        assert [(r["split"], r["step"]) for r in tested["final_validation"]] == [("validation", budget)]
        run = tmp_path / "work" / "runs" / "budget_tiny" / "place_in_box" / "single-global" / f"seed{seed}"
        assert (run / "checkpoints" / f"{budget:06d}" / "pretrained_model" / "model.safetensors").exists()
    assert (results / "table.md").exists() and "Budget:" in (results / "budget.md").read_text()

    again = run_command(args, tmp_path, env=env, timeout=900)  # a second sitting finds everything done
    assert "trained to" not in again and f"budget {budget:,} updates" in again

    # a grid whose cell takes the view that did best alone in this one, at its budget: the
    # cell's runs are this grid's recipe, so they start from its runs instead of training again
    best = {"method": "single", "best_views": {"grid": "budget_tiny", "count": 1}}
    config.write_text(yaml.safe_dump(grid | {"name": "views_tiny", "cells": [best]}))
    out = run_command(args, tmp_path, env=env, timeout=900)
    assert "- `single-best1-of-budget_tiny`: global (cell `single-global`). budget_tiny's single views" in out
    choices = json.loads((tmp_path / "results" / "views_tiny" / "best_views.json").read_text())
    assert choices["single-best1-of-budget_tiny"]["chosen"] == ["global"]
    assert choices["single-best1-of-budget_tiny"]["budget"] == budget
    for seed in (0, 1):
        name = f"place_in_box__single-global__seed{seed}.json"
        tested = json.loads((tmp_path / "results" / "views_tiny" / "runs" / name).read_text())
        assert tested["final"] == json.loads((results / "runs" / name).read_text())["final"]

    status = run_command([MURM, "status", *args[2:]], tmp_path, env=env)  # `murm status` reads the grid alike
    assert "1 of 1 cells finished" in status and f"| single-global | finished | {decision['cap']} |" in status

    run_command(
        [MURM, "report", f"--results={tmp_path / 'results'}", f"--out={tmp_path / 'REPORT.md'}", "--preface="],
        tmp_path,
        env=env,
    )
    assert "The table's one budget" in (tmp_path / "REPORT.md").read_text()

    # another grid with the same run (Table 4's cells are the hindsight grid's) starts it from
    # this grid's checkpoint, in a copy of its folder; a run of another config trains from scratch
    first = {
        seed: tmp_path / "work" / "runs" / "budget_tiny" / "place_in_box" / "single-global" / f"seed{seed}"
        for seed in (0, 1)
    }
    before = {seed: (run / "eval.csv").read_text() for seed, run in first.items()}
    other = grid | {
        "name": "budget_other",
        "budget": {"cap": 40, "every": 10, "episodes": 2, "max_cap": 40},
        "cells": [
            grid["cells"][0],
            {"method": "single", "cameras": ["global"], "policy": {"hidden_units": 64}, "label": "narrow"},
        ],
    }
    config.write_text(yaml.safe_dump(other))
    # a copy that a kill -9 cut short: half a folder beside where the run goes
    torn = tmp_path / "work" / "runs" / "budget_other" / "place_in_box" / "single-global" / "seed0.tmp"
    (torn / "checkpoints").mkdir(parents=True)
    (torn / "log.csv").write_text("step,value_loss\n10,0.")
    out = run_command(args, tmp_path, env=env, timeout=900)
    assert out.count("(the same run, trained by another grid)") == 2, out
    assert not torn.exists()
    for seed, run in first.items():
        assert (run / "eval.csv").read_text() == before[seed]  # the first grid's folder is untouched
        ours = json.loads(
            (
                tmp_path / "results" / "budget_other" / "curves" / f"place_in_box__single-global__seed{seed}.json"
            ).read_text()
        )
        theirs = json.loads(
            (
                tmp_path / "results" / "budget_tiny" / "curves" / f"place_in_box__single-global__seed{seed}.json"
            ).read_text()
        )
        assert ours["curve"][: len(theirs["curve"])] == theirs["curve"] and ours["steps"] == 40
        assert f"starts from {run} at step {theirs['steps']}" in out
        assert ours["adopted_from"]["step"] == theirs["steps"] and ours["adopted_from"]["from"] == str(run)
    narrow = tmp_path / "work" / "runs" / "budget_other" / "place_in_box" / "narrow" / "seed0"
    assert [line.split(",")[0] for line in (narrow / "log.csv").read_text().splitlines()[1:3]] == ["10", "20"]

    # a new machine: the results folder (committed) holds budget_tiny's curves to the cap and no
    # test yet, the work dir is empty; its runs train again there, rather than the grid failing
    # at the test for want of the policies they kept, and `murm status` says they have not started
    config.write_text(yaml.safe_dump(grid))
    for tested in (results / "runs").glob("*.json"):
        tested.unlink()
    new_machine = [*args[:4], f"--work_dir={tmp_path / 'new_machine'}", args[5]]
    assert "| single-global | not started |" in run_command([MURM, "status", *new_machine[2:]], tmp_path, env=env)
    out = run_command(new_machine, tmp_path, env=env, timeout=900)
    assert out.count("its kept policies not in this work dir: trained again") == 2, out
    budget = json.loads((results / "budget.json").read_text())["budget"]
    for seed in (0, 1):
        run = tmp_path / "new_machine" / "runs" / "budget_tiny" / "place_in_box" / "single-global" / f"seed{seed}"
        assert (run / "checkpoints" / f"{budget:06d}" / "pretrained_model" / "model.safetensors").exists()
        tested = json.loads((results / "runs" / f"place_in_box__single-global__seed{seed}.json").read_text())
        assert tested["steps"] == budget and tested["final"][0]["split"] == "test"
