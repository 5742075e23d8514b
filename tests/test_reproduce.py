"""`murm reproduce`: the smoke grid end to end (shrunk further), reuse of finished runs, and
that every shipped config parses."""

import csv
import json
import os
import re
import shutil
import sys
from dataclasses import replace
from pathlib import Path

import pytest
import yaml

from lerobot_murm.experiments.configuration_reproduce import load_reproduce_config
from lerobot_murm.training.train import load_train_config

sys.path.insert(0, str(Path(__file__).parent / "helpers"))
from commands import run
from quiet import assert_quiet
from stored_run import stored_run

REPO = Path(__file__).parents[1]
MURM = Path(sys.executable).parent / "murm"
TINY = [
    "--collection.episodes=4",
    "--collection.image_size=16",
    "--vqvae.steps=20",
    "--vqvae.batch_size=16",
    "--train.steps=20",
    "--train.log_every=10",
    "--train.eval_every=10",
    "--train.eval_episodes=1",
    "--train.final_eval_episodes=2",
    "--train.eval_envs=1",
    "--train.batch_size=32",
]


def murm(args: list[str], cwd: Path) -> str:
    env = {**os.environ, "HF_HUB_OFFLINE": "1"}
    # a liveness bound: the real-size smoke cell takes ~5 min alone, twice that beside a grid
    result = run([MURM, *args], timeout=1800, cwd=cwd, env=env)
    assert result.returncode == 0, f"murm {args[0]} failed:\n{result.stdout[-3000:]}\n{result.stderr[-5000:]}"
    assert_quiet(result.stdout + result.stderr)  # `make run` ends with `murm reproduce`
    return result.stdout


