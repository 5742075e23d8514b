"""A robot's own recording, made by stock LeRobot as `lerobot-record` makes one (two cameras under
other names, 96x128 video, 6-D state and action, no goal images, no success column), through
`murm train-vqvae`, `murm encode --to-dataset`, `lerobot-train --policy.type=murm` and a robot
loop's `select_action` towards a goal image; and the bad inputs such data brings."""

import json
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from lerobot.common.control_utils import predict_action
from lerobot.datasets.lerobot_dataset import LeRobotDataset
from lerobot.policies.factory import make_pre_post_processors
from lerobot.policies.utils import prepare_observation_for_inference

from lerobot_murm.features import ACTION, image_key, latent_goal_key, latent_key
from lerobot_murm.policy.modeling_murm import MurmPolicy
from lerobot_murm.vqvae import VQVAE, VQVAEConfig
from lerobot_murm.vqvae.code_packing import unpack_codes
from lerobot_murm.vqvae.frames import episode_last_rows
from lerobot_murm.vqvae.latent_dataset import LATENTS_FILE
from lerobot_murm.vqvae.resize import encoder_side, fit_images

sys.path.insert(0, str(Path(__file__).parent / "helpers"))
from commands import run_command
from one_line import murm_error

BIN = Path(sys.executable).parent
CAMERAS = ("laptop", "phone")
HEIGHT, WIDTH = 96, 128
JOINTS = ["shoulder_pan", "shoulder_lift", "elbow_flex", "wrist_flex", "wrist_roll", "gripper"]
EPISODE_LENGTHS = (20, 20, 20)
TINY_VQVAE = ["--steps", "20", "--batch-size", "16", "--codebook-size", "32"]


def record(root: Path, lengths: tuple[int, ...], video: bool = True) -> LeRobotDataset:
    """A dataset as `lerobot-record` writes an SO-101's: joint positions in degrees, two cameras.
    A bright square moves across both views as the joints move, so the frames differ."""
    camera = {
        "dtype": "video" if video else "image",
        "shape": (HEIGHT, WIDTH, 3),
        "names": ["height", "width", "channels"],
    }
    joints = {"dtype": "float32", "shape": (len(JOINTS),), "names": JOINTS}
    features = {image_key(c): camera for c in CAMERAS} | {"observation.state": joints, ACTION: joints}
    dataset = LeRobotDataset.create(
        "local/so101_own", fps=30, features=features, root=root, robot_type="so101_follower"
    )
    rng = np.random.default_rng(0)
    for length in lengths:
        start, end = rng.uniform(-90, 90, len(JOINTS)), rng.uniform(-90, 90, len(JOINTS))
        for t in range(length):
            state = (start + (end - start) * t / length).astype(np.float32)
            frame = {"observation.state": state, ACTION: state + 5.0, "task": "put the cube in the box"}
            for k, c in enumerate(CAMERAS):
                image = np.full((HEIGHT, WIDTH, 3), 40 + 60 * k, np.uint8)
                row, col = int(10 + 60 * t / length), int(10 + 90 * (t / length) ** (k + 1))
                image[row : row + 24, col : col + 24] = (230, 200, 40)
                frame[image_key(c)] = image
            dataset.add_frame(frame)
        dataset.save_episode(parallel_encoding=False)  # no fork from this multi-threaded test process
    dataset.finalize()
    return LeRobotDataset("local/so101_own", root=root)


