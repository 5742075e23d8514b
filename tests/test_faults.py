"""Fault injection: kill -9 and a full disk during `murm collect`, a full disk while keeping
an encoder, kill -9 mid encoder save, a torn checkpoint swap, a training state that would run
code, kill -9 of the trainer during evaluation."""

import hashlib
import json
import os
import random
import resource
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
import pytest
import torch

from lerobot_murm import checkpointing
from lerobot_murm.checkpointing import (
    CheckpointError,
    append_rows,
    load_state,
    recover,
    save_state,
    set_aside_rows_after,
    staging_folder,
    swap_in,
)
from lerobot_murm.collection import CollectConfig, collect
from lerobot_murm.experiments.configuration_reproduce import load_reproduce_config
from lerobot_murm.vqvae import VQVAE, VQVAEConfig
from lerobot_murm.vqvae.encoder_files import IncompleteEncoder

sys.path.insert(0, str(Path(__file__).parent / "helpers"))
from commands import run

MURM = Path(sys.executable).parent / "murm"
RECIPE = ["--task", "place_in_box", "--cameras", "global,active", "--image-size", "16"]
SUMMARY = "meta/murm_collection.json"


def unbroken_collection(root: Path, episodes: int, flush_every: int) -> Path:
    """The collection a faulted one must end as: RECIPE's, collected in one go."""
    collect(
        CollectConfig(
            task="place_in_box",
            root=root,
            episodes=episodes,
            workers=1,
            cameras=("global", "active"),
            image_size=16,
            flush_every=flush_every,
        )
    )
    return root


def disk_full_past(limit: int) -> Callable[[], None]:
    """A child process's full disk, simulated without privileges by a file-size limit: writes
    past `limit` bytes fail with EFBIG, as they would with ENOSPC (not a killed process)."""

    def small_disk() -> None:
        resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit))
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)

    return small_disk


def contents(root: Path) -> dict[str, object]:
    """Every file of a dataset by content: parquet as its table (less the random fingerprint
    `datasets` stamps on each write), JSON parsed (LeRobot orders the keys of stats.json
    differently from one process to the next), anything else as bytes."""

    def read(path: Path) -> object:
        if path.suffix == ".parquet":
            return pq.read_table(path).replace_schema_metadata(None)
        if path.suffix == ".json":
            data = json.loads(path.read_text())
            if path.name == "murm_collection.json":  # it keeps the text of info.json and stats.json
                saved = data["flushed"]["rewritten"]
                data["flushed"]["rewritten"] = {k: v and json.loads(v) for k, v in saved.items()}
            return data
        return hashlib.sha256(path.read_bytes()).hexdigest()

    return {p.relative_to(root).as_posix(): read(p) for p in sorted(root.rglob("*")) if p.is_file()}


def saved_episodes(root: Path) -> int:
    path = root / SUMMARY
    return json.loads(path.read_text())["episodes"] if path.exists() else 0


def alive(pid: int) -> bool:
    try:
        return Path(f"/proc/{pid}/stat").read_text().split(") ")[1][0] != "Z"
    except FileNotFoundError:
        return False


def descendants(pid: int) -> list[int]:
    children = subprocess.run(["pgrep", "-P", str(pid)], capture_output=True, text=True).stdout.split()
    return [int(c) for c in children] + [d for c in children for d in descendants(int(c))]


def murm_collect(root: Path, episodes: int, flush_every: int, resume: bool) -> list[str]:
    args = [str(MURM), "collect", *RECIPE, "--root", str(root), "--episodes", str(episodes), "--workers", "2"]
    return args + ["--flush-every", str(flush_every)] + (["--resume"] if resume else [])


def collect_until_killed(args: list[str], root: Path, rng: random.Random) -> None:
    """Start the collection `args` writing to `root`, kill -9 it at a random moment within one
    flush interval after its next flush (mid-episode, mid-write or mid-flush), so that a fast
    machine cannot finish first."""
    before = saved_episodes(root)
    log = root.with_name("stderr.txt")
    with log.open("w") as stderr:  # a file: an unread pipe could fill and block the run
        process = subprocess.Popen(args, stdout=subprocess.DEVNULL, stderr=stderr)
    deadline = time.monotonic() + 900  # a liveness bound, generous for a crowded CI machine
    try:
        while saved_episodes(root) <= before:
            assert process.poll() is None, f"the collection ended before it could be killed: {log.read_text()[-2000:]}"
            assert time.monotonic() < deadline, f"no flush: {log.read_text()[-2000:]}"
            time.sleep(0.05)
        time.sleep(rng.uniform(0.0, 0.5))  # about one flush interval at 4-5 episodes/s
        workers = descendants(process.pid)
    except BaseException:  # a failed test leaves no collection running
        process.kill()
        raise
    assert workers, "no worker processes"
    process.kill()
    process.wait()
    deadline = time.monotonic() + 300  # a liveness bound: they leave within a second on an idle machine
    while any(alive(pid) for pid in workers):
        assert time.monotonic() < deadline, f"processes left behind: {[p for p in workers if alive(p)]}"
        time.sleep(0.1)


