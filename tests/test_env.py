"""The simulator's contract: spaces, seeding, goal images, success criteria, errors, robustness."""

import sys
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

from lerobot_murm.env import CAMERA_NAMES, GYM_IDS, TASK_NAMES, MurmEnv
from lerobot_murm.env.tasks import WORKSPACE_HIGH, WORKSPACE_LOW
from lerobot_murm.expert import ScriptedExpert
from lerobot_murm.features import goal_key

sys.path.insert(0, str(Path(__file__).parent / "helpers"))
from commands import run


def rollout(env: MurmEnv, seed: int, steps: int, action_seed: int = 0) -> list[dict]:
    rng = np.random.default_rng(action_seed)
    observations = [env.reset(seed=seed)[0]]
    for _ in range(steps):
        observations.append(env.step(rng.uniform(-1, 1, size=4))[0])
    return observations


def assert_same_observations(a: list[dict], b: list[dict]) -> None:
    assert len(a) == len(b)
    for obs_a, obs_b in zip(a, b, strict=True):
        assert obs_a["pixels"].keys() == obs_b["pixels"].keys()
        for key in obs_a["pixels"]:
            np.testing.assert_array_equal(obs_a["pixels"][key], obs_b["pixels"][key], err_msg=key)
        np.testing.assert_array_equal(obs_a["agent_pos"], obs_b["agent_pos"])
        np.testing.assert_array_equal(obs_a["environment_state"], obs_b["environment_state"])


@pytest.mark.parametrize("task", TASK_NAMES)
def test_registered_gym_env_passes_the_gymnasium_checker(task):
    env = gym.make(GYM_IDS[task])
    assert env.spec.max_episode_steps == 100
    check_env(env.unwrapped, skip_render_check=False)
    env.close()


def test_observation_has_five_cameras_goals_state_and_privileged_state(make_env):
    env = make_env(task="place_in_box")
    obs, info = env.reset(seed=3)
    assert info == {"is_success": False}
    expected = set(CAMERA_NAMES) | {goal_key(c) for c in CAMERA_NAMES}
    assert set(obs["pixels"]) == expected
    for image in obs["pixels"].values():
        assert image.shape == (48, 48, 3) and image.dtype == np.uint8
        assert image.std() > 5, "an image is blank"
    assert obs["agent_pos"].shape == (4,) and obs["agent_pos"].dtype == np.float32
    assert obs["environment_state"].shape == (6,)
    assert env.observation_space.contains(obs)
    frame = env.render()  # the 256x256 overview, then a 128-wide column per camera: view above goal
    assert frame.shape == (256, 256 + 5 * 128, 3) and frame.dtype == np.uint8


def test_render_tiles_each_camera_as_observed_above_its_goal_beside_the_overview(make_env):
    env = make_env(task="pick_up", cameras=("side", "active"), image_size=16, render_size=64)
    obs, _ = env.reset(seed=2)
    obs, *_ = env.step(np.array([0.5, 0.0, -1.0, 0.0]))
    frame = env.render()
    assert frame.shape == (64, 64 + 2 * 32, 3)
    overview = make_env(task="pick_up", cameras=("side",), render_size=64, render_views=False)
    overview.reset(seed=2)
    assert overview.render().shape == (64, 64, 3)
    for column, camera in enumerate(("side", "active")):
        tiles = frame[:, 64 + 32 * column : 64 + 32 * (column + 1)]
        for row, key in enumerate((camera, goal_key(camera))):
            tile = tiles[32 * row : 32 * (row + 1)]
            # 2x nearest-neighbour enlargement of the observed image; the label covers the top-left corner
            np.testing.assert_array_equal(tile[16:, 16:], obs["pixels"][key][8:, 8:].repeat(2, 0).repeat(2, 1))
            assert np.any(tile[:8, :] != obs["pixels"][key][:4].repeat(2, 0).repeat(2, 1)), "no label"


