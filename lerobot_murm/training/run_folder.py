"""A training run's folder: its checkpoints (written beside and swapped in, so a crash
leaves one complete checkpoint), the policies kept at chosen steps, and the summary of a
finished run. `train.py` drives the training; this module is what it leaves on disk.

Folder: `train_config.yaml`, `log.csv` (LOG_COLUMNS), `eval.csv` (EVAL_COLUMNS),
`sittings.csv` (SITTINGS_COLUMNS), `learning_curve.png`, `checkpoints/last/` (policy + `training_state.pt`),
`checkpoints/<step>/pretrained_model` (kept policies), `final_eval.json`.
"""

from __future__ import annotations

import csv
import json
import shutil
from datetime import UTC, datetime
from pathlib import Path
from typing import TYPE_CHECKING

import torch

from lerobot_murm.checkpointing import (
    COMPLETE_MARK,
    CheckpointError,
    append_rows,
    last_logged_step,
    load_state,
    recover,
    save_state,
    staging_folder,
    swap_in,
)
from lerobot_murm.policy.modeling_murm import MurmPolicy
from lerobot_murm.policy.precision import cpu_description
from lerobot_murm.policy.processor_murm import make_murm_pre_post_processors

if TYPE_CHECKING:
    from lerobot_murm.training.train import TrainConfig

LOG_COLUMNS = ["step", "value_loss", "critic_loss", "actor_loss", "q", "v", "reward", "adv_weight", "steps_per_s"]
EVAL_COLUMNS = ["step", "mask_p", "success_rate", "episodes", "seconds", "split", "mask_mode"]
SITTINGS_COLUMNS = ["step", "precision", "seeds_together", "machine", "started"]
SITTINGS_FILE = "sittings.csv"
DTYPE_NAMES = {torch.bfloat16: "bf16", torch.float32: "fp32"}


def record_sitting(run_dir: Path, step: int, dtype: torch.dtype, seeds_together: int, device: torch.device) -> None:
    """A row for a sitting that trains the run on from `step`: the dtype `precision: auto`
    resolved to on its machine, how many seeds it trains stacked with it (1: one after another,
    as on CPUs without native bf16) and the machine. A long run moves between machines, so its
    record says which part trained how."""
    machine = torch.cuda.get_device_name(device) if device.type == "cuda" else cpu_description()
    row = {
        "step": step,
        "precision": DTYPE_NAMES[dtype],
        "seeds_together": seeds_together,
        "machine": machine,
        "started": datetime.now(UTC).isoformat(timespec="seconds"),
    }
    append_rows(Path(run_dir) / SITTINGS_FILE, SITTINGS_COLUMNS, [row])


def read_sittings(run_dir: Path) -> list[dict]:
    """The run's sittings in order (`record_sitting`); [] for a run from before they were recorded."""
    path = Path(run_dir) / SITTINGS_FILE
    if not path.exists():
        return []
    with path.open(newline="") as f:
        return [
            row | {"step": int(row["step"]), "seeds_together": int(row["seeds_together"])} for row in csv.DictReader(f)
        ]


def save_checkpoint(
    folder: Path, policy: MurmPolicy, optimizer_state: dict, step: int, generator: torch.Generator, elapsed_s: float
) -> None:
    """Write the next `folder` beside it, then swap it in (`checkpointing.swap_in`): a crash at
    any point leaves one complete checkpoint, which the next run finds (`checkpointing.recover`)."""
    tmp = staging_folder(folder)
    pretrained = tmp / "pretrained_model"
    policy.save_pretrained(pretrained)
    preprocessor, postprocessor = make_murm_pre_post_processors(policy.config)
    preprocessor.save_pretrained(pretrained)
    postprocessor.save_pretrained(pretrained)
    state = {
        "step": step,
        "optimizer": optimizer_state,
        "generator": generator.get_state(),
        "torch_rng": torch.get_rng_state(),
        "policy": policy.state_dict(),
        "elapsed_s": elapsed_s,  # wall time of all sittings so far, so a resumed run reports its whole time
    }
    save_state(state, tmp / COMPLETE_MARK)
    swap_in(folder)


def resume_state(out: Path, last: Path, device: torch.device) -> dict | None:
    """The training state to resume from; None for a new run. A run that has logged steps
    but has no readable checkpoint is an error, never a silent restart over its logs."""
    if recover(last):
        return load_state(last / COMPLETE_MARK, device)
    logged = last_logged_step(out / "log.csv")
    if logged is not None or last.exists():
        raise CheckpointError(
            f"{out} holds an earlier run (logged to step {logged}) but no checkpoint to resume from "
            f"({last / COMPLETE_MARK} is missing); move {out} away or set another output_dir"
        )
    return None


def finished_summary(config: TrainConfig) -> dict | None:
    """The summary of a run finished for `config.steps`; None if it is to train (a run finished
    for fewer steps trains on, its evaluation at that step kept beside)."""
    finished = Path(config.output_dir) / "final_eval.json"
    if not finished.exists():
        return None
    summary = json.loads(finished.read_text())
    if summary["steps"] == config.steps:
        return summary
    if summary["steps"] > config.steps:
        raise CheckpointError(
            f"{config.output_dir} is trained to {summary['steps']} steps, more than the "
            f"{config.steps} asked; move it away or set another output_dir"
        )
    finished.rename(finished.with_name(f"final_eval_{summary['steps']}.json"))
    return None


def kept_policy(run_dir: Path, step: int) -> Path:
    """Where a run keeps its policy at `step` (`keep_every`)."""
    return Path(run_dir) / "checkpoints" / f"{step:06d}" / "pretrained_model"


def keep_policy(run_dir: Path, step: int) -> None:
    """A copy of the last checkpoint's policy as the policy at `step` (`keep_every`)."""
    kept = kept_policy(run_dir, step)
    if kept.exists():  # kept before a stop, at this very step
        return
    tmp = staging_folder(kept.parent)
    shutil.copytree(Path(run_dir) / "checkpoints" / "last" / "pretrained_model", tmp / kept.name)
    tmp.rename(kept.parent)  # whole or absent
