"""One collection split into episode ranges (shards) that run on different machines, then
merged with LeRobot's `aggregate_datasets`.

Episode i depends on the recipe's seed and i alone (`episodes.run_episode`), so a shard
collects episodes [start, stop) exactly as one long collection would, and the merged
dataset holds the same frames in the same order. Shards live beside the dataset in
`<root>.shards/`; the merge writes `<root>.merging/` and renames it to `<root>` once its
summary is written, so a dataset folder is either complete or absent. A task waits for
another that holds the folder it is to write (a retry whose first try's lock an NFS lease
still holds; locking.py).
"""

from __future__ import annotations

import json
import shutil
from dataclasses import replace
from pathlib import Path

from lerobot.datasets.aggregate import aggregate_datasets

from lerobot_murm.collection import dataset as murm_dataset
from lerobot_murm.collection.collect import CollectConfig, collect
from lerobot_murm.locking import exclusive


def is_complete(config: CollectConfig) -> bool:
    """`config.root` holds at least `config.episodes` episodes of `config.recipe`."""
    summary = config.root / murm_dataset.SUMMARY_FILE
    if not summary.exists():
        return False
    done = json.loads(summary.read_text())["episodes"] >= config.episodes
    return done and murm_dataset.read_recipe(config.root) == config.recipe


def shard_ranges(episodes: int, shard_episodes: int) -> list[range]:
    if shard_episodes < 1:
        raise ValueError(f"shard_episodes must be at least 1, got {shard_episodes}")
    return [range(start, min(start + shard_episodes, episodes)) for start in range(0, episodes, shard_episodes)]


def shard_config(config: CollectConfig, episodes: range) -> CollectConfig:
    root = config.root.with_name(f"{config.root.name}.shards") / f"{episodes.start:06d}-{episodes.stop:06d}"
    # one simulator in the task's own process: a shard task asks the cluster for one CPU
    return replace(
        config,
        root=root,
        first_episode=episodes.start,
        episodes=len(episodes),
        workers=1,
        resume=root.exists(),
        overwrite=False,
    )


def collect_shard(config: CollectConfig, episodes: range) -> Path:
    """Collect one shard (resuming a stopped one); a finished shard is left as it is."""
    shard = shard_config(config, episodes)
    with exclusive(shard.root, wait=True):
        if not is_complete(shard):
            collect(replace(shard, resume=shard.root.exists()))
    return shard.root


def merge_shards(config: CollectConfig, ranges: list[range]) -> dict:
    """The finished shards of `ranges` (in order) as one dataset at `config.root`; returns its summary."""
    shards = [shard_config(config, episodes) for episodes in ranges]
    unfinished = [s.root.name for s in shards if not is_complete(s)]
    if unfinished:
        raise ValueError(f"cannot merge {config.root}: shards {unfinished} are not finished")
    with exclusive(config.root, wait=True):
        merging = config.root.with_name(f"{config.root.name}.merging")
        shutil.rmtree(merging, ignore_errors=True)  # what a stopped merge left
        aggregate_datasets(
            [s.repo_id for s in shards], config.repo_id, roots=[s.root for s in shards], aggr_root=merging
        )
        successes = murm_dataset.episode_successes(config.repo_id, merging)
        summary = murm_dataset.write_summary(merging, config.recipe, successes, config.episodes)
        merging.rename(config.root)
        shutil.rmtree(shards[0].root.parent)
    return summary
