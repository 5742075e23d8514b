"""`murm reproduce` on other executors: `--jobs N` local processes, and a real local Ray
cluster (a head and a worker node started here, several worker processes) that must give
the local executor's results, with the collection in shards and a worker killed mid-run."""

import json
import os
import signal
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import pytest
from test_reproduce import MURM, REPO, TINY

from lerobot_murm.experiments.executors import ProcessExecutor, SerialExecutor, make_executor

RAY = Path(sys.executable).parent / "ray"
TIMING_FIELDS = ("wall_s", "train_steps_per_s", "sittings")  # sittings: when each began (a killed run has two)


def _threads() -> int:
    import torch

    return torch.get_num_threads()


def test_jobs_divide_the_cores_between_their_processes():
    executor = ProcessExecutor(jobs=2, cores=4)
    try:
        threads = [result for _, result in executor.map(_threads, [(), ()])]
    finally:
        executor.close()
    assert threads == [2, 2]  # both jobs ran, each with 4 // 2 threads
    assert list(SerialExecutor().map(divmod, [(7, 2), (9, 4)])) == [((7, 2), (3, 1)), ((9, 4), (2, 1))]


@pytest.mark.parametrize(
    "flags, message",
    [
        (["--jobs=0"], "--jobs must be at least 1"),
        (["--executor=ray", "--jobs=2"], "--jobs is for the local executor"),
        (["--address=127.0.0.1:1"], "--address is for --executor ray"),
    ],
)
def test_bad_executor_flags_stop_with_one_line(flags, message, capsys):
    from lerobot_murm.cli import main

    with pytest.raises(SystemExit) as stop:
        main(["reproduce", "--config", str(REPO / "configs/reproduce/smoke.yaml"), *flags])
    lines = [line for line in capsys.readouterr().err.splitlines() if line.startswith("murm reproduce:")]
    assert stop.value.code == 2 and len(lines) == 1 and message in lines[0], lines
    assert make_executor("local").__class__ is SerialExecutor


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture
def ray_cluster():
    """A head node (1 CPU) and a worker node (2 CPUs) on this machine, each `ray start` in its
    own process group so that teardown stops exactly this cluster's processes."""
    temp = tempfile.mkdtemp(prefix="ray", dir="/tmp")  # short: Ray's socket paths must stay under 107 characters
    env = {**os.environ, "PYTHONPATH": str(REPO), "HF_HUB_OFFLINE": "1", "RAY_USAGE_STATS_ENABLED": "0"}
    address = f"127.0.0.1:{_free_port()}"
    nodes = []

    def start(*args: str) -> None:
        # a raylet must register within Ray's fixed 30 s; a busy machine can miss that: try again
        for _ in range(3):
            node = subprocess.Popen(
                [str(RAY), "start", *args, f"--dashboard-agent-listen-port={_free_port()}"],
                env=env,
                start_new_session=True,
                stdout=subprocess.PIPE,
                stderr=subprocess.STDOUT,
                text=True,
            )
            nodes.append(node)
            out = node.communicate(timeout=180)[0]
            if node.returncode == 0:
                return
            _stop(node)
        raise AssertionError(f"ray start {' '.join(args)} failed 3 times:\n{out[-3000:]}")

    try:
        start(
            "--head",
            f"--port={address.split(':')[1]}",
            "--num-cpus=1",
            f"--temp-dir={temp}",
            "--include-dashboard=false",
        )
        start(f"--address={address}", "--num-cpus=2")
        yield address
    finally:
        for node in nodes:
            _stop(node)
        subprocess.run(["rm", "-rf", temp])


def _stop(node: subprocess.Popen) -> None:
    """SIGTERM, then SIGKILL, to the process group of one `ray start`: that node's processes only."""
    for sig in (signal.SIGTERM, signal.SIGKILL):
        try:
            os.killpg(node.pid, sig)
        except ProcessLookupError:
            return
        time.sleep(3 if sig == signal.SIGTERM else 0)


