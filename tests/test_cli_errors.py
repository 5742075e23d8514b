"""Every bad input ends in one line on stderr that names it, exit 2 (usage) or 1 (failure),
before any work; --debug or MURM_DEBUG=1 shows the traceback instead. So does every failure
of a torn file or a full disk, with nothing else on stderr (what the libraries logged held back)."""

import os
import sys
from pathlib import Path

import pytest
import yaml

from lerobot_murm.cli import main
from lerobot_murm.vqvae import VQVAE, VQVAEConfig

sys.path.insert(0, str(Path(__file__).parent / "helpers"))
from commands import OFFLINE, run
from one_line import murm_error

MURM = Path(sys.executable).parent / "murm"
COLLECT = [
    "collect",
    "--task",
    "pick_up",
    "--episodes",
    "1",
    "--workers",
    "1",
    "--cameras",
    "global",
    "--image-size",
    "16",
]
QUIET = {**os.environ, **OFFLINE, "TQDM_DISABLE": "1"}  # no progress bars: stderr holds only what went wrong


def murm_stderr(argv: list, cwd: Path, python: str | None = None) -> tuple[int, list[str]]:
    """Run the installed `murm argv` (or the script `python` with `argv`) in a subprocess:
    (exit code, every line of its stderr)."""
    command = [MURM] if python is None else [sys.executable, "-c", python]
    result = run([*command, *argv], timeout=300, cwd=cwd, env=QUIET)
    code, stderr = result.returncode, result.stderr
    return code, stderr.splitlines()


@pytest.mark.parametrize(
    ("change", "code", "message"),
    [
        (["--task", "stack"], 2, "murm collect: unknown task 'stack'; valid tasks"),
        (["--cameras", "wrist"], 2, "unknown camera(s) ['wrist']"),
        (["--image-size", "0"], 2, "image_size must be an integer in"),
        (["--episodes", "-1"], 2, "episodes must be at least 1, got -1"),
        (["--workers", "0"], 2, "workers must be at least 1, got 0"),
        (["--seed", "-5"], 2, "seed must be >= 0, got -5"),
        (["--noise-std", "nan"], 2, "noise_std must be a finite number >= 0, got nan"),
        (["--flush-every", "0"], 2, "flush_every must be at least 1"),
        (["--episodes", "abc"], 2, "argument --episodes: invalid int value: 'abc'"),
        (["--resume", "--overwrite"], 2, "choose one of resume and overwrite"),
    ],
)
def test_bad_collect_arguments(tmp_path, capsys, change, code, message):
    code_seen, line = murm_error([*COLLECT, "--root", tmp_path / "ds", *change], capsys)
    assert (code_seen, message in line) == (code, True), line
    assert not (tmp_path / "ds").exists()  # nothing made


def test_a_root_that_is_a_file(tmp_path, capsys):
    (tmp_path / "file").write_text("mine")
    code, line = murm_error([*COLLECT, "--root", tmp_path / "file"], capsys)
    assert code == 1 and line.startswith("murm collect:") and "file is a file, not a folder" in line


def test_overwrite_deletes_only_what_murm_made(tmp_path, capsys):
    kept = tmp_path / "photos"
    kept.mkdir()
    (kept / "holiday.jpg").write_text("precious")
    code, line = murm_error([*COLLECT, "--root", kept, "--overwrite"], capsys)
    assert code == 1 and "--overwrite refused" in line and "not a murm collection" in line
    assert (kept / "holiday.jpg").read_text() == "precious"


def test_a_missing_dataset_folder_is_reported_as_such(tmp_path, capsys):
    missing = tmp_path / "no" / "such"
    code, line = murm_error(["train-vqvae", "--dataset", missing, "--camera", "global"], capsys)
    assert code == 2 and f"dataset folder {missing} does not exist" in line and "Repo id" not in line


