"""The package as users get it: a wheel built from the sources, installed into a fresh virtual
environment, run from a folder outside the repository.

The environment sees the test interpreter's site-packages for the dependencies (lerobot,
torch, pybullet: installing them again would take minutes) through a `.pth` file added after
the wheel is installed; lerobot_murm itself and the `murm` command come from the wheel alone.
"""

import json
import os
import shutil
import sys
import sysconfig
import zipfile
from pathlib import Path

import pytest
import torch
from lerobot.datasets.lerobot_dataset import LeRobotDataset

from lerobot_murm.policy.configuration_murm import MurmConfig
from lerobot_murm.policy.processor_murm import make_murm_pre_post_processors
from lerobot_murm.training.train import build_policy

REPO = Path(__file__).parents[1]
HELPERS = Path(__file__).parent / "helpers"
SOURCES = ("pyproject.toml", "README.md", "lerobot_murm", "lerobot_policy_murm", "datasets_cards")
CARD_TEMPLATE = "lerobot_murm/publishing/datasets_cards/murm_demonstrations.md"

sys.path.insert(0, str(HELPERS))
from commands import run_command  # noqa: E402
from quiet import assert_quiet  # noqa: E402

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def installed(tmp_path_factory) -> tuple[Path, dict]:
    """(the fresh environment, the environment variables to run it with: no PYTHONPATH)."""
    base = tmp_path_factory.mktemp("wheel")
    sources = base / "src"
    sources.mkdir()
    for name in SOURCES:
        if (REPO / name).is_dir():
            shutil.copytree(REPO / name, sources / name, symlinks=True, ignore=shutil.ignore_patterns("__pycache__"))
        else:
            shutil.copy2(REPO / name, sources / name)
    run_command(
        [
            sys.executable,
            "-m",
            "pip",
            "wheel",
            "--no-deps",
            "--no-build-isolation",
            "--no-index",
            "-q",
            "-w",
            base / "dist",
            sources,
        ],
        cwd=base,
    )
    (wheel,) = (base / "dist").glob("lerobot_policy_murm-*.whl")
    assert CARD_TEMPLATE in zipfile.ZipFile(wheel).namelist()

    venv = base / "venv"
    run_command([sys.executable, "-m", "venv", "--without-pip", venv], cwd=base)
    run_command(
        [
            sys.executable,
            "-m",
            "pip",
            "--python",
            venv / "bin" / "python",
            "install",
            "--no-deps",
            "--no-index",
            "-q",
            wheel,
        ],
        cwd=base,
    )
    purelib = run_command(
        [venv / "bin" / "python", "-c", "import sysconfig; print(sysconfig.get_path('purelib'))"], base
    )
    (Path(purelib.strip()) / "test_dependencies.pth").write_text(sysconfig.get_path("purelib") + "\n")
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"} | {"HF_HUB_OFFLINE": "1"}
    return venv, env


def test_the_wheel_brings_its_own_code_and_card_template(installed, tmp_path):
    venv, env = installed
    script = (
        "import lerobot_murm, lerobot_policy_murm; from importlib.resources import files; "
        "print(lerobot_murm.__file__); print((files('lerobot_murm.publishing') / 'datasets_cards').is_dir())"
    )
    module, has_cards = run_command([venv / "bin" / "python", "-c", script], tmp_path, env).split()
    assert Path(module).is_relative_to(venv) and has_cards == "True"


def test_the_installed_murm_collects_quietly_and_pushes_the_dataset_with_its_card(installed, tmp_path):
    venv, env = installed
    out = run_command(
        [
            venv / "bin" / "murm",
            "collect",
            "--task",
            "pick_up",
            "--root",
            tmp_path / "ds",
            "--episodes",
            "2",
            "--workers",
            "1",
            "--cameras",
            "side",
            "--image-size",
            "16",
        ],
        tmp_path,
        env,
    )
    assert "2 episodes in" in out
    assert_quiet(out)  # a first run from a fresh install

    push = f"""
import sys
sys.path.insert(0, {str(HELPERS)!r})
from fake_hub import FakeHub
from lerobot_murm.cli import main
with FakeHub() as hub:
    hub.route_all_hub_traffic()
    main(["push", "--root", {str(tmp_path / "ds")!r}, "--repo-id", "tester/wheel"])
    print(hub.files("tester/wheel")["README.md"].decode())
"""
    push_env = {k: v for k, v in env.items() if k != "HF_HUB_OFFLINE"} | {"HF_TOKEN": "hf_test_token"}
    readme = run_command([venv / "bin" / "python", "-c", push], tmp_path, push_env)
    for fact in ("pushed", "pick_up", "lifted 5 cm", "`observation.images.side_goal`", "murm collect --task pick_up"):
        assert fact in readme, fact


def test_lerobot_eval_in_the_installed_environment_loads_a_murm_checkpoint(installed, tiny_pipeline, tmp_path):
    venv, env = installed
    root, encoders = tiny_pipeline
    dataset = LeRobotDataset("local/place_in_box", root=root, video_backend="pyav")
    config = MurmConfig(method="single", cameras=["global"], encoder_dir=str(encoders))
    policy = build_policy(config, dataset, torch.device("cpu"))
    for part in (policy, *make_murm_pre_post_processors(policy.config)):  # what `murm train` saves
        part.save_pretrained(tmp_path / "ckpt")
    run_command(
        [
            venv / "bin" / "python",
            "-m",
            "lerobot.scripts.lerobot_eval",
            f"--policy.path={tmp_path / 'ckpt'}",
            "--env.type=murm",
            "--env.task=place_in_box",
            "--env.image_size=16",
            "--env.cameras=[global]",
            "--eval.n_episodes=1",
            "--eval.batch_size=1",
            f"--output_dir={tmp_path / 'eval'}",
        ],
        tmp_path,
        env,
    )
    overall = json.loads((tmp_path / "eval" / "eval_info.json").read_text())["overall"]
    assert overall["n_episodes"] == 1