@pytest.mark.slow
@pytest.mark.timeout(1800)  # the real-size smoke grid: ~7 min alone
def test_the_smoke_grid_runs_end_to_end_and_a_rerun_reuses_everything(tmp_path):
    args = [
        "reproduce",
        "--config",
        str(REPO / "configs/reproduce/smoke.yaml"),
        f"--work_dir={tmp_path / 'work'}",
        f"--results_dir={tmp_path / 'results'}",
        *TINY,
    ]
    out = murm(args, tmp_path)
    assert "| single-global | 50% |" in out and "| separated_q-global+adjacent | 0% |" in out
    # progress: the numbers of the grid's reported split (a choosing grid shows no test numbers), the time left
    assert re.search(r"\[1/2\] .* % \(test\); 1 run left, about \d+ min", out) and "[2/2]" in out
    results = tmp_path / "results" / "smoke"
    for name in ("table.md", "table.csv", "curves.png", "config.yaml"):
        assert (results / name).exists(), name
    runs = sorted(p.name for p in (results / "runs").iterdir())
    assert runs == ["place_in_box__separated_q-global+adjacent__seed0.json", "place_in_box__single-global__seed0.json"]
    result = json.loads((results / "runs" / runs[0]).read_text())
    assert [r["episodes"] for r in result["final"]] == [2, 2] and result["steps"] == 20
    validation, test = (
        range(result["validation_seeds"][0], result["validation_seeds"][1] + 1),
        range(result["eval_seeds"][0], result["eval_seeds"][1] + 1),
    )
    assert len(test) == 2 and not set(validation) & set(test)
    assert [r["episodes"] for r in result["final_validation"]] == [2, 2]
    assert 0.0 <= result["demonstration_success"] <= 1.0
    checks = sorted((tmp_path / "work" / "vqvae").glob("*/*/object_pixels.json"))  # each encoder's object check
    assert [p.parent.name for p in checks] == ["adjacent", "global"]
    assert all(json.loads(p.read_text())["reproduced_fraction"] == 1.0 for p in checks)

    stamp = {p: p.stat().st_mtime_ns for p in (results / "runs").iterdir()}
    again = murm(args, tmp_path)
    assert again.splitlines()[-8:] == out.splitlines()[-8:]  # the same table, from the stored results
    assert {p: p.stat().st_mtime_ns for p in (results / "runs").iterdir()} == stamp
    assert "collect" not in again and "vq-vae" not in again

    murm(["report", f"--results={tmp_path / 'results'}", f"--out={tmp_path / 'REPORT.md'}", "--preface="], tmp_path)
    report = (tmp_path / "REPORT.md").read_text()
    assert "## smoke" in report and "(n=1)" in report and "![learning curves](results/smoke/curves.png)" in report

    murm([*args, "--seeds=[1]"], tmp_path)  # a later sitting: another seed joins the same tables
    rows = list(csv.DictReader((results / "table.csv").open()))
    assert len(rows) == 4 and {row["seeds"] for row in rows} == {"2"}
    assert "training seeds 0, 1;" in (results / "table.md").read_text()
    assert load_reproduce_config(results / "config.yaml").seeds == [0, 1]  # the grid so far, not the sitting's part

    # a result file torn by a crash is set aside, not a crash, and its run (finished) is read back from its checkpoint
    torn = results / "runs" / "place_in_box__single-global__seed1.json"
    whole = json.loads(torn.read_text())
    torn.write_text(torn.read_text()[:100])
    out = murm(
        ["report", f"--results={tmp_path / 'results'}", f"--out={tmp_path / 'REPORT.md'}", "--preface="], tmp_path
    )
    assert f"{torn} does not read (torn?): left out" in out
    out = murm([*args, "--seeds=[1]"], tmp_path)
    assert "place_in_box__single-global__seed1.json: it does not read (torn)" in out
    assert json.loads(torn.read_text())["final"] == whole["final"]
    assert (results / "runs" / "superseded" / torn.name).read_text() == json.dumps(whole, indent=1)[:100]

    # another grid with the same single-view recipe (the smoke's data and cell, one masking level) takes the
    # finished run instead of training
    smoke = yaml.safe_load((REPO / "configs/reproduce/smoke.yaml").read_text())
    single = next(cell for cell in smoke["cells"] if cell["method"] == "single")
    other = tmp_path / "other.yaml"
    other.write_text(
        yaml.safe_dump(smoke | {"name": "other", "cells": [single | {"eval_mask_p": [0.0], "label": "global-only"}]})
    )
    murm(["reproduce", "--config", str(other), *args[3:]], tmp_path)  # the same TINY sizes as smoke
    assert not (tmp_path / "work" / "runs" / "other").exists()
    reused = json.loads((tmp_path / "results/other/runs/place_in_box__global-only__seed0.json").read_text())
    original = json.loads((results / "runs/place_in_box__single-global__seed0.json").read_text())
    assert reused["reused_from"] == "smoke/place_in_box__single-global__seed0"
    assert reused["final"] == original["final"][:1] and reused["final"][0]["mask_p"] == 0.0
    assert reused["experiment"] == "other" and reused["cell"] == "global-only"

    # a timed grid (Table 5) trains its runs itself, one at a time, whatever --jobs says
    timed = tmp_path / "timed.yaml"
    timed.write_text(yaml.safe_dump(smoke | {"name": "timed", "timed": True, "cells": [single]}))
    out = murm(["reproduce", "--config", str(timed), *args[3:], "--jobs", "2"], tmp_path)
    assert "timed times its runs: they train one at a time" in out
    assert (tmp_path / "work" / "runs" / "timed").exists()
    assert "reused_from" not in json.loads(
        (tmp_path / "results/timed/runs/place_in_box__single-global__seed0.json").read_text()
    )

    # the encoders are kept beside the results: with the work dir's encoders gone (a fresh machine), the
    # next grid copies them back instead of training another draw, and its runs record the same weights
    original = json.loads((results / "runs/place_in_box__single-global__seed0.json").read_text())
    kept = tmp_path / "results" / "encoders"
    assert sorted(p.name for p in kept.glob("*/*")) == ["adjacent", "global"]
    assert set(original["encoders"]) == {"global"} and len(original["encoders"]["global"]) == 16
    shutil.rmtree(tmp_path / "work" / "vqvae")

    # a cell with other demonstrations (Table 7) collects them but encodes them with the task's encoders
    fewer = tmp_path / "fewer.yaml"
    fewer.write_text(
        yaml.safe_dump(smoke | {"name": "fewer", "cells": [single | {"episodes": 3, "label": "demos3", "steps": 30}]})
    )
    murm(["reproduce", "--config", str(fewer), *args[3:]], tmp_path)
    encoder = next(kept.glob("*/global"))  # copied back, not trained again (a new training has its own train_seconds)
    assert (tmp_path / "work" / "vqvae" / encoder.parent.name / "global" / "metrics.json").read_text() == (
        encoder / "metrics.json"
    ).read_text()
    datasets = sorted(p.name for p in (tmp_path / "work" / "datasets").iterdir())
    assert len(datasets) == 2 and any("-3ep-" in name for name in datasets)
    assert len(list((tmp_path / "work" / "vqvae").iterdir())) == 1  # no second set of encoders
    run = json.loads((tmp_path / "results/fewer/runs/place_in_box__demos3__seed0.json").read_text())
    assert "-3ep-" in run["dataset"] and run["recipe"]["encoder_dataset"] == original["dataset"]
    assert run["encoders"] == original["encoders"]
    assert run["steps"] == run["recipe"]["train"]["steps"] == 30  # the cell's own update count

    # the cell changes (more updates): its stored result is set aside, not lost, and the run
    # trains on from its checkpoint instead of from scratch
    fewer.write_text(fewer.read_text().replace("steps: 30", "steps: 40"))
    out = murm(["reproduce", "--config", str(fewer), *args[3:]], tmp_path)
    assert "its cell changed since it ran" in out and "resuming from step 30" in out
    runs = tmp_path / "results/fewer/runs"
    assert json.loads((runs / "place_in_box__demos3__seed0.json").read_text())["steps"] == 40
    assert json.loads((runs / "superseded/place_in_box__demos3__seed0.json").read_text()) == run


