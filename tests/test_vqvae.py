"""VQ-VAE: shapes, straight-through gradients, checkpoints, training output, the latent cache."""

import json
import signal
import subprocess
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch

from lerobot_murm.collection import CollectConfig, collect
from lerobot_murm.collection.dataset import episode_successes
from lerobot_murm.expert import PAPER_NOISE_STD
from lerobot_murm.vqvae import VQVAE, VQVAEConfig
from lerobot_murm.vqvae.frames import camera_stream, load_camera_frames, open_dataset
from lerobot_murm.vqvae.latent_cache import build_latent_cache
from lerobot_murm.vqvae.latent_distance import distance_statistics
from lerobot_murm.vqvae.train import train_vqvae

sys.path.insert(0, str(Path(__file__).parent / "helpers"))
from commands import run

MURM = Path(sys.executable).parent / "murm"
REPO = "local/murm_pick_up"
TINY = VQVAEConfig(
    steps=15, batch_size=16, hidden_channels=16, residual_channels=8, codebook_size=32, holdout_fraction=0.34
)


@pytest.fixture(scope="module")
def dataset_root(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("vq") / "ds"
    collect(
        CollectConfig(
            task="pick_up",
            root=root,
            episodes=3,
            workers=1,
            cameras=("global", "top"),
            image_size=16,
            noise_std=PAPER_NOISE_STD,
        )
    )
    return root


@pytest.fixture(scope="module")
def encoder_dir(dataset_root, tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("enc") / "global"
    train_vqvae(REPO, dataset_root, "global", out, TINY, device="cpu")
    return out


def test_a_48_pixel_image_becomes_a_12x12_grid_of_5_dim_codes():
    torch.manual_seed(0)
    model = VQVAE(VQVAEConfig()).eval()
    images = torch.randint(0, 256, (4, 48, 48, 3), dtype=torch.uint8)
    assert model.encode_indices(images).shape == (4, 12, 12)
    latents = model.encode(images)
    assert latents.shape == (4, 720)
    assert model.decode(latents).shape == (4, 3, 48, 48)
    # every latent cell is exactly a codebook vector
    cells = latents.view(4, 5, 12, 12).permute(0, 2, 3, 1).reshape(-1, 5)
    assert (cells[:, None, :] == model.quantizer.codebook[None]).all(-1).any(-1).all()


def test_the_quantiser_passes_gradients_straight_through_to_the_encoder():
    model = VQVAE(VQVAEConfig(image_size=16))
    out = model(torch.randint(0, 256, (2, 16, 16, 3), dtype=torch.uint8))
    out["recon_loss"].backward()  # the reconstruction loss alone: only the straight-through path
    first_encoder_conv = model.encoder[0].weight.grad
    assert first_encoder_conv is not None and first_encoder_conv.abs().sum() > 0
    assert model.quantizer.codebook.grad is None  # the codebook learns by EMA, not by gradient


def test_ema_updates_move_the_codebook_only_in_training():
    model = VQVAE(VQVAEConfig(image_size=16))
    images = torch.randint(0, 256, (8, 16, 16, 3), dtype=torch.uint8)
    before = model.quantizer.codebook.clone()
    model.eval()(images)
    assert torch.equal(before, model.quantizer.codebook)
    model.train()(images)
    assert not torch.equal(before, model.quantizer.codebook)


def test_checkpoint_round_trip_gives_the_same_latents(tmp_path):
    model = VQVAE(VQVAEConfig(camera="side", image_size=16)).eval()
    model.save(tmp_path)
    loaded = VQVAE.load(tmp_path)
    images = torch.randint(0, 256, (3, 16, 16, 3), dtype=torch.uint8)
    assert torch.equal(model.encode(images), loaded.encode(images))
    assert loaded.config == model.config


def test_training_writes_a_self_describing_checkpoint_with_metrics_and_figure(encoder_dir, dataset_root):
    config = VQVAEConfig.load(encoder_dir / "config.json")
    assert config.camera == "global" and config.image_size == 16 and config.latent_dim == 5 * 4 * 4
    assert config.dataset["repo_id"] == REPO and len(config.dataset["fingerprint"]) == 64
    metrics = json.loads((encoder_dir / "metrics.json").read_text())
    assert metrics["steps"] == 15 and metrics["heldout"]["images"] > 0
    assert 0 < metrics["heldout"]["psnr_db"] < 100
    assert (encoder_dir / "reconstructions.png").stat().st_size > 1000


def test_held_out_images_come_from_whole_episodes(dataset_root):
    from lerobot_murm.vqvae.train import split_episodes

    dataset = open_dataset(REPO, dataset_root)
    frames = load_camera_frames(dataset, camera_stream(dataset, "global"), 16)
    train, held = split_episodes(frames, 0.34, seed=0)
    assert len(train) + len(held) == len(frames.images) + len(frames.goals)
    assert len(held) == 100 + 1  # one whole episode and its goal image


def test_latent_cache_matches_the_encoder_exactly_and_is_reused(dataset_root, encoder_dir, tmp_path):
    cache = build_latent_cache(REPO, dataset_root, encoder_dir, tmp_path)
    model = VQVAE.load(encoder_dir)
    dataset = open_dataset(REPO, dataset_root)
    frames = load_camera_frames(dataset, camera_stream(dataset, "global"), model.config.image_size)
    expected = model.encode(torch.from_numpy(frames.images[:50])).numpy()
    np.testing.assert_array_equal(cache.latents(slice(0, 50)), expected)
    np.testing.assert_array_equal(cache.goal_latents(), model.encode(torch.from_numpy(frames.goals)).numpy())
    files = list(tmp_path.glob("*.npz"))
    assert len(files) == 1
    before = files[0].stat().st_mtime_ns
    build_latent_cache(REPO, dataset_root, encoder_dir, tmp_path)
    assert files[0].stat().st_mtime_ns == before  # served from disk, not rebuilt


def test_a_changed_encoder_or_dataset_never_gets_a_stale_cache(dataset_root, encoder_dir, tmp_path):
    build_latent_cache(REPO, dataset_root, encoder_dir, tmp_path / "cache")
    retrained = tmp_path / "retrained"
    train_vqvae(REPO, dataset_root, "global", retrained, replace(TINY, seed=1), device="cpu")
    build_latent_cache(REPO, dataset_root, retrained, tmp_path / "cache")
    assert len(list((tmp_path / "cache").glob("*.npz"))) == 2

    grown = tmp_path / "grown"
    subprocess.run(["cp", "-r", str(dataset_root), str(grown)], check=True)
    collect(
        CollectConfig(
            task="pick_up",
            root=grown,
            episodes=4,
            workers=1,
            cameras=("global", "top"),
            image_size=16,
            noise_std=PAPER_NOISE_STD,
            resume=True,
        )
    )
    cache = build_latent_cache(REPO, grown, encoder_dir, tmp_path / "cache")
    assert len(list((tmp_path / "cache").glob("*.npz"))) == 3
    assert len(cache.indices) == 400


def test_clear_errors_for_a_missing_camera_and_a_wrong_image_size(dataset_root, encoder_dir, tmp_path):
    with pytest.raises(ValueError, match="has no camera 'side'; its cameras: \\['global', 'top'\\]"):
        train_vqvae(REPO, dataset_root, "side", tmp_path / "x", TINY)
    model = VQVAE.load(encoder_dir)
    with pytest.raises(ValueError, match="trained on 16x16 RGB images; got a batch of shape \\(1, 48, 48, 3\\)"):
        model.encode(torch.zeros(1, 48, 48, 3, dtype=torch.uint8))


def test_distance_statistics_suggest_an_epsilon_between_the_two_distributions(dataset_root, encoder_dir, tmp_path):
    cache = build_latent_cache(REPO, dataset_root, encoder_dir, tmp_path)
    stats = distance_statistics(cache, episode_successes(REPO, dataset_root), samples=200)
    assert stats["successful_final_frames"]["count"] == 3
    assert stats["random_frames"]["count"] == 200
    assert stats["random_frames"]["p5"] <= stats["suggested_epsilon"] <= stats["random_frames"]["p95"] * 2
    assert -1.0 <= stats["youden_j"] <= 1.0


def test_the_cli_trains_and_encodes(dataset_root, tmp_path):
    out = tmp_path / "enc"
    train = [MURM, "train-vqvae", "--dataset", dataset_root, "--camera", "top", "--steps", "5", "--out", out]
    result = run(train + ["--batch-size", "8"], timeout=300)
    assert result.returncode == 0, result.stderr[-2000:]
    assert "held-out PSNR" in result.stdout
    result = run(
        [MURM, "encode", "--dataset", dataset_root, "--encoders", out, "--cache-dir", tmp_path / "c"], timeout=300
    )
    assert result.returncode == 0, result.stderr[-2000:]
    assert (tmp_path / "c" / "epsilon.json").exists() and (tmp_path / "c" / "latent_distances.png").exists()


def test_a_stopped_training_resumes_to_the_same_encoder_as_an_unbroken_one(dataset_root, tmp_path):
    steps = 600  # a resume state is written every 250 steps; the stop comes after the first
    out = tmp_path / "stopped"
    command = [
        str(MURM),
        "train-vqvae",
        "--dataset",
        str(dataset_root),
        "--camera",
        "global",
        "--steps",
        str(steps),
        "--batch-size",
        "8",
        "--device",
        "cpu",
        "--out",
        str(out),
    ]
    log = tmp_path / "stderr.txt"  # a file, not an unread pipe that a slow run could fill and block on
    with log.open("w") as stderr_file:
        process = subprocess.Popen(command, stdout=subprocess.DEVNULL, stderr=stderr_file)
        deadline = time.monotonic() + 240
        while not (out / "training_state.pt").exists() and process.poll() is None and time.monotonic() < deadline:
            time.sleep(0.02)
        process.send_signal(signal.SIGTERM)
        process.wait(timeout=120)
    stderr = log.read_text()
    assert process.returncode == 1, stderr[-2000:]
    assert "run the same command again to resume" in stderr
    stopped = json.loads((out / "metrics.json").read_text())
    assert stopped["interrupted"] and 250 <= stopped["steps"] < steps
    assert torch.load(out / "training_state.pt", weights_only=True)["step"] == stopped["steps"]  # no code in it
    assert VQVAE.load(out).config.steps == steps  # the encoder so far is usable

    resumed = run(command, timeout=300)
    assert resumed.returncode == 0, resumed.stderr[-2000:]
    assert f"resuming from step {stopped['steps']}" in resumed.stdout
    finished = json.loads((out / "metrics.json").read_text())
    assert not finished["interrupted"] and finished["steps"] == steps
    assert not (out / "training_state.pt").exists()

    unbroken = tmp_path / "unbroken"
    train_vqvae(REPO, dataset_root, "global", unbroken, replace(VQVAEConfig(), steps=steps, batch_size=8), device="cpu")
    resumed_weights = VQVAE.load(out).state_dict()
    for name, tensor in VQVAE.load(unbroken).state_dict().items():
        assert torch.equal(tensor, resumed_weights[name]), name
