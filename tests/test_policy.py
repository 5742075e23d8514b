"""The `murm` LeRobot policy: configuration, both batch paths of `forward`, acting with
camera masking, and the self-contained checkpoint."""

import shutil
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from lerobot.configs import FeatureType, PolicyFeature
from lerobot.datasets.lerobot_dataset import LeRobotDataset
from lerobot.datasets.sampler import EpisodeAwareSampler
from lerobot.policies.factory import get_policy_class, make_policy, make_pre_post_processors

from lerobot_murm.features import goal_image_key, image_key
from lerobot_murm.policy.configuration_murm import MurmConfig
from lerobot_murm.policy.iql import camera_keep_mask
from lerobot_murm.policy.modeling_murm import LOGGED, MurmPolicy
from lerobot_murm.policy.replay import replay_for_dataset
from lerobot_murm.training.train import build_policy
from lerobot_murm.vqvae.frames import episode_last_rows
from lerobot_murm.vqvae.latent_cache import build_latent_cache

sys.path.insert(0, str(Path(__file__).parent / "helpers"))
from commands import run_command

REPO = "local/place_in_box"


def make_config(encoder_dir, **overrides) -> MurmConfig:
    fields = {"method": "separated_q", "cameras": ["global", "adjacent"], "encoder_dir": str(encoder_dir)}
    return MurmConfig(**fields | overrides)


@pytest.fixture(scope="module")
def dataset(tiny_pipeline):
    root, _ = tiny_pipeline
    return LeRobotDataset(REPO, root=root, video_backend="pyav")


@pytest.fixture
def policy(tiny_pipeline, dataset):
    torch.manual_seed(0)
    return build_policy(make_config(tiny_pipeline[1]), dataset, torch.device("cpu"))


