"""REPORT.md: each finished grid's table beside the paper's, with configuration, hardware
and wall time of every run. Built from `results/*/` alone, so it can be regenerated any
time (`murm report`), which also refreshes the README's results tables (between
`<!-- results:NAME -->` and `<!-- /results:NAME -->`) and its claims list (`<!-- claims -->`)."""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
from matplotlib.figure import Figure

from lerobot_murm.experiments.best_views import CHOICES, choices_markdown
from lerobot_murm.experiments.claims import claims_table, goal_source_table
from lerobot_murm.experiments.configuration_reproduce import load_reproduce_config
from lerobot_murm.experiments.flattening import flattening_table
from lerobot_murm.experiments.paper import PAPER_TABLES, TABLE1_TIME, TABLE2_SPREAD, TABLE5, TASKS
from lerobot_murm.experiments.results import (
    final_evaluations,
    grid_results,
    read_table,
    seed_curves,
    stored_results,
    success_text,
    write_tables,
)


def _row_keys(rows: list[dict]) -> list[tuple[str, float]]:
    """The (cell, masking) rows of a grid's table, in its order."""
    return list(dict.fromkeys((r["cell"], float(r["mask_p"])) for r in rows))


def grid_tasks(results: Path) -> tuple[str, ...]:
    """The tasks a grid runs (its config.yaml), in the paper's order: its tables' columns."""
    if not (results / "config.yaml").exists():
        return TASKS
    tasks = load_reproduce_config(results / "config.yaml").tasks
    return tuple(t for t in TASKS if t in tasks)


def _per_task(
    name: str, rows: list[dict], tasks: tuple[str, ...]
) -> dict[tuple[str, float], list[tuple[dict | None, float | None]]]:
    """Per (cell, masking) row, the paper's rows first: for each task our table row (None:
    not run yet) and the paper's value (None: none)."""
    ours = {(r["cell"], float(r["mask_p"]), r["task"]): r for r in rows}
    paper = PAPER_TABLES.get(name, {})
    keys = list(paper) + [k for k in _row_keys(rows) if k not in paper]
    return {
        (cell, mask_p): [
            (ours.get((cell, mask_p, task)), paper.get((cell, mask_p), (None,) * len(TASKS))[TASKS.index(task)])
            for task in tasks
        ]
        for cell, mask_p in keys
    }