def test_camera_subset_and_image_size_are_respected(make_env):
    env = make_env(task="pick_up", cameras=("global", "active"), image_size=32, goal_images=False)
    obs, _ = env.reset(seed=0)
    assert set(obs["pixels"]) == {"global", "active"}
    assert obs["pixels"]["active"].shape == (32, 32, 3)


@pytest.mark.parametrize("task", TASK_NAMES)
def test_same_seed_gives_the_same_episode_image_for_image(make_env, task):
    first = rollout(make_env(task=task), seed=11, steps=15)
    second = rollout(make_env(task=task), seed=11, steps=15)
    assert_same_observations(first, second)
    other = rollout(make_env(task=task), seed=12, steps=0)
    assert not np.array_equal(other[0]["environment_state"], first[0]["environment_state"])


def test_reset_forgets_the_previous_episode(make_env):
    """A reused env gives the same episode as a fresh one (no state leaks between episodes)."""
    reused = make_env(task="pick_up")
    rollout(reused, seed=5, steps=30, action_seed=9)
    assert_same_observations(rollout(reused, seed=4, steps=10), rollout(make_env(task="pick_up"), seed=4, steps=10))


@pytest.mark.parametrize("task", TASK_NAMES)
def test_goal_rendering_restores_the_scene_exactly(make_env, task):
    with_goals = rollout(make_env(task=task, goal_images=True), seed=2, steps=10)
    without = rollout(make_env(task=task, goal_images=False), seed=2, steps=10)
    for obs in with_goals:
        for camera in CAMERA_NAMES:
            obs["pixels"].pop(goal_key(camera))
    assert_same_observations(with_goals, without)


@pytest.mark.parametrize("task", TASK_NAMES)
def test_goal_images_show_a_different_scene_and_stay_fixed(make_env, task):
    env = make_env(task=task)
    episode = rollout(env, seed=8, steps=5)
    for camera in CAMERA_NAMES:
        goal = episode[0]["pixels"][goal_key(camera)]
        assert not np.array_equal(goal, episode[0]["pixels"][camera]), camera
        for obs in episode[1:]:
            np.testing.assert_array_equal(obs["pixels"][goal_key(camera)], goal)


def _move_object(env: MurmEnv, position) -> None:
    orientation = env.client.getBasePositionAndOrientation(env.task.object_body)[1]
    env.client.resetBasePositionAndOrientation(env.task.object_body, list(position), orientation)


@pytest.mark.parametrize(("task", "radius"), [("place_in_box", 0.03), ("place_in_random_box", 0.05)])
def test_place_success_is_the_distance_to_the_goal_box_centre(make_env, task, radius):
    env = make_env(task=task, cameras=("top",), goal_images=False)
    env.reset(seed=1)
    goal = env.task.goal_position
    assert not env.task.is_success(env.client)
    for offset, expected in ((0.0, True), (radius - 0.002, True), (radius + 0.002, False)):
        _move_object(env, goal + np.array([offset, 0.0, 0.0]))
        assert env.task.is_success(env.client) is expected, offset


def test_place_in_box_goal_is_one_of_nine_boxes_and_varies(make_env):
    env = make_env(task="place_in_box", cameras=("top",), goal_images=False)
    goals = set()
    for seed in range(40):
        env.reset(seed=seed)
        goals.add(tuple(np.round(env.task.goal_position, 4)))
    assert len(goals) == 9


def test_random_box_is_placed_in_three_dimensions(make_env):
    env = make_env(task="place_in_random_box", cameras=("top",), goal_images=False)
    goals = []
    for seed in range(10):
        env.reset(seed=seed)
        goals.append(env.task.goal_position)
    assert np.ptp(np.array(goals), axis=0).min() > 0.05, "box position must vary in x, y and z"


def test_pick_up_success_is_a_five_centimetre_lift(make_env):
    env = make_env(task="pick_up", cameras=("top",), goal_images=False)
    env.reset(seed=0)
    start = env.task.initial_object_position
    _move_object(env, start + [0, 0, 0.048])
    assert not env.task.is_success(env.client)
    _move_object(env, start + [0, 0, 0.052])
    assert env.task.is_success(env.client)


