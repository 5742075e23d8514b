"""A grid's tables and figures from its per-run result files: mean and std over seeds.

`table.csv` (one row per task, cell and masking level), `table.md` (cells x tasks, as in
the paper's tables) and `curves.png` (success rate over training, mean and spread over
seeds, in the style of the paper's Figures 5 and 6).
"""

from __future__ import annotations

import csv
import json
from collections import defaultdict
from pathlib import Path

import numpy as np
from matplotlib import colormaps
from matplotlib.figure import Figure

COLUMNS = [
    "task",
    "cell",
    "method",
    "cameras",
    "mask_p",
    "success_mean",
    "success_std",
    "seeds",
    "episodes_per_seed",
    "steps",
    "wall_s_mean",
    "train_steps_per_s",
]


def final_evaluations(result: dict, split: str) -> list[dict]:
    """A run's final evaluations on the `split` episodes: "test" for reported tables,
    "validation" for the grids that choose (whose test numbers nothing shows)."""
    return result["final" if split == "test" else "final_validation"]


def aggregate(results: list[dict], split: str = "test") -> list[dict]:
    """Mean and sample std over seeds per (task, cell, masking) of the final evaluations on
    the `split` episodes."""
    groups: dict[tuple, list[tuple[dict, dict]]] = defaultdict(list)
    for result in results:
        for final in final_evaluations(result, split):
            cell = result["cell"] + (", authors' masking" if final.get("mask_mode") == "authors" else "")
            groups[(result["task"], cell, final["mask_p"])].append((result, final))
    rows = []
    for (task, cell, mask_p), members in groups.items():
        rates = np.array([100 * final["success_rate"] for _, final in members])
        first = members[0][0]
        rows.append(
            {
                "task": task,
                "cell": cell,
                "method": first["method"],
                "cameras": "+".join(first["cameras"]),
                "mask_p": mask_p,
                "success_mean": round(float(rates.mean()), 2),
                "success_std": round(float(rates.std(ddof=1)), 2) if len(rates) > 1 else None,
                "seeds": len(members),
                "episodes_per_seed": members[0][1]["episodes"],
                "steps": first["steps"],
                "wall_s_mean": round(float(np.mean([r["wall_s"] for r, _ in members])), 1),
                "train_steps_per_s": round(float(np.mean([r["train_steps_per_s"] for r, _ in members])), 1),
            }
        )
    return rows


def read_result(path: Path) -> dict | None:
    """A run's result file; None where it does not read (torn by a crash before writes were
    atomic, or damaged since): the grid trains such a run again."""
    try:
        result = json.loads(Path(path).read_text())
    except (json.JSONDecodeError, UnicodeDecodeError):
        return None
    return result if isinstance(result, dict) else None


def stored_results(runs: Path) -> list[dict]:
    """The result files in `runs/`, in name order; one that does not read is left out, with a
    line that says so (`murm reproduce` sets it aside and trains that run again)."""
    results = []
    for path in sorted(Path(runs).glob("*.json")):
        result = read_result(path)
        if result is None:
            print(f"{path} does not read (torn?): left out; `murm reproduce` sets it aside and trains it again")
        else:
            results.append(result)
    return results


def read_table(path: Path) -> list[dict]:
    """A grid's table.csv, its rows as strings; one clear error if it is not one (torn, or
    written by something else)."""
    with Path(path).open(newline="") as f:
        reader = csv.DictReader(f)
        missing = [c for c in COLUMNS if c not in (reader.fieldnames or [])]
        if missing:
            raise ValueError(
                f"{path} is not a grid table ({len(missing)} of its {len(COLUMNS)} columns missing, "
                f"'{missing[0]}' first); delete it and run `murm report` again to rebuild it from its "
                "runs"
            )
        return list(reader)


def success_text(row: dict, digits: int = 1) -> str:
    """'mean ± std' over seeds; one seed has no sample std (ddof 1), so none is shown. Works
    on rows as `aggregate` makes them and as read back from table.csv (strings)."""
    mean = f"{float(row['success_mean']):.{digits}f}"
    return f"{mean} ± {float(row['success_std']):.{digits}f}" if int(row["seeds"]) > 1 else mean