def test_a_run_is_taken_from_another_grid_only_for_the_same_recipe_and_masking_levels(tmp_path):
    from lerobot_murm.experiments.reuse import finished_elsewhere, run_recipe

    table4 = load_reproduce_config(REPO / "configs/reproduce/table4.yaml", [f"--results_dir={tmp_path}"])
    table3 = load_reproduce_config(REPO / "configs/reproduce/table3.yaml", [f"--results_dir={tmp_path}"])
    table3 = replace(table3, budget=table4.budget)  # at Table 4's budget rule the two grids share single-view runs
    single4, single3 = table4.cells[0], table3.cells[0]
    recipe = run_recipe(table4, "pick_up", single4, 1)
    assert recipe == run_recipe(table3, "pick_up", single3, 1)
    assert recipe != run_recipe(table3, "pick_up", single3, 2)
    assert recipe != run_recipe(table3, "place_in_box", single3, 1)
    assert run_recipe(table4, "pick_up", table4.cells[3], 1) != run_recipe(table4, "pick_up", table4.cells[4], 1)
    table1 = load_reproduce_config(REPO / "configs/reproduce/table1.yaml", [f"--results_dir={tmp_path}"])
    widths = {cell.policy["hidden_units"]: cell for cell in table1.cells}
    assert run_recipe(table1, "place_in_box", widths[128], 0) != run_recipe(table4, "place_in_box", single4, 0)
    shared = replace(table4, budget=table1.budget)  # Table 4 at Table 1's budget rule
    assert run_recipe(table1, "place_in_box", widths[128], 0) == run_recipe(shared, "place_in_box", single4, 0)
    assert run_recipe(table1, "place_in_box", widths[64], 0) != run_recipe(shared, "place_in_box", single4, 0)
    fixed = replace(table4, budget=None)  # Table 4 without its budget: the grid's train.steps
    # Table 7's demonstrations vary; its encoders are the task's own, trained on the default collection
    table7 = load_reproduce_config(REPO / "configs/reproduce/table7.yaml", [f"--results_dir={tmp_path}"])
    demos250 = run_recipe(table7, "place_in_box", table7.cells[0], 0)
    default = run_recipe(table4, "place_in_box", table4.cells[3], 0)
    assert demos250["dataset"] != default["dataset"] and demos250["encoder_dataset"] == default["dataset"]
    assert "encoder_dataset" not in default
    # a cell's own update count is part of its recipe; the grid's count spelled out is not a new recipe
    default = run_recipe(fixed, "place_in_box", fixed.cells[3], 0)
    longer = run_recipe(fixed, "place_in_box", replace(fixed.cells[3], steps=40_000), 0)
    assert longer["train"]["steps"] == 40_000 and longer != default
    assert run_recipe(fixed, "place_in_box", replace(fixed.cells[3], steps=fixed.train.steps), 0) == default

    final = [{"mask_p": p, "success_rate": 0.5, "episodes": 100} for p in (0.0, 0.1)]
    encoders = {"global": "0123456789abcdef"}
    stored = {"final": final, "curve": [[5000, 0.0, 0.4], [5000, 0.1, 0.3]], "recipe": recipe, "encoders": encoders}
    (tmp_path / "table4" / "runs").mkdir(parents=True)
    earlier_setting = tmp_path / "table4" / "runs" / "pick_up__single-global__seed1.json"
    earlier_setting.write_text(json.dumps(stored))
    assert finished_elsewhere(table3, recipe, [0.0], encoders) is None  # no validation seeds: chosen on its test seeds
    stored["validation_seeds"] = [200_000, 200_099]
    earlier_setting.write_text(json.dumps(stored))
    found = finished_elsewhere(table3, recipe, [0.0], encoders)
    assert found["final"] == final[:1] and found["curve"] == [[5000, 0.0, 0.4]]
    assert found["reused_from"] == "table4/pick_up__single-global__seed1"
    assert finished_elsewhere(table3, recipe, [0.0, 0.5], encoders) is None  # never evaluated with 50 % masking
    assert finished_elsewhere(table3, run_recipe(table3, "pick_up", single3, 2), [0.0], encoders) is None
    assert finished_elsewhere(table4, recipe, [0.0], encoders) is None  # a grid does not reuse itself
    # trained on other encoders (another draw of the same recipe), on unknown ones, or none trained yet here
    assert finished_elsewhere(table3, recipe, [0.0], {"global": "fedcba9876543210"}) is None
    assert finished_elsewhere(table3, recipe, [0.0], None) is None
    earlier_setting.write_text(json.dumps({k: v for k, v in stored.items() if k != "encoders"}))
    assert finished_elsewhere(table3, recipe, [0.0], encoders) is None


