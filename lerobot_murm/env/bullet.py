"""PyBullet, imported and connected without the lines its C code prints.

pybullet prints `pybullet build time: ...` to stderr when it is imported and
`argv[0]=` to stdout when `BulletClient` connects (it passes an empty option
string, which pybullet echoes). Both come from C `printf`, below Python's
`sys.stdout`, so `contextlib.redirect_stdout` cannot catch them: the file
descriptors themselves are pointed at /dev/null for the length of those two calls
and restored right after. Every simulator is built through `connect()`, and this
module is imported before any other `lerobot_murm.env` module imports pybullet.
An env never closed would otherwise print "Exception ignored ... TypeError" at exit,
when pybullet's own clean-up finds the module half torn down.
"""

from __future__ import annotations

import ctypes
import os
import sys
from collections.abc import Iterator
from contextlib import contextmanager

_LIBC = ctypes.CDLL(None) if os.name == "posix" else None  # the C library the process runs on


@contextmanager
def native_output_silenced() -> Iterator[None]:
    """Send what C code writes to stdout and stderr to /dev/null inside the block.

    Python's buffers are flushed before, C's stdio buffers before the streams are
    restored, so nothing written outside the block is lost or held back. Python
    exceptions raised inside still propagate (and are printed) as usual.
    """
    for stream in (sys.stdout, sys.stderr):
        if stream is not None:
            stream.flush()
    try:
        saved = {fd: os.dup(fd) for fd in (1, 2)}
    except OSError:  # a closed stdout/stderr: nothing to silence
        yield
        return
    devnull = os.open(os.devnull, os.O_WRONLY)
    try:
        for fd in saved:
            os.dup2(devnull, fd)
        yield
    finally:
        if _LIBC is not None:
            _LIBC.fflush(None)
        for fd, copy in saved.items():
            os.dup2(copy, fd)
            os.close(copy)
        os.close(devnull)


with native_output_silenced():
    import pybullet
    from pybullet_utils.bullet_client import BulletClient


class QuietBulletClient(BulletClient):
    """A `BulletClient` that also disconnects silently when an env left open is collected at exit."""

    def __del__(self) -> None:
        try:  # noqa: SIM105  (not contextlib.suppress: at interpreter exit module globals may be None already)
            super().__del__()
        except Exception:  # at interpreter exit pybullet's module globals may be None already
            pass


def connect() -> BulletClient:
    """A headless (DIRECT) simulator client of its own."""
    with native_output_silenced():
        return QuietBulletClient(connection_mode=pybullet.DIRECT)