def markdown_table(rows: list[dict]) -> str:
    tasks = list(dict.fromkeys(r["task"] for r in rows))
    lines = ["| cell | masking | " + " | ".join(tasks) + " |", "|---|---:|" + "---:|" * len(tasks)]
    for cell, mask_p in dict.fromkeys((r["cell"], r["mask_p"]) for r in rows):
        cells = []
        for task in tasks:
            match = [r for r in rows if (r["task"], r["cell"], r["mask_p"]) == (task, cell, mask_p)]
            cells.append(success_text(match[0]) if match else "-")
        lines.append(f"| {cell} | {mask_p:.0%} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def seed_curves(results: list[dict]) -> dict[tuple[str, str, float], list[dict[float, float]]]:
    """Each (task, cell, masking)'s learning curves: one {step: success %} per seed."""
    curves: dict[tuple[str, str, float], list[dict[float, float]]] = defaultdict(list)
    for result in results:
        by_mask: dict[float, dict[float, float]] = defaultdict(dict)
        for step, mask_p, rate in result["curve"]:
            by_mask[mask_p][step] = 100 * rate
        for mask_p, points in by_mask.items():
            curves[(result["task"], result["cell"], mask_p)].append(points)
    return curves


def plot_curves(results: list[dict], path: Path) -> None:
    tasks = list(dict.fromkeys(r["task"] for r in results))
    cells = list(dict.fromkeys(r["cell"] for r in results))
    curves = seed_curves(results)
    fig = Figure(figsize=(5 * len(tasks) + 2, 4.8))
    axes = fig.subplots(1, len(tasks), squeeze=False)
    for ax, task in zip(axes[0], tasks, strict=True):
        for (curve_task, cell, mask_p), seeds in curves.items():  # colour: cell; line style: masking
            if curve_task != task:
                continue
            steps = sorted(set.intersection(*(set(s) for s in seeds)))
            values = np.array([[s[step] for step in steps] for s in seeds])
            label = f"{cell}" + (f", masking {mask_p:.0%}" if mask_p else "")
            color = colormaps["tab10"](cells.index(cell) % 10)
            style = "-" if mask_p == 0 else (":" if mask_p < 0.3 else "--")
            ax.plot(steps, values.mean(0), style, color=color, marker="o", markersize=3, label=label)
            ax.fill_between(steps, values.min(0), values.max(0), color=color, alpha=0.15)
        for budget in sorted({r["budget"] for r in results if r["task"] == task and "budget" in r}):
            ax.axvline(budget, color="grey", linestyle="-.", linewidth=1, label=f"the table's budget ({budget:,})")
        ax.set(title=task, xlabel="gradient steps", ylabel="success rate (%)", ylim=(-2, 102))
    handles, labels = axes[0, 0].get_legend_handles_labels()
    ncol = 3 if len(tasks) > 1 else 2  # one narrow panel: long labels in two columns
    fig.legend(handles, labels, loc="lower center", ncol=ncol, fontsize=7, frameon=False)
    fig.tight_layout(rect=(0, 0.06 + 0.035 * -(-len(labels) // ncol), 1, 1))
    fig.savefig(path, dpi=110, bbox_inches="tight")  # never crop a long legend label


def write_tables(config, results: list[dict], out: Path) -> list[dict]:
    rows = aggregate(results, config.report_split)
    with (out / "table.csv").open("w", newline="") as f:
        writer = csv.DictWriter(f, COLUMNS)
        writer.writeheader()
        writer.writerows(rows)
    table = markdown_table(rows)
    seeds = ", ".join(str(s) for s in sorted({r["seed"] for r in results}))
    header = (
        f"# {config.name}\n\nSuccess rate (%), mean ± sample std (ddof 1) over training seeds {seeds}; "
        f"{rows[0]['episodes_per_seed']} {config.report_split} episodes per seed and masking level.\n\n"
    )
    (out / "table.md").write_text(header + table)
    plot_curves(results, out / "curves.png")
    return rows


def grid_results(config, runs: Path) -> list[dict]:
    """Every finished run in `runs/`, earlier sittings' included, in the grid's task and
    cell order: the tables always cover everything finished so far."""
    grid = [(task, cell.label) for task in config.tasks for cell in config.cells]
    order = {key: i for i, key in enumerate(grid)}
    return sorted(stored_results(runs), key=lambda r: (order.get((r["task"], r["cell"]), len(order)), r["seed"]))