def test_a_grid_keeps_its_runs_where_auto_precision_resolves_otherwise_and_reuses_none_of_them(tmp_path):
    from lerobot_murm.experiments.reuse import finished_elsewhere, kept_as_finished, run_recipe, stored_at

    table4 = load_reproduce_config(REPO / "configs/reproduce/table4.yaml", [f"--results_dir={tmp_path}"])
    table3 = load_reproduce_config(REPO / "configs/reproduce/table3.yaml", [f"--results_dir={tmp_path}"])
    single = table4.cells[0]
    recipe = run_recipe(table4, "place_in_box", single, 0)
    other = "torch.float32" if recipe["precision"] == "torch.bfloat16" else "torch.bfloat16"
    on_another_machine = recipe | {"precision": other}  # a bf16 CPU's run read back on one without, or back
    assert kept_as_finished(recipe, recipe) and kept_as_finished(on_another_machine, recipe)
    assert not kept_as_finished(on_another_machine | {"train": recipe["train"] | {"steps": 1}}, recipe)
    # a budget grid's curve or test stored on the other machine stands too (not set aside, so not
    # trained or tested again each time the study changes machines)
    curve = tmp_path / "curves" / "place_in_box__single-global__seed0.json"
    curve.parent.mkdir()
    curve.write_text(json.dumps({"steps": 150_000, "recipe": on_another_machine}))
    assert stored_at(curve, recipe, 150_000) and curve.exists()
    for asked in ("fp32", "bf16"):  # a cell that asks for a precision trains again in it
        cell = replace(single, policy={"precision": asked})
        own = run_recipe(table4, "place_in_box", cell, 0)
        flipped = own | {"precision": "torch.bfloat16" if asked == "fp32" else "torch.float32"}
        assert kept_as_finished(own, own) and not kept_as_finished(flipped, own)
        curve.write_text(json.dumps({"steps": 150_000, "recipe": flipped}))
        assert not stored_at(curve, own, 150_000) and not curve.exists()  # set aside

    # another grid takes only a run of the very same recipe, precision included
    runs = tmp_path / "table4" / "runs"
    runs.mkdir(parents=True)
    final = [{"mask_p": 0.0, "success_rate": 0.5, "episodes": 100}]
    encoders = {"global": "0123456789abcdef"}
    stored = {
        "final": final,
        "curve": [],
        "validation_seeds": [200_000, 200_099],
        "recipe": on_another_machine,
        "encoders": encoders,
    }
    (runs / "place_in_box__single-global__seed0.json").write_text(json.dumps(stored))
    assert finished_elsewhere(table3, recipe, [0.0], encoders) is None
    (runs / "place_in_box__single-global__seed0.json").write_text(json.dumps(stored | {"recipe": recipe}))
    found = finished_elsewhere(table3, recipe, [0.0], encoders)
    assert found["reused_from"] == "table4/place_in_box__single-global__seed0"


def test_an_encoder_stage_stopped_midway_keeps_the_encoders_it_finished(tmp_path, monkeypatch):
    """The end of a sitting (or a failed job) in the encoder stage: each encoder finished
    before it is beside the results already, for the next machine to copy back."""
    from lerobot_murm.experiments import artifacts, reproduce as driver
    from lerobot_murm.experiments.executors import SerialExecutor

    config = load_reproduce_config(
        REPO / "configs/reproduce/table6.yaml",
        [f"--results_dir={tmp_path / 'results'}", f"--work_dir={tmp_path / 'work'}"],
    )
    root = artifacts.encoder_root(config, "place_in_box")

    def train_one(config, root, camera):  # stands in for a VQ-VAE training: a finished encoder's files
        if camera == "top":
            raise RuntimeError("the sitting ended")
        out = artifacts.encoder_dir(config, root) / camera
        out.mkdir(parents=True)
        (out / "config.json").write_text("{}")
        (out / "model.safetensors").write_bytes(camera.encode())
        (out / "metrics.json").write_text(
            json.dumps({"interrupted": False, "steps": artifacts.encoder_steps(config, camera)})
        )

    monkeypatch.setattr(driver, "ensure_encoder", train_one)
    with pytest.raises(RuntimeError, match="the sitting ended"):
        driver.build_encoders(SerialExecutor(), config, [(root, "global"), (root, "top")])
    kept = artifacts.kept_encoder_dir(config, root)
    assert sorted(p.name for p in kept.iterdir()) == ["global"]
    assert (kept / "global" / "model.safetensors").read_bytes() == b"global"


def test_a_sitting_that_runs_part_of_a_grid_adds_to_the_grid_it_records(tmp_path):
    import draccus

    from lerobot_murm.experiments.reuse import grid_so_far

    table3 = REPO / "configs/reproduce/table3.yaml"
    stored = tmp_path / "config.yaml"
    with stored.open("w") as f:
        draccus.dump(load_reproduce_config(table3, ["--tasks=[place_in_box]", "--seeds=[0,1]"]), f)
    sitting = load_reproduce_config(table3, ["--tasks=[pick_up,place_in_box]", "--seeds=[2]"])
    grid = grid_so_far(sitting, stored)
    assert grid.tasks == ["place_in_box", "pick_up"] and grid.seeds == [0, 1, 2]
    assert grid_so_far(grid, stored) == grid
    changed = load_reproduce_config(table3, ["--tasks=[pick_up]", "--train.steps=40000"])
    assert grid_so_far(changed, stored) == changed  # another recipe: a new grid, recorded as it is
    assert grid_so_far(sitting, tmp_path / "none.yaml") == sitting
    stored.write_text("cells: [{method: single, cam")  # torn
    assert grid_so_far(sitting, stored) == sitting


