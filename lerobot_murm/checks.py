"""Checks a command runs on its inputs before its first expensive step."""

from __future__ import annotations

import os
from pathlib import Path


def check_writable(path: Path) -> None:
    """`path` is a folder we can write in, or can be created: else a one-line `PermissionError`
    (or `NotADirectoryError`) now rather than after minutes of work."""
    path = Path(path)
    if path.exists() and not path.is_dir():
        raise NotADirectoryError(f"{path} is a file, not a folder")
    existing = path
    while not existing.exists():
        existing = existing.parent
    if not existing.is_dir():
        raise NotADirectoryError(f"cannot create {path}: {existing} is a file, not a folder")
    if not os.access(existing, os.W_OK | os.X_OK):
        raise PermissionError(f"cannot write in {path}: {existing} is not writable")