def _task_processes(name: str) -> list[int]:
    """Ray worker processes running a task named `name` (not the simulator processes they fork)."""
    pids = []
    for proc in Path("/proc").iterdir():
        try:
            title = (proc / "cmdline").read_bytes().split(b"\0")[0].decode()
            parent = Path(f"/proc/{(proc / 'stat').read_text().rsplit(')', 1)[1].split()[1]}/cmdline").read_bytes()
        except (OSError, ValueError, IndexError):
            continue
        if title.startswith(f"ray::{name}") and not parent.startswith(b"ray::"):
            pids.append(int(proc.name))
    return pids


def _without_timings(result: dict) -> dict:
    """A run's result less its wall times (the evaluations' `seconds` included) and sittings."""

    def strip(value):
        if isinstance(value, list):
            return [strip(v) for v in value]
        return {k: v for k, v in value.items() if k != "seconds"} if isinstance(value, dict) else value

    return {k: strip(v) for k, v in result.items() if k not in TIMING_FIELDS}


def _frames(root: Path):
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    return LeRobotDataset(f"local/{root.name}", root=root).hf_dataset.with_format("arrow")[:]


@pytest.mark.slow
@pytest.mark.timeout(1800)  # two tiny grids side by side, each bounded at 900 s
def test_the_smoke_grid_on_a_ray_cluster_matches_the_local_executor_and_survives_a_killed_worker(tmp_path, ray_cluster):
    grid = ["reproduce", "--config", str(REPO / "configs/reproduce/smoke.yaml"), *TINY]
    # the reference: the local executor, one torch thread like every Ray task here (so the same arithmetic)
    env = {**os.environ, "HF_HUB_OFFLINE": "1", "OMP_NUM_THREADS": "1"}
    local = subprocess.Popen(
        [str(MURM), *grid, f"--work_dir={tmp_path / 'local'}", f"--results_dir={tmp_path / 'local' / 'results'}"],
        cwd=tmp_path,
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )
    on_ray = subprocess.Popen(
        [
            str(MURM),
            *grid,
            "--work_dir=ray",
            "--results_dir=ray/results",
            "--executor=ray",
            f"--address={ray_cluster}",
            "--cpus-per-task=1",
            "--shard-episodes=2",
        ],
        cwd=tmp_path,
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )
    try:
        # kill -9 the workers running training tasks once a run has a checkpoint to resume from
        deadline, killed = time.monotonic() + 600, []
        while not killed and on_ray.poll() is None and time.monotonic() < deadline:
            checkpoints = list((tmp_path / "ray" / "runs").glob("smoke/*/*/seed0/checkpoints/last/training_state.pt"))
            killed = _task_processes("train_run") if checkpoints else []
            for pid in killed:
                os.kill(pid, signal.SIGKILL)
            time.sleep(0.05)
        ray_out = on_ray.communicate(timeout=900)[0]
        local_out = local.communicate(timeout=900)[0]
    finally:  # a failed test leaves no driver behind
        for driver in (on_ray, local):
            driver.kill()
    assert local.returncode == 0, local_out[-5000:]
    assert on_ray.returncode == 0, ray_out[-5000:]
    assert killed, "no training task was caught running"
    assert "resuming from step" in ray_out  # Ray retried the killed run, which resumed from its checkpoint

    runs = sorted((tmp_path / "local" / "results" / "smoke" / "runs").glob("*.json"))
    assert len(runs) == 2
    for path in runs:
        ours = json.loads((tmp_path / "ray" / "results" / "smoke" / "runs" / path.name).read_text())
        assert _without_timings(ours) == _without_timings(json.loads(path.read_text())), path.name
    # the collection ran as two shards of two episodes, merged into the same frames
    (name,) = [p.name for p in (tmp_path / "local" / "datasets").iterdir()]
    assert _frames(tmp_path / "ray" / "datasets" / name).equals(_frames(tmp_path / "local" / "datasets" / name))
    assert sorted(p.name for p in (tmp_path / "ray" / "datasets").iterdir()) == [name]  # shards merged, removed
    assert "(collect_shard pid=" in ray_out and "(train_run pid=" in ray_out  # the work ran as Ray tasks