@pytest.mark.parametrize("path", sorted((REPO / "configs" / "reproduce").glob("*.yaml")), ids=lambda p: p.stem)
def test_every_experiment_config_parses(path):
    config = load_reproduce_config(path)
    assert config.name == path.stem and config.cells


def test_table7_reads_k_both_ways_a_share_of_noisy_episodes_and_a_scale_of_the_noise():
    from lerobot_murm.experiments.artifacts import collect_config
    from lerobot_murm.experiments.configuration_reproduce import CellSpec
    from lerobot_murm.expert import default_noise_std

    config = load_reproduce_config(REPO / "configs/reproduce/table7.yaml")
    cells = {cell.label: cell for cell in config.cells}
    std = default_noise_std("place_in_box")
    share = collect_config(config, "place_in_box", cells["noisy25"])
    assert share.noisy_fraction == 0.25 and share.noise_std == pytest.approx(std)
    scaled = collect_config(config, "place_in_box", cells["scale25"])
    assert scaled.noisy_fraction == 1.0 and scaled.noise_std == pytest.approx(0.25 * std)
    assert len({collect_config(config, "place_in_box", c).root for c in config.cells}) == len(config.cells)
    with pytest.raises(ValueError, match="noise_scale"):
        CellSpec(method="separated_q", cameras=["global"], noise_scale=0.5, noisy_fraction=0.5)


TRAINING_CONFIGS = sorted(p for p in REPO.glob("configs/*/*.yaml") if p.parent.name != "reproduce")


@pytest.mark.parametrize("path", TRAINING_CONFIGS, ids=lambda p: f"{p.parent.name}/{p.stem}")
def test_every_training_config_parses(path, tiny_pipeline):
    config = load_train_config(path, [f"--policy.encoder_dir={tiny_pipeline[1]}"])
    assert config.task == path.parent.name and config.policy.method == path.stem


def test_an_encoder_is_reused_only_when_trained_to_the_end_for_the_asked_steps(tmp_path):
    from lerobot_murm.experiments.artifacts import encoder_is_finished

    assert not encoder_is_finished(tmp_path, 2500)  # nothing there
    (tmp_path / "metrics.json").write_text(json.dumps({"steps": 2500, "interrupted": False}))
    assert encoder_is_finished(tmp_path, 2500) and not encoder_is_finished(tmp_path, 5000)
    (tmp_path / "metrics.json").write_text(json.dumps({"steps": 1200, "interrupted": True}))
    assert not encoder_is_finished(tmp_path, 1200)


def random_policy_success(task: str, seeds: list[int]) -> float:
    """Uniform random actions on the same evaluation episodes."""
    import gymnasium as gym
    import numpy as np

    from lerobot_murm.env import EPISODE_STEPS, GYM_IDS

    env = gym.make(GYM_IDS[task], cameras=["global"])
    rng, successes = np.random.default_rng(0), []
    for seed in seeds:
        env.reset(seed=seed)
        successes.append(any(env.step(rng.uniform(-1, 1, 4))[4]["is_success"] for _ in range(EPISODE_STEPS)))
    env.close()
    return float(np.mean(successes))


@pytest.mark.slow
@pytest.mark.timeout(1800)  # the real-size smoke grid: ~7 min alone
def test_the_smoke_single_view_cell_learns_a_policy_that_beats_random_actions(tmp_path):
    """The README's smoke grid at its real size (100 demonstrations, 48x48 images), single-view
    cell only: collection, VQ-VAE, IQL and evaluation in the simulator, from nothing."""
    import yaml

    from lerobot_murm.training.evaluate import evaluation_seeds

    config = yaml.safe_load((REPO / "configs/reproduce/smoke.yaml").read_text())
    config["cells"] = [cell | {"eval_mask_p": [0.0]} for cell in config["cells"] if cell["method"] == "single"]
    config["train"]["eval_every"] = config["train"]["steps"]  # learning is checked at the end only
    (tmp_path / "smoke_single.yaml").write_text(yaml.safe_dump(config))
    murm(
        [
            "reproduce",
            "--config",
            str(tmp_path / "smoke_single.yaml"),
            f"--work_dir={tmp_path / 'work'}",
            f"--results_dir={tmp_path / 'results'}",
        ],
        tmp_path,
    )
    result = json.loads((tmp_path / "results/smoke/runs/place_in_box__single-global__seed0.json").read_text())
    learned = result["final"][0]
    assert learned["mask_p"] == 0.0
    random = random_policy_success("place_in_box", evaluation_seeds(learned["episodes"], result["eval_seeds"][0]))
    assert learned["success_rate"] >= random + 0.15, (learned, random)