@pytest.mark.slow
def test_kill_9_at_random_points_then_resume_gives_the_unbroken_dataset(tmp_path):
    episodes, flush_every = 12, 2
    reference = unbroken_collection(tmp_path / "unbroken", episodes, flush_every)

    root, rng = tmp_path / "killed", random.Random(16)
    collect_until_killed(murm_collect(root, episodes, flush_every, resume=False), root, rng)
    collect_until_killed(murm_collect(root, episodes, flush_every, resume=True), root, rng)
    assert saved_episodes(root) < episodes, "killed too late to test anything"
    finished = run(murm_collect(root, episodes, flush_every, resume=True), timeout=300)
    assert finished.returncode == 0, finished.stderr[-2000:]
    assert contents(root) == contents(reference)  # the same files, metadata included


COPY_FROM_DONORS = """
import sys
from pathlib import Path
from lerobot_murm.collection import CollectConfig, collect
from lerobot_murm.collection.prefixes import noise_donors
half = CollectConfig(task="place_in_box", root=Path(sys.argv[1]), episodes=int(sys.argv[2]), workers=2,
                     cameras=("global", "active"), image_size=16, flush_every=2, noisy_fraction=0.5,
                     resume=sys.argv[3] == "resume")
collect(half, donors=noise_donors(half))
"""


@pytest.mark.slow
def test_kill_9_while_copying_from_noise_donors_then_resume_gives_the_unbroken_dataset(tmp_path):
    """A half-noisy collection copied from its all-clean and all-noisy siblings (as `murm
    reproduce` builds Table 7's) survives kill -9 like a simulated one."""
    episodes = 16
    recipe = {"task": "place_in_box", "workers": 2, "cameras": ("global", "active"), "image_size": 16, "flush_every": 2}
    for name, fraction in (("clean", 0.0), ("noisy", 1.0)):
        collect(CollectConfig(root=tmp_path / "datasets" / name, episodes=episodes, noisy_fraction=fraction, **recipe))
    reference = tmp_path / "unbroken"
    collect(CollectConfig(root=reference, episodes=episodes, noisy_fraction=0.5, **recipe))

    root, rng = tmp_path / "datasets" / "half", random.Random(7)
    copy = [sys.executable, "-c", COPY_FROM_DONORS, str(root), str(episodes)]
    collect_until_killed(copy + ["fresh"], root, rng)
    collect_until_killed(copy + ["resume"], root, rng)
    assert saved_episodes(root) < episodes, "killed too late to test anything"
    finished = run(copy + ["resume"], timeout=300)
    assert finished.returncode == 0, finished.stderr[-2000:]
    assert contents(root) == contents(reference)


@pytest.mark.slow
def test_a_full_disk_mid_collection_loses_only_the_unflushed_episodes(tmp_path):
    """The disk fills while a data file grows (`disk_full_past`). The flushed episodes stay;
    after making room, --resume ends with the unbroken dataset."""
    episodes, flush_every = 6, 2
    reference = unbroken_collection(tmp_path / "unbroken", episodes, flush_every)
    root = tmp_path / "ds"
    command = [str(MURM), "collect", *RECIPE, "--root", str(root), "--workers", "1"]
    first = run(command + ["--episodes", "2", "--flush-every", "2"], timeout=300)
    assert first.returncode == 0, first.stderr[-2000:]
    two_episodes = max(p.stat().st_size for p in root.glob("data/*/*.parquet"))

    small_disk = disk_full_past(int(1.5 * two_episodes))  # the next data file fails in its third episode
    full = run(
        command + ["--episodes", str(episodes), "--flush-every", "100", "--resume"], timeout=300, preexec_fn=small_disk
    )
    assert full.returncode == 1, full.stderr[-2000:]
    assert full.stderr.splitlines()[-1].startswith(f"murm collect: cannot write to {root} (")
    assert "2 of 6 episodes are safely saved; make room, then run again with --resume" in full.stderr
    assert "Traceback" not in full.stderr.split("libtorchcodec loading traceback]")[-1]

    resumed = run(command + ["--episodes", str(episodes), "--flush-every", str(flush_every), "--resume"], timeout=300)
    assert resumed.returncode == 0, resumed.stderr[-2000:]
    assert "removed" in resumed.stdout  # the torn files of the full disk
    assert contents(root) == contents(reference)


