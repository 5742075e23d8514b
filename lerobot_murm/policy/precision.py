"""Which precision IQL's matmuls run in: bfloat16 where it makes training faster.

Parameters, Adam's state, the output layers and every loss stay float32; only the matmuls
of the hidden layers (nearly all the FLOPs) run in bf16 under `torch.autocast`. On CPUs with
avx512_bf16 or AMX a bf16 matmul of our shapes is 2-3x faster than fp32 (BENCHMARKS.md);
without them torch emulates bf16 and it is slower, hence `auto` asks the hardware. On a
CUDA GPU our networks are too small to keep it busy: a step is bound by launching ~100 small
kernels, and autocast's casts add kernels, so bf16 trained 0.79-1.00x as fast as fp32 on an
H200 at batch 256 to 4096 (BENCHMARKS.md) and `auto` is fp32 there.

Under `lerobot-train`, accelerate wraps `policy.forward` in its own autocast only when the
policy config has a `dtype` field or `use_amp` is set; `MurmConfig` has neither by default,
and the context here is entered inside `forward`, so it decides either way (an inner
autocast overrides an outer one), and both trainers take the same path.
"""

from __future__ import annotations

import functools
import platform
from pathlib import Path

import torch

PRECISIONS = ("auto", "fp32", "bf16")
NATIVE_BF16_CPU_FLAGS = frozenset({"avx512_bf16", "amx_bf16"})


def cpu_has_native_bf16(cpuinfo: str | None = None) -> bool:
    """True when /proc/cpuinfo (or the given text) lists avx512_bf16 or amx_bf16.

    torch has no public query for this (`torch.backends.cpu.get_cpu_capability()` says
    "AVX512" on CPUs with and without bf16), so the kernel's flag list it is; a system
    without /proc (macOS, Windows) counts as without.
    """
    if cpuinfo is None:
        return _this_cpu_has_native_bf16()
    flags = {word for line in cpuinfo.splitlines() if line.startswith("flags") for word in line.split()}
    return bool(flags & NATIVE_BF16_CPU_FLAGS)


def cpu_description(cpuinfo: str | None = None) -> str:
    """The CPU as a run's record names it: its model name, family and model (a cloud CPU's
    name is often only its brand: "AMD EPYC" is Zen 3 without bf16 and Zen 4 with it), and
    whether it has native bf16, which decides what `precision: auto` trains in and how fast."""
    if cpuinfo is None:
        try:
            cpuinfo = Path("/proc/cpuinfo").read_text()
        except OSError:
            return platform.processor() or platform.machine()
    fields: dict[str, str] = {}
    for line in cpuinfo.splitlines():
        key, _, value = line.partition(":")
        fields.setdefault(key.strip(), value.strip())
    name = fields.get("model name") or platform.machine()
    has_family = {"cpu family", "model"} <= fields.keys()
    family = f", family {fields['cpu family']} model {fields['model']}" if has_family else ""
    return f"{name}{family}, {'native' if cpu_has_native_bf16(cpuinfo) else 'no native'} bf16"


@functools.cache
def _this_cpu_has_native_bf16() -> bool:
    try:
        return cpu_has_native_bf16(Path("/proc/cpuinfo").read_text())
    except OSError:
        return False


def resolve_precision(precision: str, device: torch.device) -> torch.dtype:
    """The matmul dtype for `precision` on `device`: `auto` is bf16 on CPUs with native bf16,
    float32 elsewhere (GPUs included: launch-bound at these widths, see the module doc)."""
    if precision not in PRECISIONS:
        raise ValueError(f"unknown precision {precision!r}; choose one of {list(PRECISIONS)}")
    if precision == "auto":
        return torch.bfloat16 if device.type == "cpu" and cpu_has_native_bf16() else torch.float32
    return torch.bfloat16 if precision == "bf16" else torch.float32


def matmul_precision(dtype: torch.dtype, device: torch.device) -> torch.autocast:
    """Autocast to bf16 when `dtype` is bf16; otherwise a disabled autocast, which also turns
    off any autocast a caller opened, so `fp32` means fp32. No cast cache on CUDA: a CUDA graph
    (training/cuda_graph.py) cannot capture one."""
    return torch.autocast(
        device.type, dtype=torch.bfloat16, enabled=dtype == torch.bfloat16, cache_enabled=device.type != "cuda"
    )


def compute_dtype(device: torch.device) -> torch.dtype:
    """The dtype matmuls run in here: the autocast dtype inside `matmul_precision`, else float32.
    Inputs cast to it once are not cast again by every layer that reads them."""
    return torch.get_autocast_dtype(device.type) if torch.is_autocast_enabled(device.type) else torch.float32


def fp32_output(forward):
    """Run an output layer's forward in float32 even under autocast: a sparse-reward return
    reaches hundreds, where bf16's 8-bit mantissa would round Q and V by whole units, the
    size of one TD step."""

    @functools.wraps(forward)
    def full_precision_forward(self: torch.nn.Module, x: torch.Tensor) -> torch.Tensor:
        with torch.autocast(x.device.type, enabled=False):
            return forward(self, x.float())

    return full_precision_forward