def test_the_report_puts_a_grids_discussion_under_its_table_and_names_reused_runs(tmp_path):
    import draccus

    from lerobot_murm.experiments.report import write_report

    grid = tmp_path / "results" / "table3"
    (grid / "runs").mkdir(parents=True)
    config = load_reproduce_config(
        REPO / "configs/reproduce/table3.yaml", ["--tasks=[place_in_box,pick_up]", "--seeds=[0]"]
    )
    draccus.dump(config, (grid / "config.yaml").open("w"))
    top = {"recipe": {"precision": "torch.bfloat16"}, "encoders": {"top": "3a2b1039f7cb38bb"}}
    side = {  # three seeds side by side, started from another grid's run at step 10,000
        "wall_s": 3960.0,
        "seeds_together": 3,
        "adopted_from": {"from": "/w/runs/table2/pick_up/single-side/seed0", "step": 10000, "wall_s": 360.0},
        # bf16 on one machine, resumed there, then on one without native bf16
        "sittings": [
            {"step": step, "precision": dtype, "machine": "AMD EPYC", "started": "2026-12-08T01:00:00+00:00"}
            for step, dtype in ((0, "bf16"), (10000, "bf16"), (60000, "fp32"))
        ],
    }
    for cell, reused in (
        ("single-global", {"reused_from": "table4/pick_up__single-global__seed0"}),
        ("single-top", top),
        ("single-side", side),
    ):
        run = stored_run("pick_up", cell, "single", [cell.split("-")[1]], **reused)
        (grid / "runs" / f"pick_up__{cell}__seed0.json").write_text(json.dumps(run))
    (grid / "discussion.md").write_text("Top beats nothing here.\n")

    report = write_report(tmp_path / "results", tmp_path / "REPORT.md").read_text()
    table, rest = report.split("![learning curves]")
    assert "| single-top | 0% |" in table and "50.0 (n=1)" in table  # one seed: no sample std
    assert "place_in_random_box" not in table  # a task the grid does not run gets no column
    assert rest.index("Top beats nothing here.") < rest.index("Runs:")
    assert "6.0 min (the run of table4/pick_up__single-global__seed0)" in rest
    assert "66.0 min (from step 10,000 of table2/pick_up/single-side/seed0)" in rest
    # top's 6 min, and a third of side's 60 min after the other grid's 6
    assert "Machine time of the runs this grid trained (2; seeds trained side by side counted once" in rest
    assert "from there): 0.4 h." in rest
    assert "| cpu | bf16 | top 3a2b1039 |" in rest  # which precision and which draw of the encoders
    assert "| cpu | - | - |" in rest  # a run from before they were recorded
    assert "| cpu | bf16, fp32 from 60,000 | - |" in rest  # a run that moved between machines
    assert (grid / "table.csv").exists() and (grid / "curves.png").exists()
    assert (grid / "vs_paper.png").exists() and "![ours beside the paper](results/table3/vs_paper.png)" in table

    from lerobot_murm.experiments.report import update_readme

    readme = tmp_path / "README.md"
    readme.write_text(
        "# x\n<!-- results:table3 -->\nSTALE TABLE\n<!-- /results:table3 -->\n<!-- results:table9 -->\nkept\n"
        "<!-- /results:table9 -->\nend\n"
    )
    assert update_readme(tmp_path / "results", readme) == ["table3"]
    text = readme.read_text()
    assert "STALE TABLE" not in text and "| single-top | 0% | - (18.8) | 50 (0.2) |" in text
    assert "| single-global | 0% | - (34.5) | 50 (15.7) |" in text
    assert "kept" in text and text.endswith("end\n")


def test_the_time_table_compares_each_run_with_the_baseline_on_its_own_machine():
    from lerobot_murm.experiments.paper import TABLE5
    from lerobot_murm.experiments.report import time_table

    fast, slow = "Xeon, native bf16, 2 torch threads", "EPYC, no native bf16, 2 torch threads"
    runs = [
        {"task": "place_in_box", "cell": cell, "seed": seed, "hardware": hardware, "train_steps_per_s": sps}
        for cell, seed, hardware, sps in (
            ("single-global", 0, fast, 100.0),
            ("single-global", 1, slow, 20.0),
            ("separated_q-global+adjacent", 0, fast, 50.0),
            ("separated_q-global+adjacent", 1, slow, 5.0),
            ("dropout-global+adjacent", 0, "a third CPU", 40.0),
        )
    ]
    table = time_table(runs, TABLE5)
    assert "| place_in_box | single-global | 60.0 | 1.00 | 2 | 2 | 1.00 |" in table
    # 100 / 50 on one machine and 20 / 5 on the other: (2 + 4) / 2, not 60 / 27.5
    assert "| place_in_box | separated_q-global+adjacent | 27.5 | 3.00 | 2 | 2 | 1.55 |" in table
    assert "| place_in_box | dropout-global+adjacent | 40.0 | - | 1 | 1 | 1.05 |" in table  # no baseline on its CPU
    assert table.count("separated_q") == 1  # one row per cell, whatever its runs' machines


