"""Collections share their episodes: a smaller one cut from a larger one, a larger one carrying
a smaller one on, and a partly noisy one copied from the all-clean and all-noisy ones hold
exactly the frames a direct collection would."""

import importlib
import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch
from lerobot.datasets.lerobot_dataset import LeRobotDataset

from lerobot_murm.collection import CollectConfig, collect
from lerobot_murm.collection.dataset import SUMMARY_FILE, episode_successes
from lerobot_murm.collection.donors import Donor
from lerobot_murm.collection.prefixes import cut_from_larger, noise_donors, start_from_smaller
from lerobot_murm.collection.shards import is_complete
from lerobot_murm.experiments.executors import SerialExecutor
from lerobot_murm.experiments.reproduce import build_datasets

SMALL = {"task": "pick_up", "cameras": ("global",), "image_size": 16, "workers": 1}
REPO = "local/murm_pick_up"


def config(root: Path, episodes: int, **kwargs) -> CollectConfig:
    return CollectConfig(root=root, episodes=episodes, **SMALL, **kwargs)


def assert_same_dataset(a: Path, b: Path) -> None:
    first, second = (LeRobotDataset(REPO, root=root, video_backend="pyav") for root in (a, b))
    assert first.meta.total_episodes == second.meta.total_episodes and len(first) == len(second)
    columns = [c.hf_dataset.with_format("numpy")[:] for c in (first, second)]
    for key in ("action", "observation.state", "next.success", "episode_index", "frame_index"):
        np.testing.assert_array_equal(columns[0][key], columns[1][key], err_msg=key)
    for i in (0, len(first) // 2, len(first) - 1):
        for key in ("observation.images.global", "observation.images.global_goal"):
            assert torch.equal(first[i][key], second[i][key]), (i, key)
    summaries = [json.loads((root / SUMMARY_FILE).read_text()) for root in (a, b)]
    for key in ("recipe", "episodes", "requested_episodes", "episode_success"):
        assert summaries[0][key] == summaries[1][key], key
    assert list(episode_successes(REPO, a)) == summaries[0]["episode_success"]


def test_a_smaller_collection_is_the_start_of_a_larger_one(tmp_path):
    datasets = tmp_path / "datasets"
    collect(config(datasets / "four", 4))
    collect(config(tmp_path / "direct" / "two", 2))

    two = config(datasets / "two", 2)
    (datasets / "two.cutting" / "data").mkdir(parents=True)  # what a cut killed midway left
    (datasets / "two.cutting" / "data" / "torn.parquet").write_bytes(b"PAR1 torn")
    assert cut_from_larger(two) and is_complete(two)
    assert_same_dataset(two.root, tmp_path / "direct" / "two")
    assert not list(datasets.glob("*.cutting"))
    other_recipe = config(datasets / "two-clean", 2, noisy_fraction=0.0)
    assert not cut_from_larger(other_recipe) and not other_recipe.root.exists()


def test_a_larger_collection_carries_a_finished_smaller_one_on(tmp_path):
    datasets = tmp_path / "datasets"
    collect(config(datasets / "two", 2))
    collect(config(tmp_path / "direct" / "four", 4))

    (datasets / "four.copying" / "meta").mkdir(parents=True)  # what a copy killed midway left
    four = start_from_smaller(config(datasets / "four", 4))
    assert four.resume and four.root.exists() and not is_complete(four)
    collect(four)
    assert_same_dataset(four.root, tmp_path / "direct" / "four")
    assert is_complete(config(datasets / "two", 2))  # the smaller one is left as it was
    assert not (datasets / "four.copying").exists()


def test_a_grid_simulates_only_the_largest_collection_of_a_recipe(tmp_path, monkeypatch):
    import lerobot_murm.experiments.artifacts as artifacts

    simulated = []
    real_collect = artifacts.collect
    monkeypatch.setattr(
        artifacts, "collect", lambda c, donors: simulated.append((c.root.name, c.resume)) or real_collect(c, donors)
    )
    datasets = tmp_path / "datasets"
    collect(config(datasets / "two", 2))  # finished before: the four-episode collection carries it on
    wanted = [config(datasets / name, n) for name, n in (("one", 1), ("four", 4), ("three", 3))]
    build_datasets(SerialExecutor(), wanted, workers=1)
    assert simulated == [("four", True)]
    assert all(is_complete(c) for c in wanted)
    collect(config(tmp_path / "direct" / "three", 3))
    assert_same_dataset(datasets / "three", tmp_path / "direct" / "three")
    build_datasets(SerialExecutor(), [replace(c, resume=False) for c in wanted], workers=1)
    assert simulated == [("four", True)]  # nothing left to do


def test_a_partly_noisy_collection_is_copied_from_the_clean_and_the_noisy_ones(tmp_path, monkeypatch):
    # the package's `collect` is the function
    collect_module = importlib.import_module("lerobot_murm.collection.collect")

    datasets = tmp_path / "datasets"
    half = config(datasets / "half", 7, noisy_fraction=0.5)
    flags = [half.recipe.episode_start(i)[1] for i in range(7)]
    assert any(flags[:6]) and not all(flags[:6]) and flags[6], flags  # both kinds, and a noisy last one
    collect(config(datasets / "clean", 7, noisy_fraction=0.0))
    collect(config(datasets / "noisy", 6))  # lacks episode 6: that one is simulated
    collect(config(tmp_path / "direct" / "half", 7, noisy_fraction=0.5))
    assert noise_donors(config(datasets / "clean", 7, noisy_fraction=0.0)) == {}

    simulated = []
    real_run = collect_module.run_episode
    monkeypatch.setattr(collect_module, "run_episode", lambda recipe, i: simulated.append(i) or real_run(recipe, i))
    donors = noise_donors(half)
    assert donors == {False: Donor(datasets / "clean", 7), True: Donor(datasets / "noisy", 6)}
    collect(half, donors=donors)
    assert simulated == [6]
    assert_same_dataset(half.root, tmp_path / "direct" / "half")


def test_a_grid_collects_the_clean_and_noisy_donors_before_the_partly_noisy_collection(tmp_path, monkeypatch):
    import lerobot_murm.experiments.artifacts as artifacts

    built = []
    real_collect = artifacts.collect
    monkeypatch.setattr(
        artifacts, "collect", lambda c, donors: built.append((c.root.name, sorted(donors))) or real_collect(c, donors)
    )
    datasets = tmp_path / "datasets"
    wanted = [
        config(datasets / name, 5, noisy_fraction=f) for name, f in (("quarter", 0.25), ("clean", 0.0), ("noisy", 1.0))
    ]
    build_datasets(SerialExecutor(), wanted, workers=1)
    assert built == [("clean", []), ("noisy", []), ("quarter", [False, True])]
    collect(config(tmp_path / "direct" / "quarter", 5, noisy_fraction=0.25))
    assert_same_dataset(datasets / "quarter", tmp_path / "direct" / "quarter")