def _processes_with(marker: str) -> list[int]:
    """Processes whose environment holds `marker` (every process a command started inherits it)."""
    pids = []
    for proc in Path("/proc").iterdir():
        try:
            if marker.encode() in (proc / "environ").read_bytes():
                pids.append(int(proc.name))
        except (OSError, ValueError):
            continue
    return pids


@pytest.mark.slow
@pytest.mark.parametrize("stop", ["kill -9 the driver", "Ctrl-C", "SIGTERM"])
def test_a_stopped_grid_keeps_its_checkpoints_and_starts_no_queued_job(tmp_path, stop):
    """`murm reproduce --jobs 2` stopped mid-training, by kill -9 of the driver, by Ctrl-C
    (SIGINT to the whole process group) or by SIGTERM to the group (`kill`, a scheduler's
    preemption): each run saves its checkpoint at its next step, no process outlives the
    stop, and the jobs still queued behind the two running ones never start. Ctrl-C and
    SIGTERM end the driver last, with its one line, once its jobs have saved."""
    import torch

    name, value = "MURM_TEST_DRIVER", tmp_path.name
    marker = f"{name}={value}"
    env = {**os.environ, "HF_HUB_OFFLINE": "1", name: value}
    # no evaluation before the end: the only checkpoints are a run's start and the one its stop writes
    long = [*TINY, "--train.steps=100000", "--train.eval_every=100000", "--seeds=[0,1,2]", "--stack_seeds=false"]
    stderr = tmp_path / "stderr.txt"
    with stderr.open("wb") as err:
        driver = subprocess.Popen(
            [
                str(MURM),
                "reproduce",
                "--config",
                str(REPO / "configs/reproduce/smoke.yaml"),
                *long,
                "--work_dir=work",
                "--results_dir=results",
                "--jobs=2",
            ],
            cwd=tmp_path,
            env=env,
            stdout=subprocess.DEVNULL,
            stderr=err,
            start_new_session=True,  # its own process group, as a terminal gives a command
        )
    logs = lambda: sorted((tmp_path / "work" / "runs").glob("smoke/*/*/seed*/log.csv"))  # noqa: E731

    def assert_saved() -> None:
        for log in logs():
            last_logged = int(log.read_text().splitlines()[-1].split(",")[0])
            state = torch.load(log.parent / "checkpoints" / "last" / "training_state.pt", weights_only=True)
            assert state["step"] >= last_logged > 0, log  # saved when the run stopped

    try:
        deadline = time.monotonic() + 600
        while time.monotonic() < deadline and driver.poll() is None:
            if len(logs()) == 2 and all(len(log.read_text().splitlines()) > 2 for log in logs()):
                break  # both jobs are training
            time.sleep(0.2)
        assert driver.poll() is None, "the driver ended before both runs were training"
        if stop in ("Ctrl-C", "SIGTERM"):
            os.killpg(driver.pid, signal.SIGINT if stop == "Ctrl-C" else signal.SIGTERM)
            assert driver.wait(timeout=180) == 1
            # the driver's last line (multiprocessing's resource tracker, a process of its own, may
            # print its shutdown warning after it, in either order under load)
            ours = [line for line in stderr.read_text().splitlines() if "resource_tracker" not in line]
            assert "finished cells are kept" in ours[-1]
            assert_saved()  # before the driver ended, not after
            if stop == "SIGTERM":  # SIGTERM once killed the driver outright and leaked its pool's semaphores
                assert "leaked" not in stderr.read_text()
        else:
            driver.kill()
        deadline = time.monotonic() + 120
        while _processes_with(marker) and time.monotonic() < deadline:
            time.sleep(0.5)
        assert not _processes_with(marker), "job or simulator processes outlived the stop"
    finally:
        for pid in _processes_with(marker):
            os.kill(pid, signal.SIGKILL)
    assert len(logs()) == 2, logs()  # the jobs queued behind them never started
    assert_saved()
