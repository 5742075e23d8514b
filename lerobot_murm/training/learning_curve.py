"""The learning-curve figure of a training run (paper Figures 5 and 6): success rate and losses."""

from __future__ import annotations

import csv
from pathlib import Path

from matplotlib.figure import Figure


def read_run_csv(path: Path) -> list[dict[str, float | str]]:
    """Rows of a run's CSV, numbers as floats (eval.csv's split and mask_mode stay text). A last
    line without its newline is a row the trainer is writing at this moment (`murm status`
    reads beside a running grid): left out, not misread."""
    if not path.exists():
        return []
    text = path.read_text()
    complete = text[: text.rfind("\n") + 1]
    return [
        {k: v if k in ("split", "mask_mode") else float(v) for k, v in row.items()}
        for row in csv.DictReader(complete.splitlines())
    ]


def validation_curve(eval_rows: list[dict]) -> list[dict]:
    """The learning curve: validation evaluations under the paper's masking (the test rows
    are for reporting only and are never plotted against training)."""
    return [
        r for r in eval_rows if r.get("split", "validation") == "validation" and r.get("mask_mode", "paper") == "paper"
    ]


def plot_learning_curve(run_dir: Path) -> Path:
    """Success rate per masking level over training steps, beside the three IQL losses."""
    run_dir = Path(run_dir)
    evals, logs = validation_curve(read_run_csv(run_dir / "eval.csv")), read_run_csv(run_dir / "log.csv")
    fig = Figure(figsize=(10, 3.6))
    ax_success, ax_loss = fig.subplots(1, 2)
    for mask_p in sorted({row["mask_p"] for row in evals}):
        rows = [r for r in evals if r["mask_p"] == mask_p]
        ax_success.plot(
            [r["step"] for r in rows],
            [100 * r["success_rate"] for r in rows],
            marker="o",
            label=f"masking {mask_p:.0%}",
        )
    ax_success.set(xlabel="gradient steps", ylabel="success rate (%)", ylim=(-2, 102), title="validation episodes")
    if evals:
        ax_success.legend()
    for key in ("value_loss", "critic_loss", "actor_loss"):
        ax_loss.plot([r["step"] for r in logs], [r[key] for r in logs], label=key)
    ax_loss.set(xlabel="gradient steps", yscale="symlog", title="IQL losses")
    if logs:
        ax_loss.legend()
    fig.suptitle(run_dir.name)
    fig.tight_layout()
    path = run_dir / "learning_curve.png"
    fig.savefig(path, dpi=100)
    return path