def stage_checkpoint(folder: Path, step: int) -> None:
    """A complete next checkpoint beside `folder`, as `murm train` writes one before the swap."""
    tmp = staging_folder(folder)
    (tmp / "pretrained_model").mkdir(parents=True)
    (tmp / "pretrained_model" / "model.safetensors").write_text(f"weights of step {step}")
    save_state({"step": step}, tmp / "training_state.pt")


def die_at_call(monkeypatch, owner, name: str, call: int) -> None:
    """The `call`-th call of `owner.name` dies as kill -9 would: nothing after it runs."""
    real, calls = getattr(owner, name), []

    def dying(*args, **kwargs):
        calls.append(args)
        if len(calls) == call:
            raise KeyboardInterrupt("killed")
        return real(*args, **kwargs)

    monkeypatch.setattr(owner, name, dying)


@pytest.mark.parametrize(
    ("crash", "expected_step"),
    [(("rename", 1), 1), (("rename", 2), 2), (("rmtree", 2), 2)],
    ids=["before-first-rename", "between-renames", "before-cleanup"],
)
def test_a_torn_checkpoint_swap_recovers_a_complete_checkpoint(tmp_path, monkeypatch, crash, expected_step):
    """Killed before the swap (last intact), between its renames (only last.old and a complete
    last.tmp exist), or before removing last.old: the newest complete checkpoint is used, and
    the next swap works (it used to fail with "Directory not empty")."""
    last = tmp_path / "checkpoints" / "last"
    stage_checkpoint(last, 1)
    swap_in(last)
    stage_checkpoint(last, 2)
    what, call = crash
    die_at_call(monkeypatch, Path if what == "rename" else checkpointing.shutil, what, call)
    with pytest.raises(KeyboardInterrupt):
        swap_in(last)
    monkeypatch.undo()
    assert recover(last)
    assert load_state(last / "training_state.pt")["step"] == expected_step
    assert (last / "pretrained_model" / "model.safetensors").read_text() == f"weights of step {expected_step}"
    assert sorted(p.name for p in last.parent.iterdir()) == ["last"]
    stage_checkpoint(last, 3)
    swap_in(last)
    assert load_state(last / "training_state.pt")["step"] == 3


def test_a_half_written_checkpoint_is_never_used(tmp_path):
    last = tmp_path / "last"
    stage_checkpoint(last, 1)
    swap_in(last)
    torn = staging_folder(last)
    (torn / "pretrained_model").mkdir(parents=True)  # killed before its training state was written
    assert recover(last) and load_state(last / "training_state.pt")["step"] == 1
    assert not torn.exists()


def test_an_unreadable_training_state_is_a_clear_error(tmp_path):
    path = tmp_path / "training_state.pt"
    save_state({"step": 5, "weights": torch.zeros(1000)}, path)
    path.write_bytes(path.read_bytes()[:2000])
    with pytest.raises(CheckpointError, match=f"cannot read training state {path} .*damaged"):
        load_state(path)
    with pytest.raises(CheckpointError, match="missing"):
        load_state(tmp_path / "none.pt")


class RunsCode:
    """What a training state from someone else could hold: unpickling it calls a function."""

    def __init__(self, marker: Path):
        self.marker = marker

    def __reduce__(self):
        return Path.touch, (self.marker,)


def test_a_training_state_holds_plain_values_and_loads_no_code(tmp_path):
    path, marker = tmp_path / "training_state.pt", tmp_path / "code_ran"
    torch.save({"step": 5, "trap": RunsCode(marker)}, path)
    with pytest.raises(CheckpointError, match="holds more than tensors and plain numbers; it is not loaded"):
        load_state(path)
    assert not marker.exists()
    with pytest.raises(TypeError, match=r"state\['rng'\] is a Generator"):  # found when saved, not at resume
        save_state({"step": 5, "rng": np.random.default_rng(0)}, path)
    state = {
        "step": 5,
        "rng": np.random.default_rng(0).bit_generator.state,
        "weights": torch.ones(2),
        "betas": (0.9, 1),
    }
    save_state(state, path)
    assert torch.load(path, weights_only=True)["rng"] == state["rng"]


