"""Updates replayed from a CUDA graph: on a GPU our step is ~100 small kernels whose launches
bound it (the GPU is 0-6 % busy, BENCHMARKS.md), and a graph launches them all at once.

The whole update is captured, sampling included: fixed shapes (one batch size), the
sampling generators registered with the graph (each replay draws the next batches, as
eager steps would), Adam `capturable`, no host synchronisation inside (the sampler never
checks a value, `iql_loss` returns its logged values as a tensor). Those values are summed
on the device, and `read` brings their mean back every `log_every` steps: the one sync.
Without a graph (CPU, or `cuda_graph: false`) the same object runs the updates eagerly.
"""

from __future__ import annotations

from collections.abc import Callable

import torch
from torch import Tensor


class CudaGraph:
    """One torch.cuda.CUDAGraph that replays the draws of `generators`."""

    def __init__(self, generators: list[torch.Generator]):
        self.graph = torch.cuda.CUDAGraph()
        for generator in generators:
            self.graph.register_generator_state(generator)

    def capture(self, fn: Callable[[], None]) -> None:
        with torch.cuda.graph(self.graph):
            fn()

    def replay(self) -> None:
        self.graph.replay()


def make_capturable(optimizer: torch.optim.Optimizer) -> None:
    """Adam steps inside a graph only with its step counts on the device (`capturable`)."""
    for group in optimizer.param_groups:
        group["capturable"] = True


class Updates:
    """Calls `update` (one whole update, returning its logged values on the device): eagerly,
    or with a `graph`, `warmup` times eagerly (on a side stream on CUDA, as capture needs:
    these are real updates) and then captured once and replayed."""

    def __init__(
        self,
        update: Callable[[], Tensor],
        graph: CudaGraph | None = None,
        warmup: int = 3,
        device: torch.device = torch.device("cpu"),
    ):
        self.update, self.graph, self.warmup, self.device = update, graph, warmup, device
        self.calls, self._pending = 0, 0
        self._sum: Tensor | None = None

    def _accumulate(self) -> None:
        logged = self.update()
        if self._sum is None:  # allocated by the first (eager) call: the captured graph adds into it
            self._sum = torch.zeros_like(logged)
        self._sum.add_(logged)

    def __call__(self) -> None:
        if self.graph is None:
            self._accumulate()
        elif self.calls < self.warmup:
            self._warm_up()
        else:
            if self.calls == self.warmup:
                self.graph.capture(self._accumulate)  # records the kernels; computes nothing
            self.graph.replay()
        self.calls += 1
        self._pending += 1

    def read(self) -> Tensor:
        """The mean logged values of the updates since the last read, on the host."""
        if self._sum is None or not self._pending:
            raise RuntimeError("no update since the last read")
        mean = (self._sum / self._pending).cpu()
        self._sum.zero_()
        self._pending = 0
        return mean

    def _warm_up(self) -> None:
        if self.device.type != "cuda":
            return self._accumulate()
        stream = torch.cuda.Stream(self.device)
        stream.wait_stream(torch.cuda.current_stream(self.device))
        with torch.cuda.stream(stream):
            self._accumulate()
        torch.cuda.current_stream(self.device).wait_stream(stream)
