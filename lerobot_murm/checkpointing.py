"""Crash-safe files for long runs: atomic writes, a checkpoint folder swap that survives a
kill at any point, training states that fail loudly and load no code, and logs that never
lose a row.

Shared by `murm train` (policy checkpoints, `log.csv`, `eval.csv`), `murm train-vqvae`
(its resume state) and `murm collect` (its summary record). Hand-written because neither
LeRobot nor accelerate offers a recoverable folder swap: LeRobot's `save_checkpoint`
writes into the final folder in place.
"""

from __future__ import annotations

import csv
import io
import os
import pickle
import shutil
from pathlib import Path

import torch


class CheckpointError(RuntimeError):
    """A checkpoint or training state that is missing or unreadable where one is expected."""


def write_synced(path: Path, data: bytes) -> None:
    """Write `path` and return once its bytes are on disk."""
    with Path(path).open("wb") as f:
        f.write(data)
        f.flush()
        os.fsync(f.fileno())


def write_atomic(path: Path, data: bytes) -> None:
    """Write `path` so that a reader (or a crash) sees the old content or the new, never a part."""
    path = Path(path)
    tmp = path.with_name(path.name + ".partial")
    write_synced(tmp, data)
    os.replace(tmp, path)


PLAIN = (torch.Tensor, str, int, float, bool, type(None))  # what `torch.load(weights_only=True)` reads back


def _check_plain(value: object, where: str) -> None:
    if isinstance(value, dict):
        for key, item in value.items():
            _check_plain(key, where)
            _check_plain(item, f"{where}[{key!r}]")
    elif isinstance(value, list | tuple):
        for i, item in enumerate(value):
            _check_plain(item, f"{where}[{i}]")
    elif not isinstance(value, PLAIN):
        raise TypeError(f"a training state holds tensors and plain numbers only; {where} is a {type(value).__name__}")


def save_state(state: dict, path: Path) -> None:
    """`torch.save`, atomically, of tensors and plain values only: what `load_state` reads back
    (checked here, so that a run finds out now rather than when it resumes)."""
    _check_plain(state, "state")
    buffer = io.BytesIO()
    torch.save(state, buffer)
    write_atomic(path, buffer.getvalue())


def load_state(path: Path, device: torch.device | str = "cpu") -> dict:
    """A training state saved by `save_state`; a clear `CheckpointError` if it cannot be read.

    Loaded with `weights_only=True`: a run folder someone else gave you resumes without
    running any code its pickle names."""
    path = Path(path)
    if not path.is_file():
        raise CheckpointError(f"training state {path} is missing")
    try:
        return torch.load(path, map_location=device, weights_only=True)
    except Exception as error:  # torch raises RuntimeError, EOFError, UnpicklingError... on a torn file
        if isinstance(error, pickle.UnpicklingError) and "Weights only load failed" in str(error):
            raise CheckpointError(
                f"training state {path} holds more than tensors and plain numbers; it is not loaded, since that "
                "could run code: move its folder away to start that run over"
            ) from None
        raise CheckpointError(
            f"cannot read training state {path} ({type(error).__name__}: {str(error).splitlines()[0]}); "
            "it is damaged: move its folder away to start that run over"
        ) from None


COMPLETE_MARK = "training_state.pt"  # written last: a checkpoint folder holding it is complete


def staging_folder(folder: Path) -> Path:
    """Where `swap_in` expects the next version of `folder` to be written (emptied first)."""
    tmp = folder.with_name(folder.name + ".tmp")
    shutil.rmtree(tmp, ignore_errors=True)
    return tmp


def swap_in(folder: Path) -> None:
    """Replace `folder` by its complete staging folder. A crash at any point leaves a state
    `recover` turns into one complete checkpoint: `folder`, `folder.tmp` or `folder.old`."""
    tmp, old = folder.with_name(folder.name + ".tmp"), folder.with_name(folder.name + ".old")
    if not (tmp / COMPLETE_MARK).exists():
        raise CheckpointError(f"{tmp} is incomplete (no {COMPLETE_MARK}); not swapping it in")
    shutil.rmtree(old, ignore_errors=True)  # a leftover of a crash after an earlier swap
    if folder.exists():
        folder.rename(old)
    tmp.rename(folder)
    shutil.rmtree(old, ignore_errors=True)


def recover(folder: Path) -> bool:
    """Repair what a crash in `swap_in` left; True if `folder` is then a complete checkpoint.

    Newest first: a complete `folder`, else a complete `folder.tmp` (the crash came between
    the two renames), else `folder.old` (the crash came before `folder.tmp` was complete).
    """
    tmp, old = folder.with_name(folder.name + ".tmp"), folder.with_name(folder.name + ".old")
    if not (folder / COMPLETE_MARK).exists():
        for candidate in (tmp, old):
            if (candidate / COMPLETE_MARK).exists():
                shutil.rmtree(folder, ignore_errors=True)
                candidate.rename(folder)
                print(f"recovered the checkpoint {folder} from {candidate.name} (an earlier run stopped mid-save)")
                break
    for leftover in (tmp, old):
        shutil.rmtree(leftover, ignore_errors=True)
    return (folder / COMPLETE_MARK).exists()


def append_rows(path: Path, columns: list[str], rows: list[dict]) -> None:
    new = not path.exists()
    with path.open("a", newline="") as f:
        writer = csv.DictWriter(f, columns)
        if new:
            writer.writeheader()
        writer.writerows(rows)


def last_logged_step(path: Path) -> int | None:
    """The largest `step` in a CSV log, None if there is no log or no row."""
    if not path.exists():
        return None
    with path.open() as f:
        steps = [int(row["step"]) for row in csv.DictReader(f)]
    return max(steps) if steps else None


def set_aside_rows_after(path: Path, step: int) -> int:
    """Move the rows a resumed run will write again (step > `step`) to `<name>.superseded.csv`,
    so the log reads as one run and no row is ever lost. Returns how many were moved."""
    if not path.exists():
        return 0
    with path.open() as f:
        reader = csv.DictReader(f)
        columns, rows = list(reader.fieldnames or []), list(reader)
    later = [r for r in rows if int(r["step"]) > step]
    if later:
        append_rows(path.with_suffix(".superseded.csv"), columns, later)
        kept = io.StringIO()
        writer = csv.DictWriter(kept, columns, lineterminator="\r\n")
        writer.writeheader()
        writer.writerows([r for r in rows if int(r["step"]) <= step])
        write_atomic(path, kept.getvalue().encode())
    return len(later)
