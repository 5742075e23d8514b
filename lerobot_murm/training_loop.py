"""The step loop both trainers share (`murm train`, `murm train-vqvae`).

It counts steps from where a resumed run stopped, shows progress, keeps the wall time of
all sittings of a run, and stops cleanly: Ctrl-C or SIGTERM finish the current step (a
step cut in half would leave nothing consistent to save); the trainer then writes what it
needs to resume and raises `TrainingInterrupted`. What a step is, and what is saved, stays
with each trainer.
"""

from __future__ import annotations

import signal
import time

from lerobot_murm.progress import progress


class TrainingInterrupted(RuntimeError):
    """Raised after a stop request, once the state to resume from is written."""


class StopRequest:
    """While active, Ctrl-C / SIGTERM only set `requested`; the loop checks it between steps."""

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


class TrainingLoop:
    """Steps `start`..`total` of a run whose earlier sittings took `earlier_s` seconds; the
    clock of this sitting starts when the loop is made.

        loop = TrainingLoop(total, start=step, earlier_s=elapsed_so_far, desc="murm train")
        with loop:
            while loop.running():
                ...one update...
                loop.advance()
                if loop.every(checkpoint_every) and not loop.finished:
                    save(loop.step, loop.elapsed())
        if loop.interrupted:
            save(loop.step, loop.elapsed()); raise TrainingInterrupted(...)
    """

    def __init__(self, total: int, start: int = 0, earlier_s: float = 0.0, desc: str = "train") -> None:
        self.total, self.first, self.step = total, start, start
        self.desc = desc
        self._earlier_s = earlier_s
        self._started = time.perf_counter()
        self._ended: float | None = None
        self._stop = StopRequest()

    def __enter__(self) -> TrainingLoop:
        self._entered = time.perf_counter()
        self._stop.__enter__()
        self._progress = progress(total=self.total, initial=self.step, desc=self.desc, unit="step")
        return self

    def __exit__(self, *exc: object) -> None:
        self._ended = time.perf_counter()
        self._progress.close()
        self._stop.__exit__(*exc)

    def running(self) -> bool:
        """True while steps are left and no stop was requested."""
        return self.step < self.total and not self._stop.requested

    def advance(self) -> None:
        """Count one finished step."""
        self.step += 1
        self._progress.update()

    def every(self, period: int) -> bool:
        return self.step % period == 0

    def show(self, **values: object) -> None:
        """Figures beside the progress bar (losses, success)."""
        self._progress.set_postfix(refresh=False, **values)

    @property
    def stop_requested(self) -> bool:
        """A stop was asked for (work between steps, such as an evaluation, may end early)."""
        return self._stop.requested

    @property
    def finished(self) -> bool:
        return self.step >= self.total

    @property
    def interrupted(self) -> bool:
        return not self.finished

    def elapsed(self) -> float:
        """Wall seconds of all sittings so far, this one up to now."""
        return self._earlier_s + time.perf_counter() - self._started

    def steps_per_s(self) -> float:
        """Steps of this sitting per second inside the loop (the setup before it not counted)."""
        looped_s = (self._ended or time.perf_counter()) - self._entered
        return (self.step - self.first) / max(looped_s, 1e-9)