def test_a_grid_without_a_paper_table_gets_no_paper_columns(tmp_path):
    from lerobot_murm.experiments.report import comparison, plot_against_paper

    rows = [
        {
            "task": "pick_up",
            "cell": "single-global",
            "mask_p": "0.0",
            "success_mean": "56.0",
            "success_std": "",
            "seeds": "1",
        }
    ]
    ours = comparison("updates", rows)
    assert plot_against_paper("table3", rows, ("pick_up",), tmp_path / "table3.png")
    assert not plot_against_paper("updates", rows, ("pick_up",), tmp_path / "updates.png")  # no paper table
    assert not plot_against_paper("table3", rows, ("place_in_box",), tmp_path / "none.png")  # nothing run there
    assert not (tmp_path / "updates.png").exists() and not (tmp_path / "none.png").exists()
    assert ours.splitlines()[0] == "| cell | masking | place_in_box | place_in_random_box | pick_up |"
    assert "| single-global | 0% | - | - | 56.0 (n=1) |" in ours  # one seed: no sample std
    assert "pick_up: ours | paper" in comparison("table3", rows)
    # study v1's number in its own column where it differs from ours, not where it is ours
    assert comparison("table3", rows, earlier=rows) == comparison("table3", rows)
    earlier = [rows[0] | {"success_mean": "10.0"}]
    with_v1 = comparison("table3", rows, ("pick_up",), earlier)
    assert "pick_up: ours | v1 | paper" in with_v1 and "| single-global | 0% | 56.0 (n=1) | 10.0 | 15.7 |" in with_v1


def test_a_choosing_grid_reports_validation_episodes_and_never_the_test_ones():
    from lerobot_murm.experiments.results import aggregate

    def run(seed: int, validation: float, test: float) -> dict:
        return {
            "task": "place_in_box",
            "cell": "c",
            "method": "single",
            "cameras": ["global"],
            "seed": seed,
            "steps": 10,
            "wall_s": 1.0,
            "train_steps_per_s": 1.0,
            "final": [{"mask_p": 0.0, "success_rate": test, "episodes": 100}],
            "final_validation": [{"mask_p": 0.0, "success_rate": validation, "episodes": 100}],
        }

    runs = [run(0, 0.5, 0.9), run(1, 0.7, 0.1)]
    (validation,), (test,) = aggregate(runs, "validation"), aggregate(runs)
    assert validation["success_mean"] == 60.0 and test["success_mean"] == 50.0
    assert validation["success_std"] == pytest.approx(14.14, abs=0.01)  # sample std, ddof 1
    with pytest.raises(Exception) as error:  # draccus wraps the config's ValueError
        load_reproduce_config(REPO / "configs/reproduce/table4.yaml", ["--report_split=train"])
    assert "report_split must be 'test' or 'validation'" in str(error.value.__cause__ or error.value)


def test_table2_runs_the_papers_epsilons_mapped_to_our_encoders_scale(tiny_pipeline, tmp_path):
    from lerobot_murm.experiments.reproduce import cell_epsilon, epsilon_scales, train_config
    from lerobot_murm.vqvae.latent_distance import read_statistics

    root, encoders = tiny_pipeline
    stats = read_statistics(encoders / "global")
    suggested, random = stats["suggested_epsilon"], stats["random_frames"]
    table2 = load_reproduce_config(REPO / "configs/reproduce/table2.yaml", [f"--work_dir={tmp_path}"])
    ours = {cell.label: cell_epsilon(cell, encoders) for cell in table2.cells}
    assert ours["single-global-paper-eps0.1"] == pytest.approx([0.05 * suggested])
    assert ours["single-global-paper-eps5"] == pytest.approx([2.5 * suggested])
    assert ours["single-global-paper-eps2"] is None  # the suggestion itself: Table 4's baseline, reused
    config = train_config(table2, "place_in_box", table2.cells[3], 0, root, encoders)
    assert config.policy.epsilon == pytest.approx([1.5 * suggested])

    scales = epsilon_scales([suggested, 1.5 * suggested], ["global", "adjacent"], encoders)
    assert scales["epsilon_paper_scale"][0] == pytest.approx(2.0, abs=1e-3)
    assert 0 <= scales["epsilon_quantile"][0] <= 1 and scales["epsilon_quantile"][1] >= 0

    median = load_reproduce_config(
        REPO / "configs/reproduce/table2.yaml",
        ["--cells=[{method: single, cameras: [global], epsilon_quantile: [0.5], label: median}]"],
    ).cells[0]
    assert cell_epsilon(median, encoders) == pytest.approx([random["p50"]], rel=1e-6)
    # the share of random frames' distances under the median: 0.5 up to the ties of a tiny encoder's
    # distances (blurred 16x16 images give many equal ones)
    assert epsilon_scales(cell_epsilon(median, encoders), ["global"], encoders)["epsilon_quantile"] == [
        pytest.approx(0.5, abs=0.05)
    ]


