"""Hub push and pull through LeRobot's real code, against a local stand-in of the Hub's HTTP API.

There is no network here: `tests/helpers/fake_hub.py` answers the requests
huggingface_hub makes (repo creation, preupload/commit, tags, refs, tree, file
resolution), so everything above the HTTP boundary is the real code path.
"""

import os
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from lerobot_murm.collection import CollectConfig, collect
from lerobot_murm.expert import PAPER_NOISE_STD
from lerobot_murm.publishing import pull_dataset, push_dataset

sys.path.insert(0, str(Path(__file__).parent / "helpers"))
from commands import run

MURM = Path(sys.executable).parent / "murm"


@pytest.fixture(scope="module")
def collected(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("collected") / "ds"
    collect(
        CollectConfig(
            task="place_in_random_box",
            root=root,
            episodes=2,
            workers=1,
            cameras=("global", "top"),
            image_size=16,
            noise_std=PAPER_NOISE_STD,
        )
    )
    return root


def test_push_uploads_the_dataset_with_the_murm_card_and_pull_gets_it_back(collected, hub, tmp_path):
    card = push_dataset(collected, "tester/murm_random_box")
    files = hub.files("tester/murm_random_box")
    assert {"meta/info.json", "meta/stats.json", "meta/murm_collection.json", "README.md"} <= set(files)
    assert any(name.startswith("data/") and name.endswith(".parquet") for name in files)
    readme = files["README.md"].decode()
    assert card in readme  # our card is the description section of LeRobot's card
    for fact in ("place_in_random_box", "within 5 cm", "`observation.images.top_goal`", "k = 1.0", "100.0%"):
        assert fact in readme, fact
    assert "v3.0" in hub.repos["tester/murm_random_box"]["tags"]  # LeRobot's codebase-version tag

    pulled = pull_dataset("tester/murm_random_box", tmp_path / "pulled")
    original = pull_dataset("local/murm_place_in_random_box", collected)  # already local: no download
    assert pulled.meta.total_episodes == 2 and len(pulled) == len(original) == 200
    for i in (0, 123, 199):
        a, b = pulled[i], original[i]
        assert torch.equal(a["observation.images.top_goal"], b["observation.images.top_goal"])
        assert torch.equal(a["action"], b["action"])
    np.testing.assert_allclose(pulled.meta.stats["action"]["mean"], original.meta.stats["action"]["mean"])


def test_without_a_reachable_hub_push_and_pull_fail_with_a_clear_message(collected, tmp_path):
    env = {**os.environ, "HF_ENDPOINT": "http://127.0.0.1:9", "HF_TOKEN": "hf_test_token"}
    env.pop("HF_HUB_OFFLINE", None)
    for args in (
        ["push", "--root", str(collected), "--repo-id", "tester/x"],
        ["pull", "--repo-id", "tester/x", "--root", str(tmp_path / "x")],
    ):
        result = run([MURM, *args], env=env, timeout=180)
        assert result.returncode == 1, result.stderr[-2000:]
        last = result.stderr.strip().splitlines()[-1]
        assert last.startswith(f"murm {args[0]}: could not") and "unreachable or refused" in last, last
