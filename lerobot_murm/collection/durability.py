"""What a collection has safely on disk, and how to get back to it after a hard stop.

LeRobot's writer keeps the current data and `meta/episodes` parquet files open until
`finalize()` (a file only gets its footer, and becomes readable, when closed) and rewrites
`info.json` and `stats.json` in place after every episode. `murm collect` therefore
flushes every few episodes: `finalize()`, then a snapshot of the files that now exist and
of the two JSON files' text, written last and atomically with the collection summary, then a
fresh writer (`LeRobotDataset.resume`, which starts new files). After kill -9 or a full
disk, `restore` deletes whatever was written after the last snapshot (torn or not) and
puts the JSON files back: the dataset is then exactly what it was at that flush.
"""

from __future__ import annotations

from pathlib import Path

from lerobot_murm.checkpointing import write_atomic

REWRITTEN = ("meta/info.json", "meta/stats.json")  # rewritten after every episode
WRITTEN_ONCE = ("data", "meta")  # every other file below these is written once and closed


class UnrepairableCollection(RuntimeError):
    """A file that was safely written has changed since: nothing to restore to."""


def _written_once(root: Path, summary_file: str) -> dict[str, int]:
    files = {}
    for folder in WRITTEN_ONCE:
        for path in sorted((root / folder).rglob("*")):
            relative = path.relative_to(root).as_posix()
            if path.is_file() and relative not in REWRITTEN and not relative.startswith(summary_file):
                files[relative] = path.stat().st_size
    return files


def snapshot(root: Path, summary_file: str) -> dict:
    """The dataset's files after a `finalize()`: sizes of the closed ones, content of the JSON ones."""
    rewritten = {name: (root / name).read_text() if (root / name).exists() else None for name in REWRITTEN}
    return {"files": _written_once(root, summary_file), "rewritten": rewritten}


def restore(root: Path, saved: dict, summary_file: str) -> int:
    """Bring `root` back to `saved`; returns the number of files removed (written after it)."""
    files = _written_once(root, summary_file)
    changed = [name for name, size in saved["files"].items() if files.get(name) != size]
    if changed:
        raise UnrepairableCollection(f"cannot repair {root}: {changed[0]} is missing or changed since it was saved")
    later = [name for name in files if name not in saved["files"]]
    for name in later:
        (root / name).unlink()
    for name, content in saved["rewritten"].items():
        if content is None:
            (root / name).unlink(missing_ok=True)
        else:
            write_atomic(root / name, content.encode())
    return len(later)
