"""`murm reproduce`: the smoke grid end to end (shrunk further), reuse of finished runs, and
that every shipped config parses."""

import csv
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from lerobot_murm.experiments.reproduce import load_reproduce_config
from lerobot_murm.policy.train import load_train_config

REPO = Path(__file__).parents[1]
MURM = Path(sys.executable).parent / "murm"
TINY = [
    "--collection.episodes=4", "--collection.image_size=16", "--vqvae.steps=20", "--vqvae.batch_size=16",
    "--train.steps=20", "--train.log_every=10", "--train.eval_every=10", "--train.eval_episodes=1",
    "--train.final_eval_episodes=2", "--train.eval_envs=1", "--train.batch_size=32",
]


def murm(args: list[str], cwd: Path) -> str:
    env = {**os.environ, "HF_HUB_OFFLINE": "1"}
    result = subprocess.run([str(MURM), *args], cwd=cwd, env=env, capture_output=True, text=True, timeout=900)
    assert result.returncode == 0, f"murm {args[0]} failed:\n{result.stdout[-3000:]}\n{result.stderr[-5000:]}"
    return result.stdout


@pytest.mark.slow
def test_the_smoke_grid_runs_end_to_end_and_a_rerun_reuses_everything(tmp_path):
    args = ["reproduce", "--config", str(REPO / "configs/reproduce/smoke.yaml"), f"--work_dir={tmp_path / 'work'}",
            f"--results_dir={tmp_path / 'results'}", *TINY]
    out = murm(args, tmp_path)
    assert "| single-global | 50% |" in out and "| separated_q-global+adjacent | 0% |" in out
    results = tmp_path / "results" / "smoke"
    for name in ("table.md", "table.csv", "curves.png", "config.yaml"):
        assert (results / name).exists(), name
    runs = sorted(p.name for p in (results / "runs").iterdir())
    assert runs == ["place_in_box__separated_q-global+adjacent__seed0.json", "place_in_box__single-global__seed0.json"]
    result = json.loads((results / "runs" / runs[0]).read_text())
    assert [r["episodes"] for r in result["final"]] == [2, 2] and result["steps"] == 20

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


@pytest.mark.parametrize("path", sorted((REPO / "configs" / "reproduce").glob("*.yaml")), ids=lambda p: p.stem)
def test_every_experiment_config_parses(path):
    config = load_reproduce_config(path)
    assert config.name == path.stem and config.cells


TRAINING_CONFIGS = sorted(p for p in REPO.glob("configs/*/*.yaml") if p.parent.name != "reproduce")


@pytest.mark.parametrize("path", TRAINING_CONFIGS, ids=lambda p: f"{p.parent.name}/{p.stem}")
def test_every_training_config_parses(path, tiny_pipeline):
    config = load_train_config(path, [f"--policy.encoder_dir={tiny_pipeline[1]}"])
    assert config.task == path.parent.name and config.policy.method == path.stem


def test_an_encoder_is_reused_only_when_trained_to_the_end_for_the_asked_steps(tmp_path):
    from lerobot_murm.experiments.reproduce import encoder_is_finished

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
def test_the_smoke_single_view_cell_learns_a_policy_that_beats_random_actions(tmp_path):
    """The README's smoke grid at its real size (100 demonstrations, 48x48 images), single-view
    cell only: collection, VQ-VAE, IQL and evaluation in the simulator, from nothing."""
    import yaml

    from lerobot_murm.policy.evaluate import evaluation_seeds

    config = yaml.safe_load((REPO / "configs/reproduce/smoke.yaml").read_text())
    config["cells"] = [cell for cell in config["cells"] if cell["method"] == "single"]
    (tmp_path / "smoke_single.yaml").write_text(yaml.safe_dump(config))
    murm(["reproduce", "--config", str(tmp_path / "smoke_single.yaml"), f"--work_dir={tmp_path / 'work'}",
          f"--results_dir={tmp_path / 'results'}"], tmp_path)
    result = json.loads((tmp_path / "results/smoke/runs/place_in_box__single-global__seed0.json").read_text())
    learned = result["final"][0]
    assert learned["mask_p"] == 0.0
    random = random_policy_success("place_in_box", evaluation_seeds(learned["episodes"]))
    assert learned["success_rate"] >= random + 0.15, (learned, random)
