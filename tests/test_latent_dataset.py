"""Latent datasets (`murm encode --to-dataset`): written by LeRobot's dataset tools, read by
LeRobotDataset and `lerobot-train`, the same transitions as `murm train`, Hub push/pull, and
`lerobot-train` under `accelerate launch` with two processes."""

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from lerobot.datasets.lerobot_dataset import LeRobotDataset
from lerobot.datasets.sampler import EpisodeAwareSampler
from lerobot.policies.factory import make_policy, make_pre_post_processors
from scipy import stats

from lerobot_murm.features import latent_goal_key, latent_key
from lerobot_murm.policy.configuration_murm import MurmConfig
from lerobot_murm.policy.replay import replay_for_dataset
from lerobot_murm.publishing import pull_dataset, push_dataset
from lerobot_murm.vqvae.code_packing import unpack_codes
from lerobot_murm.vqvae.latent_cache import build_latent_cache
from lerobot_murm.vqvae.latent_dataset import read_latent_caches

sys.path.insert(0, str(Path(__file__).parent / "helpers"))
from commands import OFFLINE, run, run_command

BIN = Path(sys.executable).parent
SCRIPTS = Path(__file__).parents[1] / "scripts"
CAMERAS = ["global", "adjacent"]
LATENT_REPO = "local/latents"
TRAIN_ARGS = [
    "--policy.type=murm",
    "--policy.method=dropout",
    f"--policy.cameras=[{','.join(CAMERAS)}]",
    f"--dataset.repo_id={LATENT_REPO}",
    "--wandb.enable=false",
    "--batch_size=16",
    "--num_workers=0",
]


@pytest.fixture(scope="module")
def latents(tiny_pipeline, tmp_path_factory) -> Path:
    """`murm encode --to-dataset` on the tiny demonstrations; the latent cache folder is beside it."""
    root, encoders = tiny_pipeline
    base = tmp_path_factory.mktemp("latents")
    out = run_command(
        [
            BIN / "murm",
            "encode",
            "--dataset",
            root,
            "--encoders",
            *(encoders / c for c in CAMERAS),
            "--cache-dir",
            base / "cache",
            "--to-dataset",
            base / "latents",
        ],
        cwd=base,
    )
    assert "latent dataset" in out and "600 frames" in out
    return base / "latents"


def murm_config(encoders: Path) -> MurmConfig:
    return MurmConfig(method="dropout", cameras=CAMERAS, encoder_dir=str(encoders))


