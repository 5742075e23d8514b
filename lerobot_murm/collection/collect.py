"""`murm collect`: run the noisy expert in parallel workers and write a LeRobotDataset.

Workers simulate (one simulator per process) and encode their episode's PNGs; the
main process appends episodes in index order, so the dataset does not depend on the
number of workers. Ctrl-C,
SIGTERM or a dead worker stop the run cleanly: the episodes already written are
finalized into a valid dataset, the half-done ones are dropped, and `resume=True`
carries on to the requested count.

A hard stop (kill -9, power loss, a full disk) loses at most the episodes since the last
flush: every `flush_every` episodes (10 by default, about 10 s with two workers) the
files are closed and a snapshot is recorded; `resume=True` first restores the dataset to
that snapshot (durability.py). Flushes fall on multiples of `flush_every`, so a resumed
collection writes the same files as an unbroken one. Workers exit when the main process dies.
"""

from __future__ import annotations

import math
import multiprocessing
import multiprocessing.connection
import os
import shutil
import signal
import threading
import time
from collections.abc import Callable, Iterator
from concurrent.futures import Future, ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from contextlib import contextmanager
from dataclasses import dataclass
from multiprocessing import get_context
from pathlib import Path

import datasets
import numpy as np
from lerobot.datasets.lerobot_dataset import LeRobotDataset

from lerobot_murm.checks import check_writable
from lerobot_murm.collection import dataset as murm_dataset
from lerobot_murm.collection.dataset import StagedEpisode
from lerobot_murm.collection.donors import Donor, stage_from_donor
from lerobot_murm.collection.durability import restore
from lerobot_murm.collection.episodes import EpisodeRecipe, run_episode
from lerobot_murm.env import CAMERA_NAMES, TASK_NAMES, MurmEnv
from lerobot_murm.env.cameras import validate_camera_names
from lerobot_murm.env.murm_env import TASK_DESCRIPTIONS
from lerobot_murm.expert import default_noise_std
from lerobot_murm.locking import exclusive
from lerobot_murm.progress import progress


@dataclass
class CollectConfig:
    """`murm collect`'s settings; its options are these fields (config_args.py), the comments their help."""

    task: str  # place_in_box, place_in_random_box or pick_up
    root: Path  # dataset folder (created; never overwritten silently)
    episodes: int = 1000  # episodes to have in the end
    workers: int = 2  # simulator processes
    repo_id: str | None = None  # Hub id, e.g. user/murm_place_in_box (default: local/murm_TASK)
    cameras: tuple[str, ...] = CAMERA_NAMES  # the cameras recorded
    image_size: int = 48  # pixels of each square camera image
    seed: int = 0  # base seed: episode i depends on it and i alone
    noisy_fraction: float = 1.0  # share of noisy episodes
    # expert noise std, a = clip(a* + N(0, std), -1, 1), the noise's one knob (paper 4.1's
    # k N(0, 0.1) is std 0.1 k); default: the task's calibrated std, about 75 % expert success
    # as in the paper (noisy_fraction 0: the clean expert)
    noise_std: float | None = None
    resume: bool = False  # carry on an interrupted or shorter collection
    overwrite: bool = False  # delete an existing murm dataset at root first
    first_episode: int = 0  # a shard of a larger collection holds episodes first_episode, first_episode + 1, ...
    flush_every: int = 10  # episodes between flushes to disk: the most a hard stop loses

    def __post_init__(self) -> None:
        if self.task not in TASK_NAMES:
            raise ValueError(f"unknown task {self.task!r}; valid tasks: {list(TASK_NAMES)}")
        if self.first_episode < 0:
            raise ValueError(f"first_episode must be >= 0, got {self.first_episode}")
        if self.episodes < 1:
            raise ValueError(f"episodes must be at least 1, got {self.episodes}")
        if self.workers < 1:
            raise ValueError(f"workers must be at least 1, got {self.workers}")
        if self.flush_every < 1:
            raise ValueError(f"flush_every must be at least 1, got {self.flush_every}")
        if self.seed < 0:
            raise ValueError(f"seed must be >= 0, got {self.seed}")
        if self.noise_std is None:
            self.noise_std = default_noise_std(self.task)
        if not (math.isfinite(self.noise_std) and self.noise_std >= 0):
            raise ValueError(f"noise_std must be a finite number >= 0, got {self.noise_std}")
        if not 0.0 <= self.noisy_fraction <= 1.0:
            raise ValueError(f"noisy_fraction must be in [0, 1], got {self.noisy_fraction}")
        if self.resume and self.overwrite:
            raise ValueError("choose one of resume and overwrite")
        self.cameras = validate_camera_names(self.cameras)
        MurmEnv.validate_image_size(self.image_size)
        self.root = Path(self.root)
        self.repo_id = self.repo_id or f"local/murm_{self.task}"

    @property
    def recipe(self) -> EpisodeRecipe:
        return EpisodeRecipe(
            task=self.task,
            cameras=tuple(self.cameras),
            image_size=self.image_size,
            base_seed=self.seed,
            noisy_fraction=self.noisy_fraction,
            noise_std=self.noise_std,
        )


