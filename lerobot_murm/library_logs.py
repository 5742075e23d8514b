"""LeRobot's and `datasets`' error logs, held back while a `murm` command runs.

A command that fails says so in one line on stderr (cli.py). These libraries log an error
and then raise it, or log it and go on: a torn parquet file made `datasets` print its
error twice (through its own handler and the root logger's) before our line. While
`held_back()` is active, their records of level ERROR and above are counted, not printed;
the command's last line says how many there were (`--debug` prints them as they come).
Lower levels go where they went before.
"""

from __future__ import annotations

import logging
from collections.abc import Iterator
from contextlib import contextmanager

LIBRARIES = ("lerobot", "datasets")


class HeldBack(logging.Handler):
    """Takes the place of the libraries' handlers: counts their errors, passes the rest on."""

    def __init__(self) -> None:
        super().__init__()
        self.errors = 0
        self.first: str | None = None
        self.passed_on: dict[str, tuple[list[logging.Handler], bool]] = {}  # library -> its handlers, propagate

    def emit(self, record: logging.LogRecord) -> None:
        if record.levelno >= logging.ERROR:
            self.errors += 1
            self.first = self.first or record.getMessage().splitlines()[0]
            return
        handlers, propagate = self.passed_on[record.name.split(".")[0]]
        for handler in handlers:
            if record.levelno >= handler.level:
                handler.handle(record)
        if propagate:
            logging.getLogger().callHandlers(record)


@contextmanager
def held_back() -> Iterator[HeldBack]:
    import datasets  # noqa: F401  (its import adds its handler: it must be there before this one takes over)

    held = HeldBack()
    loggers = [logging.getLogger(name) for name in LIBRARIES]
    for logger in loggers:
        held.passed_on[logger.name] = (logger.handlers, logger.propagate)
        logger.handlers, logger.propagate = [held], False
    try:
        yield held
    finally:
        for logger in loggers:
            logger.handlers, logger.propagate = held.passed_on[logger.name]