def test_a_torn_dataset_is_a_clear_error(tmp_path, capsys):
    from lerobot_murm.collection import CollectConfig, collect

    root = tmp_path / "ds"
    collect(CollectConfig(task="pick_up", root=root, episodes=1, workers=1, cameras=("global",), image_size=16))
    data = next(root.glob("data/*/*.parquet"))
    data.write_bytes(data.read_bytes()[:-100])  # as a hard stop leaves an unclosed file
    code, line = murm_error(["train-vqvae", "--dataset", root, "--camera", "global", "--out", tmp_path / "vq"], capsys)
    assert code == 2 and f"cannot read the dataset at {root}" in line and "--resume" in line
    # `datasets` logs the error twice before raising it: held back, stderr is the one line
    code, lines = murm_stderr(
        ["train-vqvae", "--dataset", root, "--camera", "global", "--out", tmp_path / "vq"], tmp_path
    )
    assert code == 2 and len(lines) == 1 and lines[0].startswith(f"murm train-vqvae: cannot read the dataset at {root}")


FULL_DISK = """
import errno, sys
import PIL.Image
from lerobot_murm.cli import main

def full_disk(*args, **kwargs):
    raise OSError(errno.ENOSPC, "No space left on device")

PIL.Image.Image.save = full_disk  # every PNG a collection writes
main(sys.argv[1:])
"""


def test_a_full_disk_during_a_collection_is_one_line(tmp_path):
    """LeRobot's image writer logged each failed PNG (1,257 lines on a real full disk) and went on."""
    code, lines = murm_stderr([*COLLECT, "--episodes", "2", "--root", tmp_path / "ds"], tmp_path, python=FULL_DISK)
    assert code == 1 and len(lines) == 1, lines[:5]
    assert lines[0].startswith(f"murm collect: cannot write to {tmp_path / 'ds'} (No space left on device): 0 of 2")


@pytest.mark.parametrize(
    ("change", "code", "message"),
    [
        (["--steps", "0"], 2, "steps and batch_size must be at least 1, got 0"),
        (["--image-size", "30"], 2, "image_size must be a multiple of 4"),
    ],
)
def test_bad_train_vqvae_arguments(tmp_path, capsys, change, code, message):
    """Checked before the dataset is opened; a camera the dataset lacks: test_own_dataset.py."""
    argv = ["train-vqvae", "--dataset", tmp_path, "--camera", "global", "--out", tmp_path / "vq", *change]
    code_seen, line = murm_error(argv, capsys)
    assert (code_seen, message in line) == (code, True), line
    assert not (tmp_path / "vq").exists()


def test_a_torn_encoder_is_named_with_its_file(tmp_path, capsys):
    encoder = tmp_path / "vqvae" / "global"
    VQVAE(VQVAEConfig()).save(encoder)
    (encoder / "config.json").write_bytes(b"")  # what a kill between the two files of a save used to leave
    encode = ["encode", "--dataset", tmp_path, "--encoders", encoder, "--cache-dir", tmp_path / "cache"]
    code, line = murm_error(encode, capsys)
    assert code == 2
    assert f"encoder {encoder} is incomplete (config.json empty); run murm train-vqvae again to finish it" in line
    (encoder / "config.json").unlink()
    code, line = murm_error(encode, capsys)
    assert code == 2 and f"encoder {encoder} is incomplete (config.json missing)" in line


@pytest.mark.parametrize("command", ["encode", "train", "check-encoders"])
def test_a_truncated_encoder_is_one_line(train_yaml, command):
    folder = train_yaml.parent
    encoder = folder / "vqvae" / "global"
    weights = encoder / "model.safetensors"
    weights.write_bytes(weights.read_bytes()[:-100])  # a copy cut short
    argv = {
        "encode": ["encode", "--dataset", folder, "--encoders", encoder, "--cache-dir", folder / "cache"],
        "train": ["train", "--config", train_yaml],
        "check-encoders": ["check-encoders", "--dataset", folder, "--encoders", encoder],
    }[command]
    code, lines = murm_stderr(argv, folder)
    assert code == 2 and len(lines) == 1, lines[-20:]
    assert lines[0].startswith(f"murm {command}: encoder {encoder} is incomplete (model.safetensors unreadable: ")
    assert "run murm train-vqvae again to finish it" in lines[0]