def test_a_resumed_run_sets_log_rows_aside_instead_of_deleting_them(tmp_path):
    log = tmp_path / "log.csv"
    append_rows(log, ["step", "loss"], [{"step": s, "loss": s / 10} for s in range(1, 6)])
    assert set_aside_rows_after(log, 3) == 2
    assert [r.split(",")[0] for r in log.read_text().splitlines()] == ["step", "1", "2", "3"]
    superseded = tmp_path / "log.superseded.csv"
    assert [r.split(",")[0] for r in superseded.read_text().splitlines()] == ["step", "4", "5"]


@pytest.mark.slow
def test_murm_train_resumes_from_the_checkpoint_a_torn_swap_left(tiny_train_yaml, tmp_path):
    """Killed between the two renames of its last checkpoint swap, a run has only
    `checkpoints/last.old`: the next run recovers it and resumes there."""
    path = tiny_train_yaml()
    command = [str(MURM), "train", "--config", str(path)]
    first = run(command, timeout=600, env=os.environ | {"HF_HUB_OFFLINE": "1"})
    assert first.returncode == 0, first.stderr[-3000:]
    run_dir = tmp_path / "run"
    (run_dir / "final_eval.json").unlink()
    last = run_dir / "checkpoints" / "last"
    last.rename(last.with_name("last.old"))
    again = run(command + ["--steps=6"], timeout=600, env=os.environ | {"HF_HUB_OFFLINE": "1"})
    assert again.returncode == 0, again.stderr[-3000:]
    assert "recovered the checkpoint" in again.stdout and "resuming from step 4" in again.stdout
    steps = [line.split(",")[0] for line in (run_dir / "log.csv").read_text().splitlines()[1:]]
    assert steps == ["1", "2", "3", "4", "5", "6"]


KEEP_GLOBAL_ENCODER = """
import sys
from lerobot_murm.experiments import artifacts
from lerobot_murm.experiments.configuration_reproduce import load_reproduce_config
config = load_reproduce_config(sys.argv[1], sys.argv[2:])
artifacts.keep_encoders(config, [(artifacts.encoder_root(config, "place_in_box"), "global")])
"""


def test_a_full_disk_while_keeping_an_encoder_leaves_no_kept_encoder_that_looks_finished(tmp_path):
    """The disk fills while a trained encoder is copied beside the results. The half copy
    does not pass for a finished encoder (its metrics are copied last), so the next sitting
    copies it again, whole, instead of encoding with torn weights."""
    from lerobot_murm.experiments import artifacts

    overrides = [f"--results_dir={tmp_path / 'results'}", f"--work_dir={tmp_path / 'work'}"]
    table6 = Path(__file__).parents[1] / "configs/reproduce/table6.yaml"
    config = load_reproduce_config(table6, overrides)
    root = artifacts.encoder_root(config, "place_in_box")
    trained = artifacts.encoder_dir(config, root) / "global"
    trained.mkdir(parents=True)
    (trained / "config.json").write_text("{}")
    (trained / "model.safetensors").write_bytes(random.Random(0).randbytes(1 << 20))
    (trained / "metrics.json").write_text(
        json.dumps({"interrupted": False, "steps": artifacts.encoder_steps(config, "global")})
    )
    command = [sys.executable, "-c", KEEP_GLOBAL_ENCODER, str(table6), *overrides]

    full = run(command, timeout=120, preexec_fn=disk_full_past(1 << 16))
    assert full.returncode == 1 and "File too large" in full.stderr, full.stderr[-2000:]
    kept = artifacts.kept_encoder_dir(config, root) / "global"
    assert kept.exists()  # the copy was under way
    assert not artifacts.encoder_is_finished(kept, artifacts.encoder_steps(config, "global"))

    again = run(command, timeout=120)
    assert again.returncode == 0, again.stderr[-2000:]
    assert artifacts.encoder_is_finished(kept, artifacts.encoder_steps(config, "global"))
    assert artifacts.encoder_fingerprint(kept) == artifacts.encoder_fingerprint(trained)


