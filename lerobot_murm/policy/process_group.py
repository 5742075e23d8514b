"""An orderly end for the process group of a multi-process `lerobot-train` on CPUs (gloo).

`accelerate launch --multi_gpu --num_processes 2 lerobot-train --policy.type=murm` left a rank
alive for good after "End of training" in 3 of 10 runs (benchmarks/bench_accelerate_exit.py).
LeRobot's `train()` ends with `accelerator.wait_for_everyone()` (a gloo barrier) and
`accelerator.end_training()`, which unregisters the default process group; the last reference
to the group is then DDP's `Reducer`, freed when `train()` returns. py-spy of the hung rank:
the main thread, holding the GIL, is in `~ProcessGroupGloo` (freeing the Reducer) waiting for
the group's worker threads, while a worker thread is still destroying the barrier's work, which
holds the last all-reduce's tensors, and waits for the GIL to drop their Python objects.

The policy keeps a reference to the group from its construction until the interpreter exits,
so `train()`'s return frees nothing. At exit the group is destroyed if no one did it, the GIL is
let go long enough for every worker thread to finish what it was freeing, and only then is the
last reference dropped: the destructor finds idle workers and returns.
"""

from __future__ import annotations

import atexit
import time

import torch.distributed as dist

_kept: list = []
WORKERS_SETTLE_S = 0.2


def keep_process_group_until_exit() -> None:
    """Call where a policy is built; a no-op outside torch.distributed, and idempotent."""
    if _kept or not (dist.is_available() and dist.is_initialized()):
        return
    _kept.append(dist.distributed_c10d._get_default_group())
    atexit.register(release_process_group)


def release_process_group() -> None:
    """Destroy the default group unless someone did, then drop it once its workers are idle."""
    if not _kept:
        return
    if dist.is_initialized():
        dist.destroy_process_group()
    time.sleep(WORKERS_SETTLE_S)  # releases the GIL: gloo's threads finish freeing their last work
    _kept.clear()