@pytest.mark.parametrize(
    "fields, error",
    [
        ({"epsilon": [1.0], "paper_epsilon": [2.0]}, "set one of epsilon, paper_epsilon, epsilon_quantile"),
        ({"paper_epsilon": [2.0, 3.0]}, "2 paper_epsilon values for 1 cameras"),
        ({"epsilon_quantile": [1.5]}, "epsilon_quantile values must be in (0, 1)"),
        ({"paper_epsilon": [0.0]}, "epsilon values must be positive"),
        ({"steps": 0}, "steps must be at least 1, got 0"),
    ],
)
def test_a_cell_with_a_bad_epsilon_is_refused_with_one_line(fields, error):
    from lerobot_murm.experiments.configuration_reproduce import CellSpec

    with pytest.raises(ValueError, match=re.escape(f"cell single-global: {error}")):
        CellSpec(method="single", cameras=["global"], **fields)


def test_the_table2_report_says_on_which_scale_each_epsilon_is(tmp_path):
    import draccus

    from lerobot_murm.experiments.report import write_report

    grid = tmp_path / "results" / "table2"
    (grid / "runs").mkdir(parents=True)
    draccus.dump(
        load_reproduce_config(REPO / "configs/reproduce/table2.yaml", ["--seeds=[0]"]), (grid / "config.yaml").open("w")
    )
    for cell, epsilon, paper, quantile in (
        ("single-global-paper-eps0.1", 0.23, 0.1, 0.004),
        ("single-global-paper-eps2", 4.6, 2.0, 0.31),
    ):
        run = stored_run(
            "place_in_box",
            cell,
            "single",
            ["global"],
            epsilon=[epsilon],
            epsilon_paper_scale=[paper],
            epsilon_quantile=[quantile],
        )
        (grid / "runs" / f"place_in_box__{cell}__seed0.json").write_text(json.dumps(run))
    report = write_report(tmp_path / "results", tmp_path / "REPORT.md").read_text()
    assert "| single-global-paper-eps0.1 | 0% | 50.0 (n=1) | 29.0 |" in report
    assert "| place_in_box | single-global-paper-eps0.1 | 0.23 | 0.1 | 0.004 |" in report
    assert "| place_in_box | single-global-paper-eps2 | 4.6 | 2 | 0.31 |" in report
    assert "The paper's epsilons are on its own encoders' scale" in report


def test_an_encoder_whose_frames_all_encode_alike_has_no_paper_scale(tmp_path):
    from lerobot_murm.experiments.configuration_reproduce import CellSpec
    from lerobot_murm.experiments.reproduce import cell_epsilon, epsilon_scales
    from lerobot_murm.vqvae.latent_distance import QUANTILE_KEY

    (tmp_path / "global").mkdir()
    stats = {"camera": "global", "suggested_epsilon": 0.0, QUANTILE_KEY: [0.0] * 101}
    (tmp_path / "global" / "latent_distance.json").write_text(json.dumps(stats))
    assert epsilon_scales([0.0], ["global"], tmp_path)["epsilon_paper_scale"] == [None]
    with pytest.raises(ValueError, match="no scale to map the paper's epsilon to"):
        cell_epsilon(CellSpec(method="single", cameras=["global"], paper_epsilon=[1.0]), tmp_path)


def test_table2_reports_the_spread_over_seeds_during_training(tmp_path):
    import json

    from lerobot_murm.experiments.report import training_spread

    runs = tmp_path / "table2" / "runs"
    runs.mkdir(parents=True)
    for seed, successes in enumerate(((0.1, 0.3), (0.3, 0.3), (0.2, 0.6))):
        curve = [[5000, 0.0, successes[0]], [5000, 0.5, 0.0], [10000, 0.0, successes[1]]]
        (runs / f"s{seed}.json").write_text(
            json.dumps({"task": "place_in_box", "cell": "single-global-paper-eps2", "curve": curve})
        )
    # std over seeds at 5,000 updates: 10 points; at 10,000: 17.32; their mean 13.66
    table = training_spread(tmp_path / "table2", {"single-global-paper-eps2": 2.97})
    assert "| place_in_box | single-global-paper-eps2 | 13.66 | 3 | 2.97 |" in table


def test_a_cells_seeds_train_as_one_job_unless_stacking_is_off():
    from lerobot_murm.experiments.configuration_reproduce import CellSpec
    from lerobot_murm.experiments.reproduce import training_jobs

    single, separated = CellSpec("single", ["global"]), CellSpec("separated_q", ["global", "adjacent"])
    todo = [
        ("grid", "place_in_box", single, 0),
        ("grid", "place_in_box", separated, 0),
        ("grid", "place_in_box", single, 2),
        ("grid", "pick_up", single, 1),
    ]
    assert [(task, cell.label, seeds) for _, task, cell, seeds in training_jobs(todo, together=True)] == [
        ("place_in_box", "single-global", [0, 2]),
        ("place_in_box", "separated_q-global+adjacent", [0]),
        ("pick_up", "single-global", [1]),
    ]
    assert [seeds for *_, seeds in training_jobs(todo, together=False)] == [[0], [0], [2], [1]]