def comparison(name: str, rows: list[dict], tasks: tuple[str, ...] = TASKS, earlier: list[dict] | None = None) -> str:
    """Ours beside the paper's, per (cell, masking) row and task; '-' where not run yet. A
    grid of our own (no paper table) has no paper columns. `earlier`: study v1's rows of the
    same table (`results/v1/NAME.csv`), shown in their own column where they differ from ours."""
    with_paper = name in PAPER_TABLES
    v1 = {(r["cell"], float(r["mask_p"]), r["task"]): float(r["success_mean"]) for r in earlier or []}
    ours = {(r["cell"], float(r["mask_p"]), r["task"]): float(r["success_mean"]) for r in rows}
    with_v1 = any(v1.get(key, value) != value for key, value in ours.items())
    columns = ["ours"] + (["v1"] if with_v1 else []) + (["paper"] if with_paper else [])
    lines = [
        "| cell | masking | "
        + " | ".join(f"{t}: {' | '.join(columns)}" if len(columns) > 1 else t for t in tasks)
        + " |",
        "|---|---:|" + "---:|" * len(columns) * len(tasks),
    ]
    for (cell, mask_p), per_task in _per_task(name, rows, tasks).items():
        cells = []
        for task, (r, value) in zip(tasks, per_task, strict=True):
            cells.append(f"{success_text(r)} (n={r['seeds']})" if r else "-")
            if with_v1:
                earlier_value = v1.get((cell, mask_p, task))
                cells.append("" if earlier_value is None else f"{earlier_value:.1f}")
            if with_paper:
                cells.append("" if value is None else f"{value:.1f}")
        lines.append(f"| {cell} | {mask_p:.0%} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def plot_against_paper(name: str, rows: list[dict], tasks: tuple[str, ...], path: Path) -> bool:
    """`vs_paper.png`: per task and row (the paper's rows first, then ours it has no value
    for), our mean with the sample std over seeds as error bar beside the paper's value;
    False (nothing drawn) for a grid of our own or if nothing has run."""
    per_task = _per_task(name, rows, tasks)
    drawn = [t for i, t in enumerate(tasks) if any(values[i][0] for values in per_task.values())]
    if name not in PAPER_TABLES or not drawn:
        return False
    labels = [
        f"{cell}, masking {mask_p:.0%}" if mask_p and "authors'" not in cell else cell for cell, mask_p in per_task
    ]
    fig = Figure(figsize=(4.2 * len(drawn) + 3.5, 0.45 * len(labels) + 1.4))
    axes = fig.subplots(1, len(drawn), squeeze=False, sharey=True)
    y = np.arange(len(labels))
    for ax, task in zip(axes[0], drawn, strict=True):
        column = [values[tasks.index(task)] for values in per_task.values()]
        ours = [float(r["success_mean"]) if r else np.nan for r, _ in column]
        spread = [float(r["success_std"]) if r and r["success_std"] not in ("", None) else 0.0 for r, _ in column]
        paper = [np.nan if value is None else value for _, value in column]
        ax.barh(
            y - 0.2,
            ours,
            0.4,
            xerr=spread,
            color="tab:blue",
            label="ours (mean ± sample std over seeds)",
            error_kw={"elinewidth": 1, "capsize": 2},
        )
        ax.barh(y + 0.2, paper, 0.4, color="tab:gray", label="paper")
        for k, (r, _) in enumerate(column):
            at = 1 if r is None else ours[k] + spread[k] + 1
            ax.text(at, k - 0.2, "not run yet" if r is None else f"n={r['seeds']}", va="center", fontsize=7)
        ax.set(title=task, xlabel="success rate (%, test episodes)", xlim=(0, 100))
    axes[0, 0].set_yticks(y, labels, fontsize=8)
    axes[0, 0].invert_yaxis()
    handles, legend = axes[0, 0].get_legend_handles_labels()
    fig.legend(handles, legend, loc="lower center", ncol=2, fontsize=8, frameon=False)
    fig.tight_layout(rect=(0, 1.0 / (len(labels) + 3), 1, 1))
    fig.savefig(path, dpi=110, bbox_inches="tight")
    return True


def time_table(runs: list[dict], paper: dict[str, float], base_cell: str | None = None) -> str:
    """Table 5 (and Table 1's time column): each cell's time per update relative to
    `base_cell` (default: the task's first cell, the single-view baseline), from the runs'
    median training steps/s (evaluation excluded). A run is compared only with the base
    runs of its own machine (`hardware`): a grid may finish in sittings on different CPUs,
    and a ratio across them would measure the CPUs."""
    base_cells: dict[str, str] = {}
    for r in runs:
        base_cells.setdefault(r["task"], base_cell or r["cell"])
    base: dict[tuple[str, str], list[float]] = {}
    for r in runs:
        if r["cell"] == base_cells[r["task"]]:
            base.setdefault((r["task"], r["hardware"]), []).append(float(r["train_steps_per_s"]))
    cells: dict[tuple[str, str], list[dict]] = {}
    for r in runs:
        cells.setdefault((r["task"], r["cell"]), []).append(r)
    against = base_cell or "first cell"
    lines = [
        f"| task | cell | training steps/s | time per update vs. {against} (same machine) | runs | machines | paper |",
        "|---|---|---:|---:|---:|---:|---:|",
    ]
    for (task, cell), members in cells.items():
        ratios = [
            float(np.mean(base[(task, r["hardware"])])) / float(r["train_steps_per_s"])
            for r in members
            if (task, r["hardware"]) in base
        ]
        steps = float(np.mean([float(r["train_steps_per_s"]) for r in members]))
        value = paper.get(cell)
        lines.append(
            f"| {task} | {cell} | {steps:.1f} | {f'{np.mean(ratios):.2f}' if ratios else '-'} | "
            f"{len(members)} | {len({r['hardware'] for r in members})} | "
            f"{'' if value is None else f'{value:.2f}'} |"
        )
    return "\n".join(lines) + "\n"


def sweeps_epsilon(results: Path) -> bool:
    """Whether a grid's cells set the reward threshold (Table 2): its report says on which scale."""
    if not (results / "config.yaml").exists():
        return False
    cells = load_reproduce_config(results / "config.yaml").cells
    return any(c.epsilon is not None or c.paper_epsilon is not None or c.epsilon_quantile is not None for c in cells)


def epsilon_table(results: Path) -> str:
    """The epsilon each cell ran at, on our encoders' scale, on the paper's (mapped) and as a
    quantile of frame-to-goal distances, so that nobody reads the paper's value as ours."""
    lines = [
        "| task | cell | epsilon, ours | on the paper's scale | quantile of frame-to-goal distances |",
        "|---|---|---:|---:|---:|",
    ]
    runs = {}
    for r in stored_results(results / "runs"):
        runs.setdefault((r["task"], r["cell"]), r)  # every seed runs at the same epsilon (one encoder)
    for (task, cell), r in runs.items():
        paper, quantile = r.get("epsilon_paper_scale"), r.get("epsilon_quantile")
        lines.append(f"| {task} | {cell} | {_values(r['epsilon'])} | {_values(paper)} | {_values(quantile)} |")
    note = (
        "Epsilon is a threshold on the squared latent distance ||z - z_goal||^2 (eq. 4-5), so its value "
        "depends on the encoder. The paper's epsilons are on its own encoders' scale; a cell named "
        "`paper-epsX` ran at X mapped to ours: X / 2.0 (the paper's chosen value) times the epsilon "
        "`murm encode` suggests for our encoder (`paper_epsilon_on_our_scale` in "
        "lerobot_murm/vqvae/latent_distance.py). The quantile is the share of random frames closer "
        "to their goal than that epsilon ('-': a run from before these were recorded)."
    )
    return "\n".join(lines) + f"\n\n{note}\n"


def training_spread(results: Path, paper: dict[str, float]) -> str:
    """Table 2's second row: per cell, the mean over the learning curve's evaluations of the
    sample std over seeds of the success rate (unmasked, validation episodes), in points."""
    runs = stored_results(results / "runs")
    lines = ["| task | cell | mean std during training (points) | seeds | paper |", "|---|---|---:|---:|---:|"]
    for (task, cell, mask_p), seeds in seed_curves(runs).items():
        if mask_p != 0.0:
            continue
        steps = sorted(set.intersection(*(set(s) for s in seeds)))
        spread = (
            f"{np.mean([np.std([s[step] for s in seeds], ddof=1) for step in steps]):.2f}" if len(seeds) > 1 else "-"
        )
        value = paper.get(cell)
        lines.append(f"| {task} | {cell} | {spread} | {len(seeds)} | {'' if value is None else f'{value:.2f}'} |")
    return "\n".join(lines) + "\n"


def _values(values: list[float] | None) -> str:
    return "-" if values is None else ", ".join("-" if v is None else f"{v:.3g}" for v in values)


def precision_text(run: dict) -> str:
    """'bf16' / 'fp32': the dtype the run trained in, by its sittings where it recorded them
    ('bf16, fp32 from 60,000' for a run that moved to a machine without native bf16), else as
    its recipe records it."""
    changes = []  # (first step, dtype) where the dtype changed
    for sitting in run.get("sittings") or []:
        if not changes or changes[-1][1] != sitting["precision"]:
            changes.append((sitting["step"], sitting["precision"]))
    if changes:
        return ", ".join([changes[0][1]] + [f"{dtype} from {step:,}" for step, dtype in changes[1:]])
    dtype = (run.get("recipe") or {}).get("precision")
    return {"torch.bfloat16": "bf16", "torch.float32": "fp32"}.get(dtype, dtype or "-")


def encoders_text(run: dict) -> str:
    """The fingerprints of the encoders a run trained on ('-': a run from before they were
    recorded), so that a reader sees which draw of the encoders each run had."""
    encoders = run.get("encoders") or {}
    return ", ".join(f"{camera} {fingerprint[:8]}" for camera, fingerprint in encoders.items()) or "-"


def run_list(results: Path, split: str = "test") -> str:
    """One line per run, with its final success on the grid's reported `split`, then the machine
    time the grid itself spent (reused runs were paid for by the grid that trained them)."""
    lines = [
        f"| task | cell | seed | steps | final success, {split} (masking: %) | wall | train steps/s | hardware "
        "| precision | encoders |",
        "|---|---|---:|---:|---|---:|---:|---|---|---|",
    ]
    trained, seconds = 0, 0.0
    for r in stored_results(results / "runs"):
        adopted = r.get("adopted_from")
        if "reused_from" not in r:  # seeds side by side share one wall time; an adopted run's start was paid before
            paid = r["wall_s"] - (adopted["wall_s"] if adopted else 0.0)
            trained, seconds = trained + 1, seconds + paid / r.get("seeds_together", 1)
        finals = ", ".join(f"{f['mask_p']:.0%}: {100 * f['success_rate']:.0f}" for f in final_evaluations(r, split))
        wall = f"{r['wall_s'] / 60:.1f} min" + (f" (the run of {r['reused_from']})" if "reused_from" in r else "")
        if adopted:
            wall += f" (from step {adopted['step']:,} of {'/'.join(Path(adopted['from']).parts[-4:])})"
        lines.append(
            f"| {r['task']} | {r['cell']} | {r['seed']} | {r['steps']} | {finals} | "
            f"{wall} | {r['train_steps_per_s']} | {r['hardware']} | {precision_text(r)} | "
            f"{encoders_text(r)} |"
        )
    return "\n".join(lines) + (
        f"\n\nMachine time of the runs this grid trained ({trained}; seeds trained side by side counted once, "
        f"runs started from another grid's from there): {seconds / 3600:.1f} h.\n"
    )


def refresh_tables(results: Path) -> None:
    """Rebuild a grid's tables and curves from its run files (a sitting stopped part-way
    leaves finished runs that its tables do not have yet)."""
    if (results / "config.yaml").exists() and any((results / "runs").glob("*.json")):
        config = load_reproduce_config(results / "config.yaml")
        write_tables(config, grid_results(config, results / "runs"), results)


def write_report(results_dir: Path, path: Path, preface: str = "") -> Path:
    results_dir, path = Path(results_dir).resolve(), Path(path).resolve()
    sections = [preface] if preface else []
    for results in sorted(results_dir.iterdir()):
        refresh_tables(results)
    sections.append(f"## Which of the paper's claims hold here\n\n{claims_table(results_dir)}")
    for results in sorted(results_dir.iterdir()):
        if not (results / "table.csv").exists():
            continue
        rows = read_table(results / "table.csv")
        where = results.relative_to(path.parent) if results.is_relative_to(path.parent) else results
        beside = "; the paper's value beside ours" if results.name in PAPER_TABLES else ""
        config = load_reproduce_config(results / "config.yaml")
        split = config.report_split
        runs = grid_results(config, results / "runs")
        against_paper = plot_against_paper(results.name, rows, grid_tasks(results), results / "vs_paper.png")
        sections.append(
            f"## {results.name}\n\nSuccess rate (%), mean ± sample std (ddof 1) over training seeds "
            f"(n = seeds finished; a single seed has none), {rows[0]['episodes_per_seed']} {split} episodes per seed "
            f"and masking level{beside}. "
            f"Configuration: [`{where / 'config.yaml'}`]({where / 'config.yaml'}).\n\n"
            + comparison(
                results.name,
                rows,
                grid_tasks(results),
                read_table(v1) if (v1 := results_dir / "v1" / f"{results.name}.csv").exists() else None,
            )
            + (f"\n![ours beside the paper]({where / 'vs_paper.png'})\n" if against_paper else "")
            + (
                f"\nHindsight goals against the rendered goal images, the same cell and masking level "
                f"(clearly better or worse: by more than two standard errors of the difference; the rule "
                f"in the protocol above):\n\n{goals}"
                if (goals := goal_source_table(results_dir, results.name))
                else ""
            )
            + (f"\nTraining time (Table 5):\n\n{time_table(runs, TABLE5)}" if results.name == "table5" else "")
            + (
                f"\nTraining time (Table 1's time column):\n\n{time_table(runs, TABLE1_TIME, 'single-global-128')}"
                if results.name == "table1"
                else ""
            )
            + (f"\nReward threshold of each cell:\n\n{epsilon_table(results)}" if sweeps_epsilon(results) else "")
            + (
                f"\nSpread over seeds during training (Table 2's second row; validation episodes of the learning "
                f"curve):\n\n{training_spread(results, TABLE2_SPREAD)}"
                if results.name == "table2"
                else ""
            )
            + f"\n![learning curves]({where / 'curves.png'})\n\n"
            + (
                f"Where each validation curve flattens (the first evaluation that no later one beats by more "
                f"than two standard errors; `lerobot_murm/experiments/flattening.py`):\n\n"
                f"{flattening_table(runs, config.train.eval_episodes)}\n"
                if config.choose_updates
                else ""
            )
            + (
                f"The table's one budget, chosen on the seeds' mean validation curves before any test episode "
                f"(`lerobot_murm/experiments/budget.py`):\n\n{budget.read_text().strip()}\n\n"
                if (budget := results / "budget.md").exists()
                else ""
            )
            + (
                f"Cells whose cameras another grid chose (`lerobot_murm/experiments/best_views.py`):\n\n"
                f"{choices_markdown(json.loads(chosen.read_text()))}\n"
                if (chosen := results / CHOICES).exists()
                else ""
            )
            + (f"{discussion.read_text().strip()}\n\n" if (discussion := results / "discussion.md").exists() else "")
            + "Runs:\n\n"
            + run_list(results, split)
        )
    path.write_text("\n".join(sections))
    return path


def compact_table(name: str, rows: list[dict], tasks: tuple[str, ...] = TASKS) -> str:
    """Mean ± std over seeds per (cell, masking) and task, the paper's value in brackets."""
    seeds = sorted({int(r["seeds"]) for r in rows})
    lines = [f"| cell | masking | {' | '.join(tasks)} |", "|---|---:|" + "---:|" * len(tasks)]
    per_task = _per_task(name, rows, tasks)
    for cell, mask_p in _row_keys(rows):
        texts = []
        for r, value in per_task[cell, mask_p]:
            text = "-" if r is None else success_text(r, digits=0)
            texts.append(text if value is None else f"{text} ({value:.1f})")
        lines.append(f"| {cell} | {mask_p:.0%} | " + " | ".join(texts) + " |")
    count = f"{seeds[0]}" if len(seeds) == 1 else f"{seeds[0]} to {seeds[-1]}"
    plural = "s" if seeds[-1] > 1 else ""
    note = (
        f"Each value averages {count} training seed{plural} (sample std over them, ddof 1; test episodes); "
        "the paper's value in brackets."
    )
    return "\n".join(lines) + f"\n\n{note}\n"


def update_readme(results_dir: Path, readme: Path) -> list[str]:
    """Refill each `<!-- results:NAME -->` block of the README from results/NAME/table.csv,
    and the `<!-- claims -->` block with the claims' verdicts; returns the blocks refilled."""
    text, filled = readme.read_text(), []

    def refill(match: re.Match) -> str:
        name = match.group(1)
        grid = Path(results_dir) / name
        if not (grid / "table.csv").exists():
            return match.group(0)
        filled.append(name)
        table = compact_table(name, read_table(grid / "table.csv"), grid_tasks(grid))
        return f"<!-- results:{name} -->\n{table}<!-- /results:{name} -->"

    text = re.sub(r"<!-- results:(\w+) -->.*?<!-- /results:\1 -->", refill, text, flags=re.S)
    if "<!-- claims -->" in text:
        filled.append("claims")
        text = re.sub(
            r"<!-- claims -->.*?<!-- /claims -->",
            lambda _: f"<!-- claims -->\n{claims_table(Path(results_dir), rules=False)}<!-- /claims -->",
            text,
            flags=re.S,
        )
    readme.write_text(text)
    return filled