@pytest.fixture(scope="module")
def recorded(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("own") / "so101_own"
    record(root, EPISODE_LENGTHS)
    return root


@pytest.fixture(scope="module")
def encoded(recorded, tmp_path_factory) -> tuple[Path, Path]:
    """(encoder_dir, latent dataset): `murm train-vqvae` on each camera (one named by its full
    key, one by its short name), then `murm encode --to-dataset`."""
    base = tmp_path_factory.mktemp("encoded")
    encoders = base / "vqvae"
    for camera in ("observation.images.laptop", "phone"):
        out = encoders / camera.removeprefix("observation.images.")
        run_command(
            [BIN / "murm", "train-vqvae", "--dataset", recorded, "--camera", camera, *TINY_VQVAE, "--out", out], base
        )
    log = run_command(
        [
            BIN / "murm",
            "encode",
            "--dataset",
            recorded,
            "--encoders",
            *(encoders / c for c in CAMERAS),
            "--cache-dir",
            base / "cache",
            "--to-dataset",
            base / "latents",
        ],
        base,
    )
    assert f"{sum(EPISODE_LENGTHS)} frames" in log
    return encoders, base / "latents"


@pytest.mark.slow
def test_an_encoder_records_the_stream_it_was_trained_on_and_how_it_was_resized(encoded):
    for camera in CAMERAS:
        config = json.loads((encoded[0] / camera / "config.json").read_text())
        assert config["camera"] == camera and config["source_key"] == image_key(camera)
        assert config["source_size"] == [HEIGHT, WIDTH] and config["image_size"] == 48
        assert config["resize"] == "center_crop_area"


@pytest.mark.slow
def test_without_goal_images_each_frame_s_goal_is_its_episode_s_last_frame(encoded):
    latents = LeRobotDataset("local/latents", root=encoded[1])
    description = json.loads((encoded[1] / LATENTS_FILE).read_text())
    assert description["goals"] == "hindsight"
    assert latents.meta.camera_keys == [] and tuple(latents.meta.features[ACTION]["shape"]) == (len(JOINTS),)
    table = latents.hf_dataset.with_format("numpy")[:]
    last = episode_last_rows(table["episode_index"])
    for camera in CAMERAS:
        size = len(description["cameras"][camera]["codebook"])
        codes = unpack_codes(np.stack(table[latent_key(camera)]), size, 144)
        goals = unpack_codes(np.stack(table[latent_goal_key(camera)]), size, 144)
        np.testing.assert_array_equal(goals, codes[last][table["episode_index"]])
        assert len(np.unique(codes, axis=0)) > len(EPISODE_LENGTHS)  # the frames did not all encode alike
    statistics = json.loads((encoded[0] / "laptop" / "latent_distance.json").read_text())
    assert statistics["goals"] == "hindsight" and statistics["suggested_epsilon"] > 0


@pytest.mark.slow
def test_lerobot_train_learns_the_robot_s_own_actions_and_the_policy_drives_towards_a_goal_image(
    recorded, encoded, tmp_path
):
    encoders, latents = encoded
    run_command(
        [
            BIN / "lerobot-train",
            "--policy.type=murm",
            f"--policy.cameras=[{','.join(CAMERAS)}]",
            f"--policy.encoder_dir={encoders}",
            "--policy.view_dropout=true",
            "--policy.dropout_scope=actor",
            "--policy.hidden_units=16",
            "--dataset.repo_id=local/latents",
            f"--dataset.root={latents}",
            "--wandb.enable=false",
            "--batch_size=8",
            "--num_workers=0",
            "--steps=2",
            "--save_freq=2",
            f"--output_dir={tmp_path / 'run'}",
        ],
        tmp_path,
    )
    checkpoint = tmp_path / "run" / "checkpoints" / "last" / "pretrained_model"
    policy = MurmPolicy.from_pretrained(checkpoint).eval()
    assert policy.config.action_dim == len(JOINTS)
    preprocessor, postprocessor = make_pre_post_processors(policy.config, pretrained_path=str(checkpoint))

    source = LeRobotDataset("local/so101_own", root=recorded)
    frame = source[5]
    observation = {
        image_key(c): (frame[image_key(c)].permute(1, 2, 0).numpy() * 255).round().astype(np.uint8) for c in CAMERAS
    } | {"observation.state": frame["observation.state"].numpy()}

    def act() -> torch.Tensor:  # a robot loop's step: LeRobot's own inference path
        return predict_action(dict(observation), policy, torch.device("cpu"), preprocessor, postprocessor, False)

    with pytest.raises(ValueError, match="no goal for camera 'laptop'"):
        act()
    policy.set_goal_from_dataset(source, EPISODE_LENGTHS[0] - 1)  # where the first episode ended
    from_dataset = act()
    policy.set_goal({c: observation[image_key(c)] for c in CAMERAS})  # a goal photographed by the cameras
    photographed = act()
    assert from_dataset.shape == photographed.shape == (1, len(JOINTS))
    assert not torch.equal(from_dataset, photographed)  # the goal steers the action
    # the policy acts in [-1, 1]; LeRobot's postprocessor maps that to the robot's range (degrees)
    # by the dataset's statistics
    low, high = (torch.as_tensor(source.meta.stats[ACTION][k], dtype=torch.float32) for k in ("min", "max"))
    raw = policy.select_action(preprocessor(prepare_observation_for_inference(dict(observation), torch.device("cpu"))))
    assert raw.abs().max() <= 1
    torch.testing.assert_close(photographed, (raw + 1) / 2 * (high - low) + low)
    del observation[image_key("phone")]  # the phone camera drops out: the policy masks it and acts on
    assert torch.isfinite(act()).all()


@pytest.mark.slow
def test_lerobot_train_on_the_recording_itself_encodes_its_video_frames_once(recorded, encoded, tmp_path):
    """No latent dataset: the policy encodes every frame when it starts (hindsight goals, frames
    resized as the encoders' were) while LeRobot's loader decodes the videos for nothing."""
    run_command(
        [
            BIN / "lerobot-train",
            "--policy.type=murm",
            f"--policy.cameras=[{','.join(CAMERAS)}]",
            f"--policy.encoder_dir={encoded[0]}",
            "--policy.hidden_units=16",
            "--dataset.repo_id=local/so101_own",
            f"--dataset.root={recorded}",
            "--dataset.video_backend=pyav",
            "--wandb.enable=false",
            "--batch_size=4",
            "--num_workers=0",
            "--steps=1",
            "--save_freq=1",
            f"--output_dir={tmp_path / 'run'}",
        ],
        tmp_path,
    )
    config = json.loads((tmp_path / "run/checkpoints/last/pretrained_model/config.json").read_text())
    assert config["input_features"][image_key("laptop")]["shape"] == [3, HEIGHT, WIDTH]


def test_frames_are_centre_cropped_to_a_square_then_area_resized_and_never_upsampled():
    images = torch.randint(0, 256, (2, 3, HEIGHT, WIDTH), dtype=torch.uint8)
    square = images[..., :, 16:112].double()  # the centre 96x96 of 96x128
    expected = square.unflatten(-1, (48, 2)).unflatten(-3, (48, 2)).mean(dim=(-3, -1)).round()
    assert encoder_side(HEIGHT, WIDTH, 48) == 48
    torch.testing.assert_close(fit_images(images, 48), expected.to(torch.uint8), atol=1, rtol=0)
    same = torch.rand(2, 3, 48, 48)
    assert fit_images(same, 48) is same  # frames at the encoder's side (murm collect's) pass untouched
    assert encoder_side(16, 16, 48) == 16 and encoder_side(30, 41, 48) == 28  # a multiple of 4, never larger


@pytest.mark.parametrize(
    ("camera", "message"),
    [
        ("wrist", "has no camera 'wrist'; its cameras: ['laptop', 'phone']"),
        ("observation.images.wrist", "has no camera 'observation.images.wrist'; its cameras: ['laptop', 'phone']"),
        ("observation.state", "observation.state in "),
        ("action", "is no camera stream (MURM's cameras are the RGB image or video streams under observation.images.)"),
    ],
)
def test_a_camera_that_is_not_in_the_dataset_or_not_an_image_is_one_line(recorded, tmp_path, capsys, camera, message):
    argv = ["train-vqvae", "--dataset", recorded, "--camera", camera, "--out", tmp_path / "vq"]
    code, line = murm_error(argv, capsys)
    assert code == 2 and line.startswith("murm train-vqvae: ") and message in line, line
    assert not (tmp_path / "vq").exists()


def test_an_episode_of_one_frame_is_one_line(tmp_path, capsys):
    root, encoder = tmp_path / "short", tmp_path / "vq"
    record(root, (3, 1), video=False)
    code, line = murm_error(["train-vqvae", "--dataset", root, "--camera", "laptop", "--out", encoder], capsys)
    assert code == 2 and "episode 1 of" in line and "has a single frame" in line, line
    VQVAE(VQVAEConfig(camera="laptop", source_size=[HEIGHT, WIDTH])).save(encoder)  # as if trained elsewhere
    code, line = murm_error(["encode", "--dataset", root, "--encoders", encoder, "--cache-dir", tmp_path / "c"], capsys)
    assert code == 2 and "episode 1 of" in line and "has a single frame" in line, line