def test_pick_up_scatters_several_shapes(make_env):
    env = make_env(task="pick_up", cameras=("top",), goal_images=False)
    shapes = set()
    for seed in range(10):
        env.reset(seed=seed)
        shapes.add(env.task.object_shape.name)
    assert len(shapes) >= 3


@pytest.mark.parametrize("task", TASK_NAMES)
def test_scripted_expert_succeeds_through_the_real_physics(make_env, task):
    """Grasping, carrying and placing work in the simulator (the expert itself is tested elsewhere)."""
    env = make_env(task=task, cameras=("top",), goal_images=False)
    expert = ScriptedExpert(task)
    obs, _ = env.reset(seed=0)
    successes = []
    for _ in range(100):
        obs, reward, _terminated, _truncated, info = env.step(expert.act(obs))
        successes.append(info["is_success"])
        assert reward == float(info["is_success"])
    assert successes[-1], f"{task}: expert ended in phase {expert.phase}"


def test_actions_move_the_end_effector_a_few_centimetres(make_env):
    env = make_env(task="place_in_box", cameras=("top",), goal_images=False)
    obs, _ = env.reset(seed=0)
    start = obs["agent_pos"][:3].copy()
    for _ in range(4):
        obs, *_ = env.step(np.array([1.0, 0.0, 0.0, -1.0]))
    moved = obs["agent_pos"][:3] - start
    assert 0.06 < moved[0] < 0.11 and abs(moved[1]) < 0.01 and abs(moved[2]) < 0.01


def test_out_of_range_actions_are_clipped(make_env):
    big = rollout_with_action(make_env(task="pick_up"), np.array([7.0, -3.0, 2.0, 9.0]))
    unit = rollout_with_action(make_env(task="pick_up"), np.array([1.0, -1.0, 1.0, 1.0]))
    assert_same_observations(big, unit)


def rollout_with_action(env: MurmEnv, action: np.ndarray) -> list[dict]:
    observations = [env.reset(seed=0)[0]]
    observations += [env.step(action)[0] for _ in range(5)]
    return observations


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"task": "stack_blocks"}, "valid tasks: \\['place_in_box', 'place_in_random_box', 'pick_up'\\]"),
        ({"cameras": ("global", "wrist")}, "valid cameras: \\['global', 'adjacent', 'side', 'top', 'active'\\]"),
        ({"cameras": ()}, "at least one camera"),
        ({"image_size": 4}, "image_size must be an integer in \\[8, 512\\]"),
        ({"image_size": 48.0}, "image_size must be an integer"),
    ],
)
def test_bad_construction_arguments_name_the_valid_choices(kwargs, message):
    with pytest.raises(ValueError, match=message):
        MurmEnv(**kwargs)


@pytest.mark.parametrize(
    ("action", "message"),
    [
        (np.array([0.0, np.nan, 0.0, 0.0]), "action must be finite"),
        (np.array([0.0, 0.0, np.inf, 0.0]), "action must be finite"),
        (np.zeros(3), "action must have shape \\(4,\\)"),
    ],
)
def test_bad_actions_are_rejected_with_a_clear_error(make_env, action, message):
    env = make_env(task="place_in_box", cameras=("top",), goal_images=False)
    env.reset(seed=0)
    with pytest.raises(ValueError, match=message):
        env.step(action)


def test_step_before_reset_is_an_error(make_env):
    with pytest.raises(RuntimeError, match="reset"):
        make_env(task="pick_up").step(np.zeros(4))


@pytest.mark.parametrize("task", TASK_NAMES)
def test_fifty_random_episodes_keep_the_physics_sane(make_env, task):
    """Violent random actions: no NaN, nothing through the table or out of the world, arm in its box."""
    env = make_env(task=task, cameras=("top",), image_size=8, goal_images=False)
    rng = np.random.default_rng(0)
    for episode in range(50):  # 5,000 violent steps per task (physics alone: about 25 s)
        obs, _ = env.reset(seed=episode)
        for _ in range(100):
            obs, *_ = env.step(rng.choice([-1.5, -1.0, 0.0, 1.0, 1.5], size=4))
            ee, obj = obs["agent_pos"][:3], obs["environment_state"][:3]
            assert np.all(np.isfinite(obs["agent_pos"])) and np.all(np.isfinite(obs["environment_state"]))
            assert obj[2] > -0.005, f"object fell through the table in episode {episode}"
            assert np.all(np.abs(obj[:2]) < 1.0), f"object left the table in episode {episode}"
            assert np.all(ee >= WORKSPACE_LOW - 0.02) and np.all(ee <= WORKSPACE_HIGH + 0.02), episode


