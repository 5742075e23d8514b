"""One writer per output folder: an exclusive OS file lock that dies with its process.

`murm collect`, `train`, `train-vqvae`, `encode` and `reproduce` hold `exclusive(folder)`
on what they write, and so do the jobs of `murm reproduce` (local or Ray tasks) on the
datasets, encoders and runs they build in the work dir. Two writers of one folder used to
interleave their files (a corrupt parquet file, every log row twice); now the second fails
at once with `FolderInUse`, naming the folder and the holder's PID, or, for a job that
needs the artefact another job is building, waits for it. Readers take no lock.

The lock is `flock` on a hidden file beside the folder, `.NAME.lock`, not inside it: a
collection is built beside its folder and renamed into place, and `--overwrite` deletes
the folder. The kernel drops the lock when its process dies, kill -9 included, so there is
never a stale lock to remove by hand; the file itself is removed on release, and one a kill
left behind is harmless (it is locked anew, its content only names the last holder).
Children forked while a lock is held (evaluation workers) close their copy of it at once:
flock belongs to the open file, so an orphaned child would otherwise keep it locked.

On NFS, Linux implements flock with POSIX byte-range locks, which are in the protocol of
NFSv4 and work across clients (a client that dies holds its locks until its lease expires,
90 s by default). On NFSv3 they need the NLM side protocol: they work across clients only
where lockd and statd run on the clients and the server; with the `nolock` mount option
they are local to each client, and two nodes can then write one folder. Lustre supports
them when mounted with `-o flock`; s3fs and gcsfuse do not lock across machines. Where the
filesystem refuses locks altogether, commands run unlocked after a note saying so.
"""

from __future__ import annotations

import errno
import fcntl
import os
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

NO_LOCKS = (errno.ENOLCK, errno.ENOSYS, errno.EOPNOTSUPP)  # a filesystem without flock


class FolderInUse(RuntimeError):
    """Another process holds the lock of a folder this one is to write."""


_held: dict[Path, tuple[int | None, int]] = {}  # lock file -> (descriptor, depth) of this process's locks


def lock_file(folder: Path) -> Path:
    """The file whose lock guards `folder` (symlinks resolved: one folder, one lock)."""
    folder = Path(folder).resolve()
    return folder.with_name(f".{folder.name}.lock")


@contextmanager
def exclusive(folder: Path, wait: bool = False) -> Iterator[None]:
    """Hold `folder`'s lock for the block. Taken again by its holder, it is simply kept (a
    `murm reproduce` job that builds a dataset calls `collect`, which locks it too). Held by
    another process: `FolderInUse` at once, or with `wait` (a job needing an artefact
    another job is making) a note and a wait until it is free."""
    path = lock_file(folder)
    descriptor, depth = _held[path] if path in _held else (_acquire(path, Path(folder), wait), 0)
    _held[path] = (descriptor, depth + 1)
    owner = os.getpid()
    try:
        yield
    finally:
        if os.getpid() == owner:  # a forked child that unwinds this block holds nothing
            _release(path)


def _release(path: Path) -> None:
    descriptor, depth = _held.pop(path)
    if depth > 1:
        _held[path] = (descriptor, depth - 1)
    elif descriptor is not None:
        if _is_current(descriptor, path):  # removed before the lock goes: a waiter then tries a new file
            os.unlink(path)
        os.close(descriptor)


def _acquire(path: Path, folder: Path, wait: bool) -> int | None:
    path.parent.mkdir(parents=True, exist_ok=True)
    while True:
        descriptor = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            _lock(descriptor, path, folder, wait)
        except BaseException as error:
            os.close(descriptor)
            if isinstance(error, OSError) and error.errno in NO_LOCKS:
                print(f"note: the filesystem of {folder} has no file locks; nothing stops a second writer of it")
                return None
            raise
        if _is_current(descriptor, path):
            break
        os.close(descriptor)  # its holder removed it between our open and our lock: lock the new one
    os.ftruncate(descriptor, 0)
    os.write(descriptor, f"{os.getpid()}\n".encode())
    return descriptor


def _lock(descriptor: int, path: Path, folder: Path, wait: bool) -> None:
    try:
        fcntl.flock(descriptor, fcntl.LOCK_EX | fcntl.LOCK_NB)
        return
    except BlockingIOError:
        holder = os.pread(descriptor, 32, 0).decode(errors="replace").strip() or "unknown"
    if not wait:
        raise FolderInUse(f"{folder} is in use by another writer (PID {holder}); wait for it to finish or stop it")
    print(f"waiting for PID {holder} to finish writing {folder}", flush=True)
    fcntl.flock(descriptor, fcntl.LOCK_EX)


def _is_current(descriptor: int, path: Path) -> bool:
    """Whether the locked file is still the one at `path` (not one its last holder removed)."""
    try:
        on_disk = os.stat(path)
    except FileNotFoundError:
        return False
    held = os.fstat(descriptor)
    return (on_disk.st_dev, on_disk.st_ino) == (held.st_dev, held.st_ino)


def _close_in_child() -> None:
    """In a forked child: close the copies of the parent's lock files. Never unlock them
    (that would unlock the parent's too); the parent's locks stay its own."""
    for descriptor, _ in _held.values():
        if descriptor is not None:
            os.close(descriptor)
    _held.clear()


os.register_at_fork(after_in_child=_close_in_child)
