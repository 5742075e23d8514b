"""An encoder folder's two files, weights and config: saved so that a crash never leaves one
of each, and checked before use so that a torn folder is named as such.

A save used to write `model.safetensors` in place, then `config.json`: a kill between them
left new weights under an empty config, and `murm encode` then said only "Expecting value:
line 1 column 1 (char 0)". Now both files are written in full into `.saving/` inside the
folder first (a full disk fails there, leaving the previous encoder untouched), then the
old config is removed and the new files are renamed into place, config last. At any
moment the folder holds the previous encoder, the new one, or no `config.json`: no
encoder, which `check_encoder` reports with the file it lacks.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
from pathlib import Path

from safetensors import SafetensorError, safe_open

from lerobot_murm.checkpointing import write_synced

WEIGHTS_FILE = "model.safetensors"
CONFIG_FILE = "config.json"
METRICS_FILE = "metrics.json"  # beside them: what training measured (held-out PSNR, codebook use, steps)
STAGING = ".saving"


class IncompleteEncoder(RuntimeError):
    """An encoder folder with one of its files missing, empty or unreadable."""


def incomplete(directory: Path, why: str) -> IncompleteEncoder:
    return IncompleteEncoder(f"encoder {directory} is incomplete ({why}); run murm train-vqvae again to finish it")


def encoder_fingerprint(directory: Path) -> str:
    """The sha256 of the encoder's weights (hex): what latent caches, latent datasets and runs
    record of the encoder they used."""
    return hashlib.sha256((Path(directory) / WEIGHTS_FILE).read_bytes()).hexdigest()


def save_encoder_files(directory: Path, weights: bytes, config: bytes) -> None:
    """Replace the encoder in `directory` (or make one) by `weights` and `config`."""
    directory = Path(directory)
    staging = directory / STAGING
    shutil.rmtree(staging, ignore_errors=True)  # what a save cut short left
    staging.mkdir(parents=True)
    write_synced(staging / WEIGHTS_FILE, weights)
    write_synced(staging / CONFIG_FILE, config)
    (directory / CONFIG_FILE).unlink(missing_ok=True)  # from here to the last rename: no encoder, never a mixed one
    os.replace(staging / WEIGHTS_FILE, directory / WEIGHTS_FILE)
    os.replace(staging / CONFIG_FILE, directory / CONFIG_FILE)
    staging.rmdir()


def check_encoder(directory: Path) -> dict:
    """The encoder's config, once both files are found whole; `FileNotFoundError` where
    there is no encoder at all, `IncompleteEncoder` naming the file where it is torn."""
    directory = Path(directory)
    config, weights = directory / CONFIG_FILE, directory / WEIGHTS_FILE
    if not config.exists() and not weights.exists():
        raise FileNotFoundError(
            f"no VQ-VAE checkpoint in {directory} (no {CONFIG_FILE}); train one with murm train-vqvae"
        )
    for path in (config, weights):
        if not path.exists():
            raise incomplete(directory, f"{path.name} missing")
        if path.stat().st_size == 0:
            raise incomplete(directory, f"{path.name} empty")
    try:
        settings = json.loads(config.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as error:
        raise incomplete(directory, f"{CONFIG_FILE} unreadable: {error}") from None
    try:
        with safe_open(weights, framework="pt"):
            pass
    except SafetensorError as error:
        raise incomplete(directory, f"{WEIGHTS_FILE} unreadable: {error}") from None
    return settings