@pytest.mark.parametrize("task", TASK_NAMES)
def test_the_global_camera_sees_the_target_object_at_reset(make_env, task):
    """The overview camera shows the object several pixels across at 48x48 (the other views are
    the authors' and need not: their adjacent view looks at the boxes, not the spawn strip)."""
    import pybullet

    from lerobot_murm.env.cameras import CAMERAS, projection_matrix

    env = make_env(task=task, cameras=("global",), goal_images=False)
    for seed in range(4):
        env.reset(seed=seed)
        _, _, _, _, segmentation = env.client.getCameraImage(
            48, 48, CAMERAS["global"].view_matrix(), projection_matrix(), renderer=pybullet.ER_TINY_RENDERER
        )
        object_pixels = int((np.asarray(segmentation) == env.task.object_body).sum())
        assert object_pixels >= 3, f"the global camera shows {object_pixels} pixels of the object (seed {seed})"


def test_the_authors_box_grid_lands_on_ours():
    """The map from the authors' scene (boxes at x 0.275-0.525, y -0.25 to -0.5 on a table top at
    z 0.9925) puts each of their nine boxes on one of ours: their cameras frame our task as theirs."""
    from lerobot_murm.env.cameras import AUTHORS_TABLE_TOP_Z, from_authors_frame
    from lerobot_murm.env.tasks import PlaceInBox

    theirs = {
        from_authors_frame((x, y, AUTHORS_TABLE_TOP_Z))[:2] for x in (0.275, 0.4, 0.525) for y in (-0.25, -0.375, -0.5)
    }
    ours = {(x, y) for x in PlaceInBox.TRAY_XS for y in PlaceInBox.TRAY_YS}
    assert len(theirs) == 9 and all(min(np.hypot(a - c, b - d) for c, d in ours) < 1e-9 for a, b in theirs)
    assert from_authors_frame((0.0, 0.0, AUTHORS_TABLE_TOP_Z))[2] == 0.0


def test_observations_are_the_sharp_render_blurred_as_the_authors_blur(make_env):
    """Every camera's observation is TinyRenderer's image through OpenCV's 5x5 Gaussian, and
    rendering is deterministic: a second simulator with the same seed gives the same pixels."""
    from lerobot_murm.env.cameras import blur, render_view

    env = make_env(task="pick_up", image_size=48, goal_images=False)
    obs, _ = env.reset(seed=3)
    rig = env._rig
    for camera in CAMERA_NAMES:
        sharp = render_view(env.client, rig._view(camera, env.robot.ee_position()), rig._projection, 48)
        np.testing.assert_array_equal(obs["pixels"][camera], blur(sharp))
        assert not np.array_equal(sharp, blur(sharp)), camera
    again, _ = make_env(task="pick_up", image_size=48, goal_images=False).reset(seed=3)
    for camera in CAMERA_NAMES:
        np.testing.assert_array_equal(obs["pixels"][camera], again["pixels"][camera])


def test_the_simulator_prints_nothing_even_when_left_open_at_exit(tmp_path):
    """pybullet's C code prints at import and connect, and its clean-up fails noisily at exit."""
    script = (
        "import gymnasium as gym, lerobot_murm\n"
        "env = gym.make('murm/PickUp-v0', cameras=('global',), image_size=16)\n"
        "env.reset(seed=0)\n"
    )
    result = run([sys.executable, "-c", script], cwd=tmp_path, timeout=120)
    assert result.returncode == 0 and result.stdout == "" and result.stderr == "", result.stdout + result.stderr