def observation(policy: MurmPolicy, batch: int = 3, seed: int = 0) -> dict[str, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    size = policy.config.encoder_config(policy.cameras[0]).image_size
    return {
        key: torch.rand(batch, 3, size, size, generator=g)
        for c in policy.cameras
        for key in (image_key(c), goal_image_key(c))
    }


def test_lerobot_resolves_the_murm_policy_class_by_its_naming_convention():
    assert get_policy_class("murm") is MurmPolicy


def test_bad_configurations_fail_with_clear_messages(tiny_pipeline, tmp_path):
    encoders = tiny_pipeline[1]
    with pytest.raises(ValueError, match="unknown method 'attention'"):
        make_config(encoders, method="attention")
    with pytest.raises(ValueError, match="'single' takes one camera"):
        make_config(encoders, method="single")
    with pytest.raises(ValueError, match="needs at least two cameras"):
        make_config(encoders, method="dropout", cameras=["global"])
    with pytest.raises(ValueError, match="2 epsilon values for 1 cameras"):
        make_config(encoders, method="single", cameras=["global"], epsilon=[1.0, 1.0])
    # the disk is read when the settings are loaded (by the policy and the commands), not before
    missing_camera = make_config(encoders, cameras=["global", "top"])
    with pytest.raises(FileNotFoundError, match="no VQ-VAE for camera 'top'"):
        missing_camera.load_encoder_settings()
    no_folder = MurmConfig(method="single", cameras=["global"])
    with pytest.raises(ValueError, match="no encoder settings for camera 'global' yet"):
        no_folder.encoder_config("global")
    with pytest.raises(ValueError, match="set encoder_dir"):
        no_folder.load_encoder_settings()
    shutil.copytree(encoders / "global", tmp_path / "global", ignore=shutil.ignore_patterns("latent_distance.json"))
    with pytest.raises(ValueError, match="pass epsilon explicitly or run `murm encode`"):
        make_config(tmp_path, method="single", cameras=["global"]).load_encoder_settings()
    given = make_config(tmp_path, method="single", cameras=["global"], epsilon=[2.0])
    given.load_encoder_settings()
    assert given.epsilon == [2.0] and given.encoder_config("global").camera == "global"


def test_view_dropout_is_on_for_dropout_and_may_be_added_to_separated_q(tiny_pipeline, dataset):
    encoders = tiny_pipeline[1]
    assert make_config(encoders, method="dropout").view_dropout
    assert not make_config(encoders, method="separated_q").view_dropout
    with pytest.raises(ValueError, match="view_dropout applies to 'dropout' and 'separated_q', not 'concat'"):
        make_config(encoders, method="concat", view_dropout=True)
    with pytest.raises(ValueError, match="always drops views"):
        make_config(encoders, method="dropout", view_dropout=False)

    def loss_with(view_dropout: bool) -> float:
        torch.manual_seed(0)
        policy = build_policy(make_config(encoders, view_dropout=view_dropout), dataset, torch.device("cpu"))
        state = torch.randn(64, 2, 2 * policy.config.latent_dim)
        transition = {
            "state": state,
            "next_state": state,
            "action": torch.zeros(64, policy.config.action_dim),
            "reward": torch.zeros(64),
            "done": torch.zeros(64),
            "keep": keep,
        }
        return policy.iql_loss(transition)[0].item()

    keep = camera_keep_mask(64, 2, 0.5, torch.Generator().manual_seed(0))  # the sampler draws it

    assert loss_with(True) != loss_with(False)
    assert loss_with(False) == loss_with(False)


def test_actor_scoped_dropout_hides_views_from_the_policy_only(tiny_pipeline, dataset):
    encoders = tiny_pipeline[1]
    with pytest.raises(ValueError, match="unknown dropout_scope 'critic'"):
        make_config(encoders, view_dropout=True, dropout_scope="critic")

    def logged_losses(**overrides) -> dict[str, float]:
        torch.manual_seed(0)
        policy = build_policy(make_config(encoders, **overrides), dataset, torch.device("cpu"))
        state = torch.randn(64, 2, 2 * policy.config.latent_dim)
        transition = {
            "state": state,
            "next_state": state.roll(1, 0),
            "action": torch.rand(64, policy.config.action_dim),
            "reward": torch.zeros(64),
            "done": torch.zeros(64),
            "keep": camera_keep_mask(64, 2, 0.5, torch.Generator().manual_seed(1)),
        }
        return dict(zip(LOGGED, policy.iql_loss(transition)[1].tolist(), strict=True))

    no_dropout = logged_losses(view_dropout=False)
    actor_only = logged_losses(view_dropout=True, dropout_scope="actor")
    everywhere = logged_losses(view_dropout=True, dropout_scope="all")
    for critic_side in ("value_loss", "critic_loss", "q", "v"):
        assert actor_only[critic_side] == no_dropout[critic_side]
    assert actor_only["actor_loss"] != no_dropout["actor_loss"]
    assert everywhere["value_loss"] != no_dropout["value_loss"]


def test_features_are_checked_against_the_encoders(tiny_pipeline):
    config = make_config(tiny_pipeline[1])
    config.load_encoder_settings()
    image = PolicyFeature(type=FeatureType.VISUAL, shape=(3, 16, 16))
    config.input_features = {image_key("global"): image, goal_image_key("global"): image}
    with pytest.raises(ValueError, match=r"needs observation\.images\.adjacent"):
        config.validate_features()
    gray = PolicyFeature(type=FeatureType.VISUAL, shape=(1, 16, 16))
    config.input_features = {k: gray for c in ("global", "adjacent") for k in (image_key(c), goal_image_key(c))}
    with pytest.raises(ValueError, match="the encoders take RGB images"):
        config.validate_features()
    # any size (the policy resizes as the encoders' frames were), goal images or none (hindsight goals)
    big = PolicyFeature(type=FeatureType.VISUAL, shape=(3, 96, 128))
    config.input_features = {image_key(c): big for c in ("global", "adjacent")}
    config.validate_features()


def test_the_epsilon_defaults_to_the_suggestion_murm_encode_wrote(tiny_pipeline):
    import json

    config = make_config(tiny_pipeline[1])
    assert config.epsilon is None  # read from the encoders when the settings are loaded
    config.load_encoder_settings()
    expected = [
        json.loads((tiny_pipeline[1] / c / "latent_distance.json").read_text())["suggested_epsilon"]
        for c in ("global", "adjacent")
    ]
    assert config.epsilon == pytest.approx(expected)


def lerobot_rows(policy: MurmPolicy, dataset: LeRobotDataset, batch_size: int = 16) -> dict:
    """A batch as lerobot-train hands it to the policy: LeRobot's sampler, loader and preprocessor."""
    meta = dataset.meta
    sampler = EpisodeAwareSampler(
        meta.episodes["dataset_from_index"],
        meta.episodes["dataset_to_index"],
        drop_n_last_frames=policy.config.drop_n_last_frames,
        shuffle=True,
        seed=0,
    )
    preprocessor, _ = make_pre_post_processors(policy.config, dataset_stats=meta.stats)
    return preprocessor(next(iter(torch.utils.data.DataLoader(dataset, batch_size=batch_size, sampler=sampler))))


@pytest.mark.parametrize("method", ["single", "concat", "dropout", "separated_q"])
def test_forward_on_lerobot_rows_trains_every_network_but_not_the_encoders(tiny_pipeline, dataset, method):
    cameras = ["global"] if method == "single" else ["global", "adjacent"]
    torch.manual_seed(0)
    policy = make_policy(make_config(tiny_pipeline[1], method=method, cameras=cameras), ds_meta=dataset.meta).train()
    batch = lerobot_rows(policy, dataset)
    codebook = policy.encoders["global"].quantizer.codebook.clone()
    loss, info = policy.forward(batch)
    loss.backward()
    assert torch.isfinite(loss) and set(info) >= {"value_loss", "critic_loss", "actor_loss"}
    for network in (policy.critic, policy.value, policy.actor):
        assert all(p.grad is not None and p.grad.abs().sum() > 0 for p in network.parameters())
    assert all(p.grad is None for p in policy.encoders.parameters())
    assert all(p.grad is None for p in policy.critic_target.parameters())
    torch.testing.assert_close(policy.encoders["global"].quantizer.codebook, codebook)  # no EMA drift
    assert -len(cameras) <= info["reward"] <= 0


def test_a_policy_made_for_an_image_dataset_holds_its_encoded_frames_and_refuses_last_frames(tiny_pipeline, dataset):
    """lerobot-train on images: every frame encoded once at construction; a transition needs a successor."""
    policy = make_policy(make_config(tiny_pipeline[1]), ds_meta=dataset.meta)
    rows = [0, 57, 599]
    images = torch.stack([dataset[i][image_key("adjacent")] for i in rows])
    torch.testing.assert_close(policy.replay.latents[1][rows], policy.encode("adjacent", images))
    with pytest.raises(ValueError, match="last frame of an episode"):
        policy.forward({"index": torch.tensor([0, 99])})
    saved = policy.state_dict()
    assert all(v.numel() < 1_000_000 for v in saved.values())  # the replay is not part of the checkpoint


def test_hindsight_goals_replace_the_goal_images_by_each_episode_s_last_frame(tiny_pipeline, dataset):
    rendered = replay_for_dataset(make_config(tiny_pipeline[1]), dataset, cache_dir=None)
    hindsight = replay_for_dataset(make_config(tiny_pipeline[1], hindsight_goals=True), dataset, cache_dir=None)
    last = torch.from_numpy(episode_last_rows(hindsight.episode.numpy()))
    for k in range(len(hindsight.cameras)):
        torch.testing.assert_close(hindsight.latents[k], rendered.latents[k])
        torch.testing.assert_close(hindsight.goal_latents[k], rendered.latents[k][last])
        assert not torch.equal(hindsight.goal_latents[k], rendered.goal_latents[k])


def test_the_goal_gap_script_measures_hindsight_goals_against_the_rendered_ones(tiny_pipeline, tmp_path):
    """scripts/hindsight_goal_gap.py, the measure REPORT.md quotes for the hindsight grid: on the
    tiny pipeline's six successful episodes, each camera's gap equals the caches' own."""
    root, encoders = tiny_pipeline
    script = Path(__file__).parents[1] / "scripts" / "hindsight_goal_gap.py"
    args = [sys.executable, script, "--dataset", root, "--encoders", encoders / "global", encoders / "adjacent"]
    out = run_command([*args, "--cache-dir", tmp_path], tmp_path)
    rows = {
        line.split("|")[1].strip(): line.split("|")[2:-1]
        for line in out.splitlines()
        if line.startswith("| ") and not line.startswith("| camera")
    }
    assert set(rows) == {"global", "adjacent"}
    for camera, cells in rows.items():
        cache = build_latent_cache(f"local/{root.name}", root, encoders / camera, tmp_path)
        gap = ((cache.latents(episode_last_rows(cache.episode_index)) - cache.goal_latents()) ** 2).sum(-1)
        assert cells[0].strip() == "6" and cells[2].strip() == "-"  # every episode succeeded
        assert cells[1].strip() == f"{np.median(gap):.2f}, {np.quantile(gap, 0.9):.2f} (6)"


def test_select_action_is_deterministic_and_within_the_action_box(policy):
    policy.eval()
    batch = observation(policy)
    first, second = policy.select_action(batch), policy.select_action(batch)
    assert first.shape == (3, 4) and first.abs().max() <= 1.0
    torch.testing.assert_close(first, second)


def test_masking_zeroes_whole_camera_pairs_at_rate_p_and_never_all(policy):
    batch = observation(policy, batch=4000)
    state = policy.state_from_observation(batch, mask_p=0.5)
    zeroed = (state == 0).all(-1)  # (B, cameras)
    assert not zeroed.all(-1).any()
    assert abs(zeroed.float().mean().item() - 0.25) < 0.03  # p - p^2 per camera, with the all-dropped rule
    assert not (policy.state_from_observation(batch) == 0).all(-1).any()


def test_a_camera_missing_from_the_observation_is_masked(policy):
    policy.eval()
    batch = observation(policy)
    full = policy.state_from_observation(batch)
    dropped = {k: v for k, v in batch.items() if k != image_key("adjacent")}
    state = policy.state_from_observation(dropped, mask_p=0.5)  # masking never hides the camera left
    assert (state[:, 1] == 0).all()
    torch.testing.assert_close(state[:, 0], full[:, 0])
    assert torch.isfinite(policy.select_action(dropped)).all()
    with pytest.raises(ValueError, match="no image of any of the policy's cameras"):
        policy.select_action({k: v for k, v in dropped.items() if k != image_key("global")})


def test_a_goal_set_once_serves_observations_without_goal_images(policy):
    policy.eval()
    batch = observation(policy)
    frames = {image_key(c): batch[image_key(c)] for c in policy.cameras}
    with pytest.raises(ValueError, match="no goal for camera 'global'"):
        policy.select_action(frames)
    goals = {c: (batch[goal_image_key(c)][0] * 255).round().to(torch.uint8) for c in policy.cameras}
    with_goals = frames | {goal_image_key(c): (goals[c] / 255).expand(3, -1, -1, -1) for c in policy.cameras}
    # as a camera photographs it: H x W x 3 uint8, here at twice the encoders' size (area-resized back)
    policy.set_goal({c: g.repeat_interleave(2, 1).repeat_interleave(2, 2).permute(1, 2, 0) for c, g in goals.items()})
    torch.testing.assert_close(policy.select_action(frames), policy.select_action(with_goals))
    policy.reset()  # a new episode keeps the goal
    torch.testing.assert_close(policy.select_action(frames), policy.select_action(with_goals))
    with pytest.raises(ValueError, match="missing \\['adjacent'\\]"):
        policy.set_goal({"global": goals["global"]})


def test_masking_blanks_a_single_camera_image(tiny_pipeline, dataset):
    config = make_config(tiny_pipeline[1], method="single", cameras=["global"])
    policy = build_policy(config, dataset, torch.device("cpu"))
    batch = observation(policy, batch=2000)
    blank = policy.encode("global", torch.zeros(1, 3, 16, 16))[0]
    state = policy.state_from_observation(batch, mask_p=0.1)
    latent = state[:, 0, : policy.config.latent_dim]
    rate = (latent == blank).all(-1).float().mean().item()
    assert 0.07 < rate < 0.13
    goal = state[:, 0, policy.config.latent_dim :]
    torch.testing.assert_close(goal, policy.encode("global", batch[goal_image_key("global")]))  # goals stay


def test_checkpoint_carries_the_encoders_and_loads_without_them(policy, tiny_pipeline, tmp_path):
    policy.eval()
    batch = observation(policy)
    expected = policy.select_action(batch)
    copy = tmp_path / "encoders"
    shutil.copytree(tiny_pipeline[1], copy)
    policy.config.encoder_dir = str(copy)
    policy.save_pretrained(tmp_path / "ckpt")
    shutil.rmtree(copy)  # the encoder folder is gone: the checkpoint alone must do
    loaded = MurmPolicy.from_pretrained(tmp_path / "ckpt")
    torch.testing.assert_close(loaded.select_action(batch), expected)
    assert loaded.config.epsilon == policy.config.epsilon
    pre, post = make_pre_post_processors(loaded.config, dataset_stats=None)
    assert pre is not None and post is not None


def test_polyak_update_moves_the_target_critic(policy):
    before = [p.clone() for p in policy.critic_target.parameters()]
    with torch.no_grad():
        for p in policy.critic.parameters():
            p.add_(1.0)
    policy.update()
    tau = policy.config.target_update_rate
    for old, new, source in zip(before, policy.critic_target.parameters(), policy.critic.parameters(), strict=True):
        torch.testing.assert_close(new, old + tau * (source - old))


def test_latent_statistics_standardise_the_networks_inputs(policy):
    g = torch.Generator().manual_seed(0)
    latents = [torch.randn(5000, policy.config.latent_dim, generator=g) * 0.2 + 0.3 for _ in policy.cameras]
    latents[0][:, 0] = 0.7  # a feature that never changes: its std is floored, not zero
    policy.fit_latent_statistics(latents)
    state = torch.cat([torch.stack(latents, 1), torch.stack(latents, 1)], -1)  # goals share the statistics
    normalised = policy.normalize(state)
    assert normalised[:, :, 1:].mean().abs() < 0.01 and (normalised[:, :, 1:].std() - 1).abs() < 0.01
    assert normalised[:, 0, 0].abs().max() < 1e-5 and policy.latent_std[0, 0] == policy.config.latent_std_floor


@pytest.mark.parametrize(
    ("method", "cameras"),
    [("single", ["global"]), ("concat", ["global", "adjacent"]), ("separated_q", ["global", "adjacent"])],
)
def test_widths_follow_the_papers_128_units_per_camera(tiny_pipeline, dataset, method, cameras):
    """Paper 5.1: V, the policy and the single Q are 128 units per camera; each separated Q
    head is 128 (4.3). width_per_camera=False keeps every network 128 wide."""

    def widths(**overrides) -> tuple[int, int, int]:
        config = make_config(tiny_pipeline[1], method=method, cameras=cameras, **overrides)
        policy = build_policy(config, dataset, torch.device("cpu"))
        return policy.value[0].out_features, policy.actor.mean[0].out_features, policy.critic.hidden

    per_camera = 128 * len(cameras)
    q_width = 128 if method == "separated_q" else per_camera
    assert widths() == (per_camera, per_camera, q_width)
    assert widths(width_per_camera=False) == (128, 128, 128)
    q_width_32 = 32 if method == "separated_q" else 32 * len(cameras)
    assert widths(hidden_units=32) == (32 * len(cameras), 32 * len(cameras), q_width_32)


def test_separated_q_can_leave_a_dropped_cameras_q_out_of_the_mean(tiny_pipeline, dataset):
    encoders = tiny_pipeline[1]
    with pytest.raises(ValueError, match="unknown dropped_q 'ignored'"):
        make_config(encoders, dropped_q="ignored")
    with pytest.raises(ValueError, match="dropped_q 'excluded' needs separated_q with view_dropout"):
        make_config(encoders, dropped_q="excluded")  # no view dropout
    policy = build_policy(make_config(encoders, view_dropout=True, dropped_q="excluded"), dataset, torch.device("cpu"))
    state = torch.randn(8, 2, 2 * policy.config.latent_dim)
    action = torch.rand(8, policy.config.action_dim)
    keep = torch.tensor([[True, False], [False, True]] * 4)
    with torch.no_grad():
        masked = policy.critic(state, action, keep)
        first_only = policy.critic(state, action, torch.tensor([[True, False]] * 8))
        second_only = policy.critic(state, action, torch.tensor([[False, True]] * 8))
        mean = policy.critic(state, action)
    torch.testing.assert_close(masked[:, 0::2], first_only[:, 0::2])
    torch.testing.assert_close(masked[:, 1::2], second_only[:, 1::2])
    torch.testing.assert_close(mean, (first_only + second_only) / 2)
    transition = {
        "state": state,
        "next_state": state.roll(1, 0),
        "action": action,
        "reward": torch.zeros(8),
        "done": torch.zeros(8),
        "keep": keep,
    }
    loss, _ = policy.iql_loss(transition)
    assert torch.isfinite(loss)


def test_the_authors_masking_protocol_masks_one_camera_on_a_third_of_the_steps(tiny_pipeline, dataset, policy):
    with pytest.raises(ValueError, match="unknown eval_mask_mode 'sometimes'"):
        make_config(tiny_pipeline[1], eval_mask_mode="sometimes")
    batch = observation(policy, batch=6000)
    zeroed = (policy.state_from_observation(batch, mask_mode="authors") == 0).all(-1)  # (B, cameras)
    assert zeroed.sum(-1).max() == 1  # at most one camera at a time
    assert abs(zeroed.any(-1).float().mean().item() - 1 / 3) < 0.03
    assert abs(zeroed[:, 0].float().mean().item() - 1 / 6) < 0.03  # the camera is drawn uniformly
    policy.config.eval_mask_mode = "authors"
    policy.mask_generator.manual_seed(0)
    acted = policy.select_action(observation(policy, batch=64))
    policy.mask_generator.manual_seed(0)
    state = policy.state_from_observation(observation(policy, batch=64), mask_mode="authors")
    torch.testing.assert_close(acted, policy.actor.act(state.flatten(1)))


def test_latent_standardisation_can_be_switched_off(tiny_pipeline, dataset):
    policy = build_policy(make_config(tiny_pipeline[1], standardize_latents=False), dataset, torch.device("cpu"))
    policy.fit_latent_statistics([torch.randn(100, policy.config.latent_dim) + 3 for _ in policy.cameras])
    state = torch.randn(4, 2, 2 * policy.config.latent_dim)
    torch.testing.assert_close(policy.normalize(state), state)
