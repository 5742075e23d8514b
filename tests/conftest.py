import atexit
import os
import shutil
import sys
import tempfile
from pathlib import Path

import pytest
import yaml

# LeRobotDataset reads parquet through `datasets`, which keeps an Arrow copy of every new
# dataset root in ~/.cache/huggingface/datasets. The suite makes dozens of temporary roots,
# so that cache grew by gigabytes per run; point it (for the subprocesses too) at a folder
# removed at exit. Set before anything imports `datasets`, which reads it once.
_DATASETS_CACHE = tempfile.mkdtemp(prefix="murm-tests-datasets-cache-")
os.environ["HF_DATASETS_CACHE"] = _DATASETS_CACHE
atexit.register(shutil.rmtree, _DATASETS_CACHE, ignore_errors=True)

# matplotlib's font list lives in ~/.cache/matplotlib, shared by every matplotlib on the
# machine and trusted while the fonts it names exist: one written by a matplotlib whose venv was
# being deleted listed only the system's DejaVu, and every plot of a fresh clone's tests then
# warned of its missing STIX fonts (three quiet-output tests failed). The suite builds its own.
_MATPLOTLIB_DIR = tempfile.mkdtemp(prefix="murm-tests-matplotlib-")
os.environ["MPLCONFIGDIR"] = _MATPLOTLIB_DIR
atexit.register(shutil.rmtree, _MATPLOTLIB_DIR, ignore_errors=True)

from lerobot_murm.env import MurmEnv  # noqa: E402

sys.path.insert(0, str(Path(__file__).parent / "helpers"))
from process_guard import no_process_outlives_its_test  # noqa: E402, F401  (an autouse fixture)


def pytest_configure(config):
    """The xdist workers share the cores: each test's torch, and its subprocesses' (they inherit
    OMP_NUM_THREADS), gets its share. With every process at all the cores' threads, OpenMP's
    spinning waits made a collection test beside a training one 5x slower (331 s, 66 s alone)
    and the suite 19.5 minutes on 2 cores. An OMP_NUM_THREADS of your own wins."""
    import torch

    from lerobot_murm.experiments.executors import threads_per_job

    worker = getattr(config, "workerinput", None)
    workers = worker["workercount"] if worker else config.getoption("numprocesses", 1)
    os.environ.setdefault("OMP_NUM_THREADS", str(threads_per_job(workers or 1)))
    torch.set_num_threads(int(os.environ["OMP_NUM_THREADS"]))


@pytest.fixture
def make_env():
    """Build MurmEnvs that are closed after the test."""
    envs: list[MurmEnv] = []

    def _make(**kwargs) -> MurmEnv:
        env = MurmEnv(**kwargs)
        envs.append(env)
        return env

    yield _make
    for env in envs:
        env.close()


@pytest.fixture
def hub(monkeypatch):
    """The local stand-in of the Hub's HTTP API (tests/helpers/fake_hub.py) takes all Hub traffic."""
    sys.path.insert(0, str(Path(__file__).parent / "helpers"))
    from fake_hub import FakeHub

    monkeypatch.setenv("HF_TOKEN", "hf_test_token")
    monkeypatch.delenv("HF_HUB_OFFLINE", raising=False)
    with FakeHub() as fake:
        fake.route_all_hub_traffic()
        yield fake


@pytest.fixture(scope="session")
def tiny_pipeline(tmp_path_factory):
    """A real but tiny pipeline: 6 place_in_box episodes with two 16x16 cameras, a small
    VQ-VAE per camera, and the latent-distance file the policy takes its epsilon from.
    Returns (dataset_root, encoder_dir); encoder_dir/<camera> are the checkpoints."""
    from lerobot_murm.collection import CollectConfig, collect
    from lerobot_murm.collection.dataset import episode_successes
    from lerobot_murm.expert import PAPER_NOISE_STD
    from lerobot_murm.vqvae import VQVAEConfig
    from lerobot_murm.vqvae.latent_cache import build_latent_cache
    from lerobot_murm.vqvae.latent_distance import distance_statistics, save_beside_encoder
    from lerobot_murm.vqvae.train import train_vqvae

    base = tmp_path_factory.mktemp("pipeline")
    root, encoders, cache = base / "place_in_box", base / "vqvae", base / "cache"
    # the paper's std, at which our expert succeeds in every episode: the tests of the later
    # stages need successful episodes, not the default recipe's 75 %
    collect(
        CollectConfig(
            task="place_in_box",
            root=root,
            episodes=6,
            workers=1,
            cameras=("global", "adjacent"),
            image_size=16,
            noise_std=PAPER_NOISE_STD,
        )
    )
    tiny = VQVAEConfig(steps=30, batch_size=32, hidden_channels=16, residual_channels=8, codebook_size=32)
    successes = episode_successes(TINY_REPO, root)
    for camera in ("global", "adjacent"):
        train_vqvae(TINY_REPO, root, camera, encoders / camera, tiny, device="cpu")
        stats = distance_statistics(build_latent_cache(TINY_REPO, root, encoders / camera, cache), successes)
        save_beside_encoder(stats, encoders / camera)
    return root, encoders


TINY_REPO = "local/place_in_box"


@pytest.fixture
def tiny_train_yaml(tiny_pipeline, tmp_path):
    """Writes a `murm train` config for the tiny pipeline (concat on both cameras, a few steps,
    one evaluation episode, run and cache in tmp_path) with any field overridden; returns its path."""
    root, encoders = tiny_pipeline

    def write(**overrides) -> Path:
        policy = {"type": "murm", "method": "concat", "cameras": ["global", "adjacent"], "encoder_dir": str(encoders)}
        config = {
            "dataset": str(root),
            "task": "place_in_box",
            "output_dir": str(tmp_path / "run"),
            "cache_dir": str(tmp_path / "cache"),
            "steps": 4,
            "batch_size": 16,
            "log_every": 1,
            "eval_every": 100,
            "eval_episodes": 1,
            "final_eval_episodes": 1,
            "eval_envs": 1,
            "policy": policy,
        } | overrides
        path = tmp_path / "train.yaml"
        path.write_text(yaml.safe_dump(config))
        return path

    return write