class CollectionInterrupted(RuntimeError):
    """The run stopped early; the dataset holds the episodes finished before that."""


def collect(config: CollectConfig, donors: dict[bool, Donor] | None = None) -> dict:
    """Collect `config.episodes` episodes into `config.root`; returns the collection summary.
    `donors` (noisy flag -> finished collection, `prefixes.noise_donors`): episodes of that
    flag which the donor holds are copied from it instead of simulated (donors.py). One
    writer per dataset folder (locking.py): two collections of one folder corrupted it."""
    check_writable(config.root)
    with exclusive(config.root):
        return _collect(config, donors or {})


def _collect(config: CollectConfig, donors: dict[bool, Donor]) -> dict:
    dataset = _open_dataset(config)
    summary = murm_dataset.read_summary(config.root)
    if "episode_success" in summary:
        successes = list(summary["episode_success"])
    else:  # a collection from before flushing
        successes = list(murm_dataset.episode_successes(config.repo_id, config.root))
    done = len(successes)
    description = TASK_DESCRIPTIONS[config.task]

    datasets.disable_progress_bars()  # one bar per episode write would drown ours
    stop_reason, write_error = None, None
    start = time.perf_counter()
    bar = progress(total=config.episodes, initial=done, desc=f"collect {config.task}", unit="ep")
    with _deferred_stop_signals() as stop_requested:
        try:
            indices = range(config.first_episode + done, config.first_episode + config.episodes)
            for written, episode in enumerate(_episodes(config, indices, donors), start=1):
                murm_dataset.save_staged_episode(dataset, episode, description)  # never cut in half
                successes.append(episode.succeeded)
                bar.set_postfix(
                    refresh=False,
                    ep_per_s=f"{written / (time.perf_counter() - start):.2f}",
                    success=f"{np.mean(successes[done:]):.0%}",
                )
                bar.update(1)
                if stop_requested():
                    stop_reason = "interrupted"
                    break
                if len(successes) % config.flush_every == 0 and len(successes) < config.episodes:
                    dataset = _flush(dataset, config, successes)
        except BrokenProcessPool:
            stop_reason = "a worker process died"
        except OSError as error:  # a full disk: what was flushed stays, --resume repairs the rest
            write_error = error
        finally:
            bar.close()
            shutil.rmtree(murm_dataset.staging_root(config.root), ignore_errors=True)  # unsaved work
    if write_error is not None:
        saved = murm_dataset.read_summary(config.root)["episodes"]
        raise CollectionInterrupted(
            f"cannot write to {config.root} ({write_error.strerror or write_error}): {saved} of {config.episodes} "
            "episodes are safely saved; make room, then run again with --resume to carry on"
        ) from write_error
    dataset.finalize()
    summary = murm_dataset.write_summary(config.root, config.recipe, np.array(successes, bool), config.episodes)
    if stop_reason:
        raise CollectionInterrupted(
            f"{stop_reason}: {summary['episodes']} of {config.episodes} episodes are saved in {config.root}; "
            "run again with --resume to carry on"
        )
    return summary


def _flush(dataset: LeRobotDataset, config: CollectConfig, successes: list[bool]) -> LeRobotDataset:
    """Close the files (footers written), record them, and go on in new files."""
    dataset.finalize()
    murm_dataset.write_summary(config.root, config.recipe, np.array(successes, bool), config.episodes)
    resumed = LeRobotDataset.resume(config.repo_id, root=config.root, video_backend="pyav")
    datasets.disable_progress_bars()  # LeRobot turns them back on
    return resumed