def test_the_latent_dataset_is_a_lerobot_dataset_of_the_encoders_codes_without_images(tiny_pipeline, latents):
    root, encoders = tiny_pipeline
    source = LeRobotDataset("local/place_in_box", root=root)
    dataset = LeRobotDataset(LATENT_REPO, root=latents)
    assert dataset.meta.camera_keys == [] and not list(latents.rglob("*.png"))
    assert "observation.state" in dataset.meta.features and "observation.environment_state" not in dataset.meta.features
    assert len(dataset) == len(source) and dataset.meta.total_episodes == source.meta.total_episodes
    for camera in CAMERAS:
        cache = build_latent_cache("local/place_in_box", root, encoders / camera, latents.parent / "cache")
        for row in (0, 99, 100, 599):
            item, original = dataset[row], source[row]
            size, codes = len(cache.codebook), cache.indices[0].size
            unpacked = unpack_codes(item[latent_key(camera)].numpy()[None], size, codes)[0]
            np.testing.assert_array_equal(unpacked, cache.indices[row].reshape(-1))
            assert size == 32 and len(item[latent_key(camera)]) == -(-codes // 12)  # 5 bits, 12 to an int64
            episode = int(item["episode_index"])
            goal = unpack_codes(item[latent_goal_key(camera)].numpy()[None], size, codes)[0]
            np.testing.assert_array_equal(goal, cache.goal_indices[episode].reshape(-1))
            assert torch.equal(item["action"], original["action"]) and item["index"] == original["index"]
        # the codes read back as the latent cache: the same latents, bit for bit
        (read,) = read_latent_caches(dataset, [camera])
        np.testing.assert_array_equal(read.latents(), cache.latents())
        np.testing.assert_array_equal(read.goal_latents(), cache.goal_latents())


def test_codes_of_other_encoders_are_refused(latents):
    dataset = LeRobotDataset(LATENT_REPO, root=latents)
    with pytest.raises(ValueError, match="another encoder than the policy's"):
        read_latent_caches(dataset, ["global"], {"global": "0" * 64})
    with pytest.raises(ValueError, match="no codes of \\['top'\\]"):
        read_latent_caches(dataset, ["top"])


def test_murm_encode_will_not_overwrite_a_folder(tiny_pipeline, latents):
    root, encoders = tiny_pipeline
    args = [BIN / "murm", "encode", "--dataset", root, "--encoders", encoders / "global", "--to-dataset", latents]
    result = run(args, timeout=300, cwd=latents.parent, env={**os.environ, **OFFLINE})
    assert result.returncode != 0 and "exists" in result.stderr and "Traceback" not in result.stderr


def test_both_trainers_draw_the_same_transitions(tiny_pipeline, latents):
    """`murm train` (its sampler over the image dataset's latent cache) against what reaches the
    policy under lerobot-train (LeRobot's own sampler, loader and preprocessor over the latent
    dataset, then the policy's relabelling): the same start frames, the same share of hindsight
    goals and the same distribution of their offsets (two-sample tests at the 1 % level)."""
    root, encoders = tiny_pipeline
    n = 12_000

    config = murm_config(encoders)
    replay = replay_for_dataset(config, LeRobotDataset("local/place_in_box", root=root), latents.parent / "cache")
    fast = replay.sample(n, torch.Generator().manual_seed(0))

    dataset = LeRobotDataset(LATENT_REPO, root=latents)
    config = murm_config(encoders)
    policy = make_policy(config, ds_meta=dataset.meta)
    preprocessor, _ = make_pre_post_processors(config, dataset_stats=dataset.meta.stats)
    episodes = dataset.meta.episodes
    sampler = EpisodeAwareSampler(
        episodes["dataset_from_index"],
        episodes["dataset_to_index"],
        drop_n_last_frames=config.drop_n_last_frames,
        shuffle=True,
        seed=0,
    )
    loader = torch.utils.data.DataLoader(dataset, batch_size=256, sampler=sampler)
    torch.manual_seed(0)
    rows, relabelled, offsets = [], [], []
    while sum(map(len, rows)) < n:
        for batch in loader:
            index = preprocessor(batch)["index"]
            b = policy.replay.transitions(index)
            rows.append(b.row)
            relabelled.append(b.relabelled)
            offsets.append((b.goal_row - b.row)[b.relabelled])
    slow_rows, slow_relabelled, slow_offsets = torch.cat(rows)[:n], torch.cat(relabelled), torch.cat(offsets)

    fast_offsets = (fast.goal_row - fast.row)[fast.relabelled]
    assert stats.ks_2samp(fast_offsets.numpy(), slow_offsets.numpy()).pvalue > 0.01
    assert stats.ks_2samp(fast.row.numpy(), slow_rows.numpy()).pvalue > 0.01
    table = [
        [int(fast.relabelled.sum()), int((~fast.relabelled).sum())],
        [int(slow_relabelled.sum()), int((~slow_relabelled).sum())],
    ]
    assert stats.chi2_contingency(table).pvalue > 0.01
    assert abs(slow_relabelled.float().mean().item() - config.her_ratio) < 0.01
    assert slow_offsets.min() >= 1 and fast_offsets.min() >= 1


@pytest.fixture(scope="module")
def lerobot_trained(tiny_pipeline, latents, tmp_path_factory) -> tuple[str, Path]:
    """(the log, the checkpoint) of a short stock `lerobot-train` run on the latent dataset."""
    base = tmp_path_factory.mktemp("lerobot_train")
    log = run_command(
        [
            BIN / "lerobot-train",
            *TRAIN_ARGS,
            f"--policy.encoder_dir={tiny_pipeline[1]}",
            f"--dataset.root={latents}",
            "--steps=4",
            "--save_freq=4",
            "--log_freq=1",
            f"--output_dir={base / 'run'}",
        ],
        cwd=base,
    )
    return log, base / "run" / "checkpoints" / "last" / "pretrained_model"


def test_lerobot_train_learns_from_the_latent_dataset_and_lerobot_eval_runs_its_checkpoint(lerobot_trained, tmp_path):
    log, checkpoint = lerobot_trained
    assert "critic_loss" in log and "actor_loss" in log
    assert "observation.latent.global" in json.loads((checkpoint / "config.json").read_text())["input_features"]
    out = tmp_path / "eval"
    run_command(
        [
            BIN / "lerobot-eval",
            f"--policy.path={checkpoint}",
            "--env.type=murm",
            "--env.task=place_in_box",
            "--env.image_size=16",
            f"--env.cameras=[{','.join(CAMERAS)}]",
            "--eval.n_episodes=1",
            "--eval.batch_size=1",
            f"--output_dir={out}",
        ],
        cwd=tmp_path,
    )
    assert json.loads((out / "eval_info.json").read_text())["overall"]["n_episodes"] == 1


def strip_of_one_policy(policy: Path, out: Path, timeout: int) -> subprocess.CompletedProcess:
    """scripts/rollout_strip.py on one checkpoint, its exit and output returned, not checked."""
    args = [sys.executable, SCRIPTS / "rollout_strip.py", "--task", "place_in_box", "--policy", f"x={policy}"]
    return run(args + ["--out", out], timeout=timeout, env={**os.environ, **OFFLINE})


def test_rollout_strip_draws_each_checkpoint_on_the_same_episode(lerobot_trained, tmp_path):
    from PIL import Image

    checkpoint = lerobot_trained[1]
    out = tmp_path / "strip.png"
    printed = run_command(
        [
            sys.executable,
            SCRIPTS / "rollout_strip.py",
            "--task",
            "place_in_box",
            "--image-size",
            "16",
            "--steps",
            "0",
            "50",
            "99",
            "--policy",
            f"first=mine={checkpoint}",
            "--policy",
            f"second={checkpoint}",
            "--out",
            out,
        ],
        cwd=tmp_path,
    )
    assert "first=mine: " in printed and "second: " in printed  # a label may hold "="
    strip = np.asarray(Image.open(out).convert("RGB"))
    assert strip.shape == (2 * (256 + 18), 3 * 256, 3)
    first, second = strip[18:274], strip[274 + 18 :]
    np.testing.assert_array_equal(first, second)  # one policy, one episode seed: the same frames
    assert not np.array_equal(first[:, :256], first[:, 512:])  # the scene changes over the episode
    bad = strip_of_one_policy(tmp_path, out, timeout=120)
    assert bad.returncode != 0 and "expected LABEL=CHECKPOINT" in bad.stderr and "Traceback" not in bad.stderr
    (tmp_path / "not_a_policy").mkdir()
    (tmp_path / "not_a_policy" / "config.json").write_text('{"cameras": ["global"]}')
    bad = strip_of_one_policy(tmp_path / "not_a_policy", out, timeout=300)
    assert bad.returncode != 0 and "Traceback" not in bad.stderr
    assert len(bad.stderr.strip().splitlines()) == 1 and bad.stderr.startswith("rollout_strip: lerobot-eval failed on ")


def test_lerobot_train_under_accelerate_with_two_processes_saves_a_checkpoint(tiny_pipeline, latents, tmp_path):
    """Two data-parallel ranks on the CPU: accelerate's `--multi_gpu` starts them through torchrun
    (gloo when there is no GPU); `--cpu --num_processes 2` alone would start one process."""
    encoders = tiny_pipeline[1]
    log = run_command(
        [
            BIN / "accelerate",
            "launch",
            "--multi_gpu",
            "--num_processes",
            "2",
            "--num_machines",
            "1",
            "--mixed_precision",
            "no",
            "--dynamo_backend",
            "no",
            BIN / "lerobot-train",
            *TRAIN_ARGS,
            f"--policy.encoder_dir={encoders}",
            f"--dataset.root={latents}",
            "--steps=3",
            "--save_freq=3",
            "--log_freq=1",
            f"--output_dir={tmp_path / 'run'}",
        ],
        cwd=tmp_path,
    )
    assert "critic_loss" in log and "Effective batch size: 16 x 2 = 32" in log
    checkpoint = tmp_path / "run" / "checkpoints" / "000003"
    assert (checkpoint / "pretrained_model" / "model.safetensors").exists()
    state = json.loads((checkpoint / "training_state" / "training_step.json").read_text())
    assert state == {"step": 3, "num_processes": 2, "batch_size": 16}


def test_push_uploads_the_latent_dataset_with_its_card_and_pull_gets_it_back(latents, hub, tmp_path):
    card = push_dataset(latents, "tester/murm_latents")
    files = hub.files("tester/murm_latents")
    assert {"meta/info.json", "meta/murm_latents.json", "README.md"} <= set(files)
    readme = files["README.md"].decode()
    assert card in readme
    description = json.loads((latents / "meta/murm_latents.json").read_text())
    for fact in (
        "local/place_in_box",
        "`observation.latent.adjacent_goal`",
        "murm train-vqvae",
        description["cameras"]["global"]["encoder_fingerprint"],
        "murm encode --dataset",
    ):
        assert fact in readme, fact

    pulled = pull_dataset("tester/murm_latents", tmp_path / "pulled")
    original = LeRobotDataset(LATENT_REPO, root=latents)
    assert len(pulled) == len(original) == 600
    for i in (0, 250, 599):
        assert torch.equal(pulled[i][latent_key("global")], original[i][latent_key("global")])
    for a, b in zip(read_latent_caches(pulled, CAMERAS), read_latent_caches(original, CAMERAS), strict=True):
        np.testing.assert_array_equal(a.latents(), b.latents())
        np.testing.assert_array_equal(a.goal_latents(), b.goal_latents())


@pytest.mark.parametrize("codebook_size", [2, 32, 512, 513, 65536])
def test_packed_codes_unpack_to_the_same_indices_at_every_codebook_size(codebook_size):
    from lerobot_murm.vqvae.code_packing import pack_codes

    indices = np.random.default_rng(codebook_size).integers(0, codebook_size, (20, 144))
    indices[0] = codebook_size - 1  # every bit of the widest index set
    packed = pack_codes(indices, codebook_size)
    assert packed.dtype == np.int64 and (packed >= 0).all() and packed.shape[1] < 144
    np.testing.assert_array_equal(unpack_codes(packed, codebook_size, 144), indices)
    with pytest.raises(ValueError, match=r"must lie in \[0, "):
        pack_codes(indices + 1, codebook_size)