KILLED_MID_SAVE = """
import builtins, io, os, signal, sys
from lerobot_murm.vqvae import VQVAE, VQVAEConfig

model = VQVAE(VQVAEConfig(codebook_size=64))
die_at, changes = int(sys.argv[2]), []


def changing(real, changes_disk=lambda *args, **kwargs: True):
    def call(*args, **kwargs):
        if changes_disk(*args, **kwargs):
            changes.append(real.__name__)
            if len(changes) == die_at:
                os.kill(os.getpid(), signal.SIGKILL)  # kill -9 just before this change to the disk
        return real(*args, **kwargs)
    return call


def for_writing(file, mode="r", *args, **kwargs):
    return any(c in mode for c in "wax+")


io.open = builtins.open = changing(builtins.open, for_writing)
os.replace, os.rename, os.unlink, os.rmdir = (changing(f) for f in (os.replace, os.rename, os.unlink, os.rmdir))
model.save(sys.argv[1])
"""


def test_a_kill_9_anywhere_in_an_encoder_save_leaves_the_previous_encoder_or_none(tmp_path):
    """Killed before each file it opens for writing, renames or removes, a save that replaces an
    encoder leaves the previous one, the new one, or none (reported as such), never a mix: the
    weights used to be written in place and then the config, and a kill between the two left
    new weights under an empty config."""
    previous = VQVAE(VQVAEConfig(codebook_size=32))
    found = []
    for die_at in range(1, 50):
        folder = tmp_path / f"killed-at-{die_at}" / "global"
        previous.save(folder)
        save = run([sys.executable, "-c", KILLED_MID_SAVE, str(folder), str(die_at)], timeout=300)
        assert save.returncode in (0, -signal.SIGKILL), save.stderr[-2000:]
        try:
            encoder = VQVAE.load(folder)
        except IncompleteEncoder as error:
            assert f"encoder {folder} is incomplete (config.json missing)" in str(error)
            found.append("none")
            previous.save(folder)  # as `murm train-vqvae` run again does
            encoder = VQVAE.load(folder)
        else:
            found.append(encoder.config.codebook_size)  # 32: the previous encoder, 64: the new one
        if encoder.config.codebook_size == 32:
            for name, tensor in previous.state_dict().items():
                assert torch.equal(encoder.state_dict()[name], tensor), name
        if save.returncode == 0:  # it got past its last change: every point has been tried
            break
    assert found[0] == 32 and found[-1] == 64 and set(found) <= {32, "none", 64}, found


def cpu_ticks(pids: list[int]) -> int:
    """User and system CPU time of the processes still there, in clock ticks."""
    ticks = 0
    for pid in pids:
        try:
            fields = Path(f"/proc/{pid}/stat").read_text().split(") ")[1].split()
        except FileNotFoundError:
            continue
        ticks += int(fields[11]) + int(fields[12])
    return ticks


@pytest.mark.slow
def test_kill_9_of_the_trainer_during_evaluation_leaves_no_worker_and_no_traceback(tiny_train_yaml, tmp_path):
    """Orphaned by a kill -9, an evaluation worker used to write a BrokenPipeError traceback into
    the output it shared with the trainer."""
    steps = 2
    path = tiny_train_yaml(steps=steps, final_eval_episodes=20, eval_envs=2)
    output, log = tmp_path / "output.txt", tmp_path / "run" / "log.csv"
    with output.open("w") as out:  # what `murm train ... > output.txt 2>&1` would hold
        trainer = subprocess.Popen(
            [str(MURM), "train", "--config", str(path)],
            stdout=out,
            stderr=subprocess.STDOUT,
            env=os.environ | {"HF_HUB_OFFLINE": "1", "OMP_NUM_THREADS": "2"},  # two cores: worker processes
        )
    deadline = time.monotonic() + 600  # a liveness bound for a crowded machine
    try:
        while not log.exists() or log.read_text().splitlines()[-1].split(",")[0] != str(steps):
            assert trainer.poll() is None and time.monotonic() < deadline, output.read_text()[-3000:]
            time.sleep(0.05)
        workers = descendants(trainer.pid)
        idle = cpu_ticks(workers)  # the simulators were made before training and have waited since
        while cpu_ticks(workers) < idle + 5:  # the final evaluation steps them
            assert trainer.poll() is None and time.monotonic() < deadline, output.read_text()[-3000:]
            time.sleep(0.01)
    finally:
        trainer.kill()
        trainer.wait()
    assert len(workers) == 2
    while any(alive(pid) for pid in workers):
        assert time.monotonic() < deadline, f"workers left behind: {[p for p in workers if alive(p)]}"
        time.sleep(0.1)
    text = output.read_text()
    assert "Traceback" not in text and "Error" not in text, text[-3000:]
