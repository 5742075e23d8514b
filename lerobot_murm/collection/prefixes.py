"""Collections share their episodes: a smaller one is a larger one's start, and one with some
noisy demonstrations is made of the all-clean and the all-noisy one's episodes.

Episode i depends on the recipe's seed and i alone (`episodes.run_episode`), so the
250-episode collection of Table 7 is the first 250 episodes of the 1000-episode one, and
the 3000-episode one carries the 1000 on. Instead of simulating them again, a smaller
collection is cut from a finished larger one with LeRobot's `delete_episodes`, and a larger
one starts as a copy of a finished smaller one that `collect(resume=True)` carries on. Both
are built beside their final place and renamed, so a dataset folder is complete or absent.
A collection with a noisy fraction between 0 and 1 takes its episodes from the finished
all-clean and all-noisy collections beside it (`noise_donors`, donors.py).
"""

from __future__ import annotations

import logging
import shutil
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import replace
from pathlib import Path

import datasets
import numpy as np
from lerobot.datasets.dataset_tools import delete_episodes
from lerobot.datasets.lerobot_dataset import LeRobotDataset

from lerobot_murm.collection import dataset as murm_dataset
from lerobot_murm.collection.collect import CollectConfig
from lerobot_murm.collection.donors import Donor


def finished_siblings(config: CollectConfig) -> dict[int, Path]:
    """Finished collections of `config.recipe` beside `config.root`, by episode count."""
    found = {}
    for root in sorted(config.root.parent.iterdir()) if config.root.parent.is_dir() else []:
        summary = murm_dataset.read_summary(root) if root.is_dir() and root != config.root else None
        if (
            summary
            and summary["episodes"] >= summary["requested_episodes"]
            and murm_dataset.read_recipe(root) == config.recipe
        ):
            found[summary["episodes"]] = root
    return found


def cut_from_larger(config: CollectConfig) -> bool:
    """Make `config`'s collection from the first episodes of a finished larger one of its
    recipe; False if there is none."""
    larger = {n: root for n, root in finished_siblings(config).items() if n >= config.episodes}
    if not larger:
        return False
    source = larger[min(larger)]
    cutting = config.root.with_name(f"{config.root.name}.cutting")
    shutil.rmtree(cutting, ignore_errors=True)  # what a stopped cut left
    dataset = LeRobotDataset(config.repo_id, root=source, video_backend="pyav")
    total = dataset.meta.total_episodes
    if total > config.episodes:
        with _without_video_probe_warning():
            delete_episodes(dataset, list(range(config.episodes, total)), output_dir=cutting, repo_id=config.repo_id)
    else:
        shutil.copytree(source, cutting)
    successes = np.array(murm_dataset.read_summary(source)["episode_success"][: config.episodes], bool)
    murm_dataset.write_summary(cutting, config.recipe, successes, config.episodes)
    cutting.rename(config.root)
    return True


@contextmanager
def _without_video_probe_warning() -> Iterator[None]:
    """`delete_episodes` opens its result with LeRobot's default video backend, whose torchcodec
    probe logs a page-long warning where FFmpeg's libraries are missing; these datasets hold
    images, no videos, so the probe says nothing that matters here."""
    probe = logging.getLogger("lerobot.utils.import_utils")
    level = probe.level
    probe.setLevel(logging.ERROR)
    datasets.disable_progress_bars()  # one bar per parquet map; LeRobot's own bars stay
    try:
        yield
    finally:
        probe.setLevel(level)


def start_from_smaller(config: CollectConfig) -> CollectConfig:
    """If `config.root` does not exist yet, start it as a copy of the largest finished smaller
    collection of its recipe; the config to collect the rest with (resuming where one was copied)."""
    smaller = {n: root for n, root in finished_siblings(config).items() if n < config.episodes}
    if config.root.exists() or not smaller:
        return config
    copying = config.root.with_name(f"{config.root.name}.copying")
    shutil.rmtree(copying, ignore_errors=True)
    shutil.copytree(smaller[max(smaller)], copying)
    copying.rename(config.root)
    return replace(config, resume=True)


def noise_donors(config: CollectConfig) -> dict[bool, Donor]:
    """The largest finished all-clean (False) and all-noisy (True) collections of `config`'s
    recipe otherwise, beside it: where `config`'s episodes can be copied from. None for a
    collection that is all clean or all noisy itself (an empty dict)."""
    if not 0 < config.noisy_fraction < 1:
        return {}
    donors = {}
    for noisy in (False, True):
        found = finished_siblings(replace(config, noisy_fraction=float(noisy)))
        if found:
            donors[noisy] = Donor(found[max(found)], max(found))
    return donors
