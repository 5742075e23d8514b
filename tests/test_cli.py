"""`murm demo`, the README's main command, run for real."""

import sys
from pathlib import Path

from lerobot.datasets.lerobot_dataset import LeRobotDataset
from PIL import Image

sys.path.insert(0, str(Path(__file__).parent / "helpers"))
from commands import run
from quiet import assert_quiet

MURM = Path(sys.executable).parent / "murm"


def test_murm_demo_writes_the_camera_grid_one_expert_episode_per_task_and_a_small_dataset(tmp_path):
    result = run([str(MURM), "demo", "--out", str(tmp_path), "--seed", "0"], timeout=300)
    assert result.returncode == 0, result.stderr
    assert_quiet(result.stdout + result.stderr)  # `make run` starts with this command
    lines = [line for line in result.stdout.splitlines() if "seed 0" in line]
    assert [line.split()[0] for line in lines] == ["place_in_box", "place_in_random_box", "pick_up"]
    assert all("success=True" in line for line in lines), result.stdout
    assert "collected 10 place_in_box episodes" in result.stdout
    dataset = LeRobotDataset("local/demo", root=tmp_path / "demonstrations", video_backend="pyav")
    assert dataset.meta.total_episodes == 10
    for name in ("cameras.png", "rollout_place_in_box.png", "rollout_place_in_random_box.png", "rollout_pick_up.png"):
        with Image.open(tmp_path / name) as image:
            assert min(image.size) > 200


def test_murm_without_a_command_prints_usage_and_fails():
    result = run([str(MURM)], timeout=60)
    assert result.returncode == 2
    assert "demo" in result.stderr
