"""Progress bars that also read well in a log file.

In a terminal, tqdm's bar redraws itself in place. Written to a file (`nohup murm reproduce
... > log`, a cluster job), the same bar is a carriage return every tenth of a second:
hours of training made megabytes of one unreadable line, with `--jobs 2` two bars
interleaved. There, `progress` prints the bar as one plain line a minute instead
(`MURM_PROGRESS_EVERY_S` sets the seconds; 0: a line at every update).
"""

from __future__ import annotations

import os
import sys
from typing import Any, TextIO

from tqdm import tqdm

LOG_EVERY_VARIABLE = "MURM_PROGRESS_EVERY_S"  # seconds between a log file's progress lines (default 60)


class LogLines(tqdm):
    """tqdm writing its bar as a whole line, at most once every `mininterval` seconds."""

    def display(self, msg: str | None = None, pos: int | None = None) -> bool:
        self.fp.write((msg or self.__str__()) + "\n")
        self.fp.flush()
        return True


def progress(*, file: TextIO | None = None, **kwargs: Any) -> tqdm:
    """A tqdm bar on `file` (stderr): in place on a terminal, else `LogLines`."""
    file = sys.stderr if file is None else file
    if getattr(file, "isatty", lambda: False)():
        return tqdm(file=file, **kwargs)
    return LogLines(file=file, mininterval=log_every_s(), miniters=1, ascii=True, **kwargs)


def log_every_s() -> float:
    """`MURM_PROGRESS_EVERY_S`, checked: a bad value is one clear line, not float()'s."""
    value = os.environ.get(LOG_EVERY_VARIABLE, "60")
    try:
        seconds = float(value)
    except ValueError:
        seconds = -1.0
    if not seconds >= 0:  # also NaN
        raise ValueError(f"{LOG_EVERY_VARIABLE} must be a number of seconds >= 0, got {value!r}")
    return seconds