def test_encode_checks_its_encoders_and_cache_folder_before_encoding(tmp_path, capsys):
    code, line = murm_error(["encode", "--dataset", tmp_path, "--encoders", tmp_path / "none"], capsys)
    assert code == 2 and f"no VQ-VAE checkpoint in {tmp_path / 'none'}" in line
    (tmp_path / "cache").write_text("a file")
    code, line = murm_error(
        ["encode", "--dataset", tmp_path, "--encoders", tmp_path, "--cache-dir", tmp_path / "cache"], capsys
    )
    assert code == 1 and "is a file, not a folder" in line


@pytest.fixture
def train_yaml(tmp_path) -> Path:
    """A `murm train` config whose encoders exist (untrained: validation reads their files, not their weights)."""
    for camera in ("global", "adjacent"):
        VQVAE(VQVAEConfig(camera=camera)).save(tmp_path / "vqvae" / camera)
    config = {
        "dataset": str(tmp_path / "no_dataset"),
        "task": "place_in_box",
        "output_dir": str(tmp_path / "run"),
        "policy": {
            "type": "murm",
            "method": "concat",
            "cameras": ["global", "adjacent"],
            "encoder_dir": str(tmp_path / "vqvae"),
            "epsilon": [1.0, 1.0],
        },
    }
    path = tmp_path / "train.yaml"
    path.write_text(yaml.safe_dump(config))
    return path


@pytest.mark.parametrize(
    ("overrides", "code", "message"),
    [
        (["--task=stack"], 2, "unknown task 'stack'"),
        (["--steps=0"], 2, "steps must be at least 1, got 0"),
        (["--seed=-5"], 2, "seed must be >= 0, got -5"),
        (["--eval_mask_p=[1.5]"], 2, "eval_mask_p must be masking levels in [0, 1)"),
        (["--stepz=10"], 2, "unrecognized arguments: --stepz=10"),
        (["--policy.method=fancy"], 2, "unknown method 'fancy'"),
        (["--policy.encoder_dir=/no/encoders"], 2, "no VQ-VAE for camera 'global'"),
        ([], 2, "does not exist"),  # the dataset: checked before any policy or cache is built
    ],
)
def test_bad_train_configs_fail_before_any_work(train_yaml, capsys, overrides, code, message):
    code_seen, line = murm_error(["train", "--config", train_yaml, *overrides], capsys)
    assert (code_seen, message in line) == (code, True), line
    assert not (train_yaml.parent / "run" / "checkpoints").exists()


def test_a_missing_config_file_is_bad_input(tmp_path, capsys):
    for command in ("train", "reproduce"):
        code, line = murm_error([command, "--config", tmp_path / "none.yaml"], capsys)
        assert code == 2 and f"argument --config: no readable config file {tmp_path / 'none.yaml'}" in line


def test_a_typo_in_a_config_file(train_yaml, capsys):
    train_yaml.write_text(train_yaml.read_text().replace("task:", "tsak:"))
    code, line = murm_error(["train", "--config", train_yaml], capsys)
    assert code == 2 and "tsak" in line


