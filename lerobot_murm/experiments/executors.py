"""Where `murm reproduce` runs its jobs: in this process, in N local processes, or on a Ray cluster.

The driver (`reproduce`) runs its stages in order (collection, merges, encoders, training
runs), each a list of independent jobs: a module-level function and its arguments.
`map` yields every job's result as soon as it finishes, so the driver writes a run's
result file at once and a stopped driver loses no finished run. Every job is idempotent
(it skips or resumes what is already on disk), which is what makes a retried job safe.
"""

from __future__ import annotations

import multiprocessing
import multiprocessing.connection
import os
import signal
import threading
from collections.abc import Callable, Iterator
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from multiprocessing import get_context
from typing import Any

import torch

from lerobot_murm.collection.collect import CollectionInterrupted
from lerobot_murm.training_loop import TrainingInterrupted

Job = tuple[Any, ...]
EXECUTORS = ("local", "ray")


class SerialExecutor:
    """The default: every job in this process, one after another."""

    shard_episodes: int | None = None  # collect each dataset in one piece (with its own worker processes)

    def map(self, fn: Callable, jobs: list[Job], cpus: int | None = None, gpus: float | None = None) -> Iterator:
        for job in jobs:
            yield job, fn(*job)

    def close(self) -> None:
        pass


def threads_per_job(jobs: int, cores: int | None = None) -> int:
    return max(1, (cores or os.cpu_count() or 1) // jobs)


_parent_gone = threading.Event()  # in a job process: the driver died
_job_running = threading.Event()  # in a job process: a job is under way
_stopping = threading.Event()  # in a job process: the grid is stopping; take no further job


def _start_job_process(threads: int, stop: Any) -> None:
    """A job process divides the cores, and stops with its driver: when the driver dies
    (kill -9) or asks its jobs to stop (`stop` set: Ctrl-C, or another job was stopped), a
    running job gets a SIGTERM (a training run saves its checkpoint at its next step), and
    the process then refuses the jobs already queued for it instead of starting them."""
    torch.set_num_threads(threads)
    sentinel = multiprocessing.parent_process().sentinel

    def exit_with_driver() -> None:
        multiprocessing.connection.wait([sentinel])
        _parent_gone.set()
        if not _job_running.is_set():
            os._exit(1)
        os.kill(os.getpid(), signal.SIGTERM)

    def stop_when_asked() -> None:
        stop.wait()
        _stopping.set()
        if _job_running.is_set():
            os.kill(os.getpid(), signal.SIGTERM)

    threading.Thread(target=exit_with_driver, daemon=True, name="exit-with-driver").start()
    threading.Thread(target=stop_when_asked, daemon=True, name="stop-when-asked").start()


def _run_job(fn: Callable, *job: Any) -> Any:
    if _stopping.is_set():
        raise TrainingInterrupted("not started: the grid was stopping")
    _job_running.set()
    try:
        return fn(*job)
    except (TrainingInterrupted, CollectionInterrupted, KeyboardInterrupt):
        _stopping.set()  # this job was stopped (Ctrl-C reaches the whole process group): so is the grid
        raise
    finally:
        _job_running.clear()
        if _parent_gone.is_set():
            os._exit(1)


class ProcessExecutor:
    """`--jobs N`: N jobs at once in N local processes with `cores // N` torch threads each.

    Two trainers that each use every core slow each other down far more than 2x (thread
    oversubscription); dividing the cores between them lets their throughputs add up.
    Each run keeps its `train.eval_envs` simulators per seed: the camera-masking draws
    depend on how evaluation episodes are batched, so resizing them would change results.
    A job with one core steps them in its own process (`Evaluator`: no core to spare for workers).
    A stop (Ctrl-C or SIGTERM, which reach every process of the group, or one job stopped or
    failed) stops every running job at its next step with its checkpoint, and starts no
    queued one; the driver returns once they have saved. The job processes are the driver's
    own children ("spawn"): under a forkserver, a SIGTERM to the group killed the forkserver,
    the pool took that for dead workers and let the driver exit while its jobs still saved.
    """

    shard_episodes: int | None = None

    def __init__(self, jobs: int, cores: int | None = None):
        if jobs < 1:
            raise ValueError(f"--jobs must be at least 1, got {jobs}")
        self.threads = threads_per_job(jobs, cores)
        context = get_context("spawn")
        self.stop = context.Event()  # set when the grid stops: every job process stops its job
        self.pool = ProcessPoolExecutor(
            jobs, mp_context=context, initializer=_start_job_process, initargs=(self.threads, self.stop)
        )

    def map(self, fn: Callable, jobs: list[Job], cpus: int | None = None, gpus: float | None = None) -> Iterator:
        futures = {self.pool.submit(_run_job, fn, *job): job for job in jobs}
        pending = set(futures)
        try:
            while pending:
                done, pending = wait(pending, return_when=FIRST_COMPLETED)
                for future in done:
                    yield futures[future], future.result()
        finally:
            if pending:  # stopped early (Ctrl-C, or a job stopped or failed): stop the rest, keep their checkpoints
                self.stop.set()
                for future in pending:
                    future.cancel()

    def close(self) -> None:
        self.pool.shutdown(cancel_futures=True)


def _call_with_threads(fn: Callable, threads: int, *job: Any) -> Any:
    """A Ray task: `fn(*job)` with as many torch threads as the task asked CPUs for."""
    torch.set_num_threads(threads)
    return fn(*job)


class RayExecutor:
    """`--executor ray [--address ADDR]`: every job a Ray task with its resource request.

    Ray retries a task whose worker or node died (`max_retries`) and one stopped by a
    SIGTERM (a preemption: the trainer saves its checkpoint first); the retry resumes from
    the checkpoint in the shared `work_dir`. Collections are split into shards of
    `shard_episodes` episodes, one task each. Each task locks what it writes there, and
    waits for a task that holds what it needs; how those locks behave on NFS: locking.py.
    """

    def __init__(
        self,
        address: str | None = None,
        cpus_per_task: int = 1,
        gpus_per_task: float = 0.0,
        shard_episodes: int = 100,
        retries: int = 3,
    ):
        try:
            import ray
        except ImportError:
            raise SystemExit("--executor ray needs Ray: pip install 'lerobot_policy_murm[ray]'") from None
        if cpus_per_task < 1 or gpus_per_task < 0 or shard_episodes < 1 or retries < 0:
            raise ValueError("cpus_per_task and shard_episodes must be >= 1, gpus_per_task and retries >= 0")
        self.ray = ray
        self.cpus, self.gpus, self.shard_episodes, self.retries = cpus_per_task, gpus_per_task, shard_episodes, retries
        ray.init(address=address)

    def map(self, fn: Callable, jobs: list[Job], cpus: int | None = None, gpus: float | None = None) -> Iterator:
        cpus = self.cpus if cpus is None else cpus
        task = self.ray.remote(_call_with_threads).options(
            name=fn.__name__,
            num_cpus=cpus,
            num_gpus=self.gpus if gpus is None else gpus,
            max_retries=self.retries,
            retry_exceptions=[TrainingInterrupted, CollectionInterrupted],
        )
        refs = {task.remote(fn, cpus, *job): job for job in jobs}
        pending = list(refs)
        try:
            while pending:
                done, pending = self.ray.wait(pending, num_returns=1)
                yield refs[done[0]], self.ray.get(done[0])
        finally:
            for ref in pending:
                self.ray.cancel(ref)

    def close(self) -> None:
        self.ray.shutdown()


def make_executor(
    kind: str = "local",
    jobs: int = 1,
    address: str | None = None,
    cpus_per_task: int = 1,
    gpus_per_task: float = 0.0,
    shard_episodes: int = 100,
):
    if kind not in EXECUTORS:
        raise ValueError(f"unknown executor {kind!r}; choose from {list(EXECUTORS)}")
    if kind == "ray":
        if jobs != 1:
            raise ValueError("--jobs is for the local executor; Ray runs as many tasks as the cluster has room for")
        return RayExecutor(address, cpus_per_task, gpus_per_task, shard_episodes)
    if address is not None:
        raise ValueError("--address is for --executor ray")
    return SerialExecutor() if jobs == 1 else ProcessExecutor(jobs)