def _open_dataset(config: CollectConfig) -> LeRobotDataset:
    root = config.root
    if root.exists() and config.overwrite:
        _remove_collection(root)
    if root.exists() and not any(root.iterdir()):
        root.rmdir()  # an empty folder is as good as none
    if root.exists():
        if not config.resume:
            raise FileExistsError(
                f"{root} already exists; pass --resume to carry on collecting or --overwrite to replace it"
            )
        summary = murm_dataset.read_summary(root)
        if summary is None:
            raise ValueError(f"{root} is not a murm collection (no {murm_dataset.SUMMARY_FILE})")
        stored = murm_dataset.read_recipe(root)
        if stored != config.recipe:
            raise ValueError(f"cannot resume: {root} was collected with {stored}, not {config.recipe}")
        removed = restore(root, summary["flushed"], murm_dataset.SUMMARY_FILE) if "flushed" in summary else 0
        if removed:
            print(f"{root}: removed {removed} files written after the last flush ({summary['episodes']} episodes kept)")
        return LeRobotDataset.resume(config.repo_id, root=root, video_backend="pyav")
    # made beside its final place and renamed, so `root` never exists without its summary
    building = root.with_name(root.name + ".creating")
    shutil.rmtree(building, ignore_errors=True)
    murm_dataset.create_dataset(config.repo_id, building, config.recipe).finalize()
    murm_dataset.write_summary(building, config.recipe, successes=np.zeros(0, bool), requested=config.episodes)
    building.rename(root)
    return LeRobotDataset.resume(config.repo_id, root=root, video_backend="pyav")


def _remove_collection(root: Path) -> None:
    """`--overwrite`: delete a folder only if murm made it (it has the collection summary)."""
    if not root.is_dir() or not (root / murm_dataset.SUMMARY_FILE).is_file():
        if root.is_dir() and not any(root.iterdir()):
            return
        raise FileExistsError(
            f"--overwrite refused: {root} is not a murm collection (no {murm_dataset.SUMMARY_FILE}); "
            "delete it yourself if you mean it"
        )
    shutil.rmtree(root)


def make_staged_episode(
    recipe: EpisodeRecipe, index: int, dataset_root: Path, donors: dict[bool, Donor]
) -> StagedEpisode:
    """A worker's job: one episode with its images as PNG files, copied from the donor of its
    noise flag where that holds it, else simulated and encoded."""
    donor = donors.get(recipe.episode_start(index)[1]) if donors else None
    if donor is not None and index < donor.episodes:
        return stage_from_donor(donor.root, index, dataset_root, recipe.cameras)
    return murm_dataset.stage_episode(run_episode(recipe, index), dataset_root)


def _episodes(config: CollectConfig, indices: range, donors: dict[bool, Donor]) -> Iterator[StagedEpisode]:
    """Staged episodes in index order, made in `config.workers` processes (in this one if 1)."""
    recipe = config.recipe
    shutil.rmtree(murm_dataset.staging_root(config.root), ignore_errors=True)
    if config.workers == 1:
        for index in indices:
            yield make_staged_episode(recipe, index, config.root, donors)
        return
    context = get_context("forkserver")
    with ProcessPoolExecutor(config.workers, mp_context=context, initializer=_start_worker) as pool:
        pending: dict[int, Future] = {}
        upcoming = iter(indices)
        try:
            for index in indices:
                while len(pending) < 2 * config.workers:  # a bounded window keeps memory flat
                    next_index = next(upcoming, None)
                    if next_index is None:
                        break
                    pending[next_index] = pool.submit(make_staged_episode, recipe, next_index, config.root, donors)
                yield pending.pop(index).result()
        finally:
            for future in pending.values():
                future.cancel()


def _start_worker() -> None:
    """Workers leave Ctrl-C to the main process, which stops them and finalizes the dataset,
    and exit when it dies (kill -9): the connection to it, their parent's sentinel, closes.
    The forkserver and resource tracker then exit too (the workers held their pipes open)."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    sentinel = multiprocessing.parent_process().sentinel

    def exit_with_parent() -> None:
        multiprocessing.connection.wait([sentinel])
        os._exit(1)

    threading.Thread(target=exit_with_parent, daemon=True, name="exit-with-parent").start()


@contextmanager
def _deferred_stop_signals() -> Iterator[Callable[[], bool]]:
    """Turn Ctrl-C and SIGTERM into a request checked between episodes.

    Writing an episode must not be cut in half (LeRobot's writer would be left
    inconsistent), so the signals only set a flag; a second Ctrl-C still aborts.
    """
    requested = []

    def handler(signum, frame):
        if requested:
            raise KeyboardInterrupt
        requested.append(signum)

    previous = {sig: signal.signal(sig, handler) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield lambda: bool(requested)
    finally:
        for sig, old in previous.items():
            signal.signal(sig, old)
