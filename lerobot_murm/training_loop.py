"""Stopping a long training run cleanly: Ctrl-C or SIGTERM finish the current step, the
trainer writes what it needs to resume, then raises `TrainingInterrupted`."""

from __future__ import annotations

import signal


class TrainingInterrupted(RuntimeError):
    """Raised after a stop request, once the state to resume from is written."""


class StopRequest:
    """While active, Ctrl-C / SIGTERM only set `requested`; the training loop checks it
    between steps (a step cut in half would leave nothing consistent to save)."""

    def __init__(self) -> None:
        self.requested = False

    def __enter__(self) -> StopRequest:
        self._old = {s: signal.signal(s, self._handle) for s in (signal.SIGINT, signal.SIGTERM)}
        return self

    def _handle(self, *_: object) -> None:
        self.requested = True

    def __exit__(self, *exc: object) -> None:
        for s, handler in self._old.items():
            signal.signal(s, handler)