def test_the_whole_reproduce_grid_is_checked_before_collecting(tmp_path, capsys):
    grid = {
        "name": "bad",
        "tasks": ["pick_up"],
        "work_dir": str(tmp_path / "work"),
        "results_dir": str(tmp_path / "results"),
        "cells": [{"method": "single", "cameras": ["global"]}, {"method": "separated-q", "cameras": ["global", "top"]}],
    }
    path = tmp_path / "grid.yaml"
    path.write_text(yaml.safe_dump(grid))
    code, line = murm_error(["reproduce", "--config", path], capsys)
    assert code == 2 and "cell separated-q-global+top: unknown method 'separated-q'" in line
    grid["cells"][1] = {"method": "separated_q", "cameras": ["global", "top"], "policy": {"dropuot_p": 0.3}}
    path.write_text(yaml.safe_dump(grid))
    code, line = murm_error(["reproduce", "--config", path], capsys)
    assert code == 2 and "dropuot_p" in line
    grid["cells"][1]["policy"] = {}
    grid["collection"] = {"noise_std": float("nan")}
    path.write_text(yaml.safe_dump(grid))
    code, line = murm_error(["reproduce", "--config", path], capsys)
    assert code == 2 and "noise_std must be a finite number" in line
    # a budget grid's budget is chosen over all its runs: a sitting of part of it would choose it on that part
    grid["collection"] = {}
    grid["budget"] = {"cap": 20, "every": 10}
    path.write_text(yaml.safe_dump(grid))
    code, line = murm_error(["reproduce", "--config", path, "--seeds=[0]"], capsys)
    assert code == 2 and "bad chooses one budget over all its runs, so it runs whole" in line
    assert not (tmp_path / "work").exists() and not (tmp_path / "results").exists()


def test_other_commands_name_the_missing_folder(tmp_path, capsys):
    code, line = murm_error(["report", "--results", tmp_path / "none"], capsys)
    assert code == 2 and f"no results folder {tmp_path / 'none'}" in line
    code, line = murm_error(["push", "--root", tmp_path, "--repo-id", "user/ds"], capsys)
    assert code == 2 and "is not a dataset `murm collect` or `murm encode --to-dataset` made" in line


def test_a_torn_grid_table_is_a_clear_error(tmp_path, capsys):
    (tmp_path / "results" / "table4").mkdir(parents=True)
    (tmp_path / "results" / "table4" / "table.csv").write_text("task,cell\nplace_in_box,single-glo")
    code, line = murm_error(["report", "--results", tmp_path / "results", "--out", tmp_path / "REPORT.md"], capsys)
    assert code == 2 and "table.csv is not a grid table (10 of its 12 columns missing, 'method' first)" in line
    assert "run `murm report` again to rebuild it from its runs" in line


def test_debug_shows_the_traceback(tmp_path, monkeypatch):
    with pytest.raises(ValueError, match="unknown task"):
        main([*COLLECT, "--root", str(tmp_path / "ds"), "--task", "stack", "--debug"])
    monkeypatch.setenv("MURM_DEBUG", "1")
    with pytest.raises(ValueError, match="unknown task"):
        main([*COLLECT, "--root", str(tmp_path / "ds"), "--task", "stack"])


def test_the_installed_command_exits_with_one_line(tmp_path):
    result = run([str(MURM), *COLLECT, "--root", str(tmp_path / "ds"), "--seed", "-5"], timeout=600)
    assert result.returncode == 2
    assert result.stderr.splitlines()[-1] == "murm collect: seed must be >= 0, got -5 (--debug shows where)"
    assert "Traceback" not in result.stderr.split("libtorchcodec loading traceback]")[-1]


def test_a_run_without_its_checkpoint_is_never_restarted_over_its_log(train_yaml, capsys):
    run = train_yaml.parent / "run"
    (run / "checkpoints" / "last" / "pretrained_model").mkdir(parents=True)
    log = b"step,value_loss\r\n250,0.5\r\n500,0.4\r\n"
    (run / "log.csv").write_bytes(log)
    code, line = murm_error(["train", "--config", train_yaml], capsys)
    assert code == 1 and "holds an earlier run (logged to step 500) but no checkpoint to resume from" in line
    (run / "checkpoints" / "last" / "training_state.pt").write_bytes(b"PK\x03\x04 torn")
    code, line = murm_error(["train", "--config", train_yaml], capsys)
    assert code == 1 and "cannot read training state" in line and "damaged" in line
    assert (run / "log.csv").read_bytes() == log
