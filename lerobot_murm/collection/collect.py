"""`murm collect`: run the noisy expert in parallel workers and write a LeRobotDataset.

Workers simulate (one simulator per process) and encode their episode's PNGs; the
main process appends episodes in index order, so the dataset does not depend on the
number of workers. Ctrl-C,
SIGTERM or a dead worker stop the run cleanly: the episodes already written are
finalized into a valid dataset, the half-done ones are dropped, and `resume=True`
carries on to the requested count.
"""

from __future__ import annotations

import os
import shutil
import signal
import time
from collections.abc import Callable, Iterator
from concurrent.futures import Future, ProcessPoolExecutor
from contextlib import contextmanager
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass
from multiprocessing import get_context
from pathlib import Path

import datasets
import numpy as np
from lerobot.datasets.lerobot_dataset import LeRobotDataset
from tqdm import tqdm

from lerobot_murm.collection import dataset as murm_dataset
from lerobot_murm.collection.dataset import StagedEpisode
from lerobot_murm.collection.episodes import EpisodeRecipe, run_episode
from lerobot_murm.env import CAMERA_NAMES, TASK_NAMES, MurmEnv
from lerobot_murm.env.murm_env import TASK_DESCRIPTIONS
from lerobot_murm.env.cameras import validate_camera_names
from lerobot_murm.expert import default_noise_std


@dataclass
class CollectConfig:
    task: str
    root: Path
    episodes: int = 1000
    workers: int = 2
    repo_id: str | None = None  # default: local/murm_<task>
    cameras: tuple[str, ...] = CAMERA_NAMES
    image_size: int = 48
    seed: int = 0
    noise_k: float = 1.0
    noisy_fraction: float = 1.0
    noise_std: float | None = None  # None: the task's calibrated std (about 75 % success)
    resume: bool = False
    overwrite: bool = False
    first_episode: int = 0  # a shard of a larger collection holds episodes first_episode, first_episode + 1, ...

    def __post_init__(self) -> None:
        if self.task not in TASK_NAMES:
            raise ValueError(f"unknown task {self.task!r}; valid tasks: {list(TASK_NAMES)}")
        if self.first_episode < 0:
            raise ValueError(f"first_episode must be >= 0, got {self.first_episode}")
        if self.episodes < 1:
            raise ValueError(f"episodes must be at least 1, got {self.episodes}")
        if self.workers < 1:
            raise ValueError(f"workers must be at least 1, got {self.workers}")
        if self.noise_k < 0:
            raise ValueError(f"noise_k must be >= 0, got {self.noise_k}")
        if self.noise_std is None:
            self.noise_std = default_noise_std(self.task)
        if not np.isfinite(self.noise_std) or self.noise_std < 0:
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
            noise_k=self.noise_k,
            noisy_fraction=self.noisy_fraction,
            noise_std=self.noise_std,
        )


class CollectionInterrupted(RuntimeError):
    """The run stopped early; the dataset holds the episodes finished before that."""


def collect(config: CollectConfig) -> dict:
    """Collect `config.episodes` episodes into `config.root`; returns the collection summary."""
    dataset = _open_dataset(config)
    done = dataset.meta.total_episodes
    description = TASK_DESCRIPTIONS[config.task]

    datasets.disable_progress_bars()  # one bar per episode write would drown ours
    stop_reason = None
    start = time.perf_counter()
    progress = tqdm(total=config.episodes, initial=done, desc=f"collect {config.task}", unit="ep")
    successes = 0
    with _deferred_stop_signals() as stop_requested:
        try:
            for written, episode in enumerate(_episodes(config, range(config.first_episode + done, config.first_episode + config.episodes)), start=1):
                murm_dataset.save_staged_episode(dataset, episode, description)  # never cut in half
                successes += episode.succeeded
                progress.set_postfix(
                    ep_per_s=f"{written / (time.perf_counter() - start):.2f}", success=f"{successes / written:.0%}"
                )
                progress.update(1)
                if stop_requested():
                    stop_reason = "interrupted"
                    break
        except BrokenProcessPool:
            stop_reason = "a worker process died"
        finally:
            progress.close()
            dataset.finalize()
            shutil.rmtree(murm_dataset.staging_root(config.root), ignore_errors=True)  # unsaved work

    summary = murm_dataset.write_summary(
        config.root,
        config.recipe,
        murm_dataset.episode_successes(config.repo_id, config.root),
        config.episodes,
    )
    if stop_reason:
        raise CollectionInterrupted(
            f"{stop_reason}: {summary['episodes']} of {config.episodes} episodes are saved in {config.root}; "
            "run again with --resume to carry on"
        )
    return summary


def _open_dataset(config: CollectConfig) -> LeRobotDataset:
    root = config.root
    if root.exists() and config.overwrite:
        shutil.rmtree(root)
    if root.exists():
        if not config.resume:
            raise FileExistsError(
                f"{root} already exists; pass --resume to carry on collecting or --overwrite to replace it"
            )
        stored = murm_dataset.read_recipe(root)
        if stored is None:
            raise ValueError(f"{root} is not a murm collection (no {murm_dataset.SUMMARY_FILE})")
        if stored != config.recipe:
            raise ValueError(f"cannot resume: {root} was collected with {stored}, not {config.recipe}")
        return LeRobotDataset.resume(config.repo_id, root=root, video_backend="pyav")
    _check_writable(root)
    dataset = murm_dataset.create_dataset(config.repo_id, root, config.recipe)
    murm_dataset.write_summary(root, config.recipe, successes=np.zeros(0, bool), requested=config.episodes)
    return dataset


def _check_writable(root: Path) -> None:
    parent = root.parent
    while not parent.exists():
        parent = parent.parent
    if not os.access(parent, os.W_OK):
        raise PermissionError(f"cannot create {root}: {parent} is not writable")


def simulate_and_stage(recipe: EpisodeRecipe, index: int, dataset_root: Path) -> StagedEpisode:
    """A worker's job: one episode, its images encoded to PNG files."""
    return murm_dataset.stage_episode(run_episode(recipe, index), dataset_root)


def _episodes(config: CollectConfig, indices: range) -> Iterator[StagedEpisode]:
    """Staged episodes in index order, made in `config.workers` processes (in this one if 1)."""
    recipe = config.recipe
    shutil.rmtree(murm_dataset.staging_root(config.root), ignore_errors=True)
    if config.workers == 1:
        for index in indices:
            yield simulate_and_stage(recipe, index, config.root)
        return
    context = get_context("forkserver")
    with ProcessPoolExecutor(config.workers, mp_context=context, initializer=_ignore_sigint) as pool:
        pending: dict[int, Future] = {}
        upcoming = iter(indices)
        try:
            for index in indices:
                while len(pending) < 2 * config.workers:  # a bounded window keeps memory flat
                    next_index = next(upcoming, None)
                    if next_index is None:
                        break
                    pending[next_index] = pool.submit(simulate_and_stage, recipe, next_index, config.root)
                yield pending.pop(index).result()
        finally:
            for future in pending.values():
                future.cancel()


def _ignore_sigint() -> None:
    """Workers leave Ctrl-C to the main process, which stops them and finalizes the dataset."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)


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
