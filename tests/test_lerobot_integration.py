"""LeRobot finds and runs the `murm` env through its own plugin discovery, in real subprocesses."""

import json
import os
import subprocess
import sys
from pathlib import Path

import av
import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).parent / "helpers"))
from commands import OFFLINE, run as run_until

BIN = Path(sys.executable).parent
HELPERS = Path(__file__).parent / "helpers"


def run(args: list[str], cwd: Path, timeout: int = 300) -> subprocess.CompletedProcess:
    """Run a command from a neutral folder (so nothing is imported from the repo by accident)."""
    result = run_until(args, cwd=cwd, env={**os.environ, **OFFLINE}, timeout=timeout)
    assert result.returncode == 0, f"{args[0]} failed:\n{result.stdout[-3000:]}\n{result.stderr[-5000:]}"
    return result


def test_lerobot_eval_discovers_the_murm_env_type(tmp_path):
    result = run([str(BIN / "lerobot-eval"), "--help"], cwd=tmp_path)
    usage = result.stdout + result.stderr
    assert "Imported third-party plugin: lerobot_policy_murm" in usage
    env_types = next(line for line in usage.splitlines() if "--env.type {" in line)
    assert "murm" in env_types


def test_lerobot_make_env_builds_async_batches_of_the_murm_env(tmp_path):
    script = """
import numpy as np
from lerobot.utils.import_utils import register_third_party_plugins
register_third_party_plugins()
from lerobot.envs.factory import make_env, make_env_config
from lerobot.envs.utils import preprocess_observation
cfg = make_env_config("murm", task="place_in_random_box", cameras=["global", "side"])
vec = make_env(cfg, n_envs=2, use_async_envs=True)["murm"][0]
obs, info = vec.reset(seed=[0, 1])
batch = preprocess_observation(obs)
print(sorted(batch), tuple(batch["observation.images.side_goal"].shape))
obs, reward, terminated, truncated, info = vec.step(np.zeros((2, 4), dtype=np.float32))
print(type(vec).__name__, info["is_success"].tolist(), vec.call("_max_episode_steps"))
vec.close()
"""
    out = run([sys.executable, "-c", script], cwd=tmp_path).stdout.splitlines()
    assert out[-2] == (
        "['observation.environment_state', 'observation.images.global', 'observation.images.global_goal', "
        "'observation.images.side', 'observation.images.side_goal', 'observation.state'] (2, 3, 48, 48)"
    )
    assert out[-1] == "AsyncVectorEnv [False, False] (100, 100)"


def test_lerobot_eval_runs_a_policy_in_the_murm_env_with_async_batches(tmp_path):
    policy_dir = tmp_path / "policy"
    run([sys.executable, str(HELPERS / "save_untrained_act.py"), str(policy_dir), "pick_up", "global,active"], tmp_path)
    out_dir = tmp_path / "eval"
    run(
        [
            str(BIN / "lerobot-eval"),
            f"--policy.path={policy_dir}",
            "--policy.device=cpu",
            "--env.type=murm",
            "--env.task=pick_up",
            "--env.cameras=[global,active]",
            "--eval.n_episodes=2",
            "--eval.batch_size=2",
            "--eval.use_async_envs=true",
            "--seed=3",
            f"--output_dir={out_dir}",
        ],
        cwd=tmp_path,
    )
    info = json.loads((out_dir / "eval_info.json").read_text())
    overall = info["overall"]
    assert overall["n_episodes"] == 2
    assert 0.0 <= overall["pc_success"] <= 100.0
    videos = [Path(p) for p in overall["video_paths"]]
    assert videos and all(p.stat().st_size > 1000 for p in videos)
    with av.open(str(videos[0])) as container:
        frames = [frame.to_ndarray(format="rgb24") for frame in container.decode(video=0)]
    assert len(frames) > 50 and frames[0].shape == (256, 256 + 2 * 128, 3)  # overview, then global and active
    for column in (256, 384):  # each camera's goal tile (lower half): the goal stays, and is not blank
        first, last = (f[160:, column + 8 : column + 120].astype(int) for f in (frames[0], frames[-1]))
        assert np.abs(first - last).mean() < 3 and first.std() > 10


@pytest.mark.parametrize(
    ("flag", "message"),
    [("--env.task=stack", "valid tasks"), ("--env.cameras=[wrist]", "valid cameras")],
)
def test_lerobot_cli_reports_bad_env_arguments_clearly(tmp_path, flag, message):
    args = [str(BIN / "lerobot-eval"), "--policy.path=none", "--env.type=murm", flag]
    result = run_until(args, cwd=tmp_path, env={**os.environ, **OFFLINE}, timeout=120)
    assert result.returncode != 0
    assert message in result.stdout + result.stderr
