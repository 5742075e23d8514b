"""`murm reproduce --config configs/reproduce/<name>.yaml`: demonstrations -> VQ-VAEs -> IQL -> tables.

The driver. Every artefact is built once and found again by name under `work_dir`
(`artifacts.py`: a dataset by its recipe, an encoder by its dataset, camera and steps, a
training run by its cell and seed; a latent cache by fingerprints); a half-finished run
resumes from its checkpoint. Each finished run writes a small JSON file under
`results/<name>/runs/`; a rerun skips those, so a long grid runs in as many sittings as it
takes, and a run another grid already finished with the same recipe on the very same
encoders is taken from there (`reuse.py`). Missing pieces are rebuilt deterministically from
their seeds, in stages (datasets, encoders, runs) whose jobs run side by side on an executor
(`executors.py`: this process, `--jobs N` local processes, or a Ray cluster).
"""

from __future__ import annotations

import io
import json
import time
from contextlib import ExitStack
from dataclasses import replace
from pathlib import Path

import draccus
import torch

from lerobot_murm.checkpointing import write_atomic
from lerobot_murm.checks import check_writable
from lerobot_murm.collection import CollectConfig
from lerobot_murm.collection.prefixes import finished_siblings, noise_donors
from lerobot_murm.collection.shards import collect_shard, is_complete, merge_shards, shard_ranges
from lerobot_murm.experiments.artifacts import (
    collect_config,
    current_encoders,
    encoder_dir,
    encoder_fingerprint,
    encoder_root,
    ensure_dataset,
    ensure_encoder,
    fetch_kept_encoders,
    keep_encoders,
    result_path,
    run_dir,
)
from lerobot_murm.experiments.best_views import CHOICES, choices_markdown, choose_views
from lerobot_murm.experiments.budget import budget_markdown, choose_budget
from lerobot_murm.experiments.configuration_reproduce import CellSpec, ReproduceConfig
from lerobot_murm.experiments.executors import SerialExecutor
from lerobot_murm.experiments.results import final_evaluations, grid_results, markdown_table, read_result, write_tables
from lerobot_murm.experiments.reuse import (
    ADOPTED,
    adopt_run,
    budget_recipe,
    finished_elsewhere,
    grid_so_far,
    kept_as_finished,
    ready_to_test,
    run_recipe,
    set_aside,
    stored_at,
)
from lerobot_murm.locking import exclusive
from lerobot_murm.policy.configuration_murm import MurmConfig
from lerobot_murm.policy.precision import cpu_description
from lerobot_murm.training.learning_curve import read_run_csv, validation_curve
from lerobot_murm.training.run_folder import read_sittings
from lerobot_murm.training.train import TrainConfig, test_kept, train_seeds
from lerobot_murm.vqvae.latent_distance import (
    epsilon_at_quantile,
    epsilon_on_paper_scale,
    paper_epsilon_on_our_scale,
    quantile_of_epsilon,
    read_statistics,
)


def cell_epsilon(cell: CellSpec, encoders: Path) -> list[float] | None:
    """The cell's per-camera epsilon on our encoders' scale; None: the policy's default
    (`murm encode`'s suggestion)."""
    if cell.paper_epsilon is not None:
        mapped = zip(cell.paper_epsilon, cell.cameras, strict=True)
        return [paper_epsilon_on_our_scale(value, read_statistics(encoders / c)) for value, c in mapped]
    if cell.epsilon_quantile is not None:
        mapped = zip(cell.epsilon_quantile, cell.cameras, strict=True)
        return [epsilon_at_quantile(quantile, read_statistics(encoders / c)) for quantile, c in mapped]
    return cell.epsilon


def epsilon_scales(epsilon: list[float], cameras: list[str], encoders: Path) -> dict:
    """Each camera's epsilon (ours) on the paper's scale and as the share of random frames
    that close to their goal: what REPORT.md labels a run's threshold by."""
    pairs = [(e, read_statistics(encoders / c)) for e, c in zip(epsilon, cameras, strict=True)]
    return {
        "epsilon_paper_scale": [_rounded(epsilon_on_paper_scale(e, stats)) for e, stats in pairs],
        "epsilon_quantile": [round(quantile_of_epsilon(e, stats), 4) for e, stats in pairs],
    }


def _rounded(value: float | None) -> float | None:
    return None if value is None else round(value, 4)


def train_config(
    config: ReproduceConfig, task: str, cell: CellSpec, seed: int, root: Path, encoders: Path, steps: int | None = None
) -> TrainConfig:
    """A run's TrainConfig (`steps`: a budget grid's current cap)."""
    policy = MurmConfig(
        method=cell.method,
        cameras=list(cell.cameras),
        encoder_dir=str(encoders),
        epsilon=cell_epsilon(cell, encoders),
        **cell.policy,
    )
    return TrainConfig(
        dataset=str(root),
        task=task,
        policy=policy,
        output_dir=str(run_dir(config, task, cell, seed)),
        cache_dir=str(Path(config.work_dir) / "latent_cache"),
        seed=seed,
        device=config.device,
        **config.train_settings(cell, steps),
    )


def hardware() -> str:
    """What a run trained on, for the run list: the CPU (with or without native bf16), torch
    threads and any GPU. Grids run over several sittings, not always on one kind of machine."""
    gpu = f", {torch.cuda.get_device_name()}" if torch.cuda.is_available() else ""
    return f"{cpu_description()}, {torch.get_num_threads()} torch threads{gpu}"


def train_run(
    config: ReproduceConfig, task: str, cell: CellSpec, seeds: list[int], steps: int | None = None
) -> list[dict]:
    """The training runs of a cell's `seeds` and their final evaluations (each resumed from its
    checkpoint, or read back when finished), side by side as one stacked model when there are
    several (`murm train` with seeds); their results, for the driver to store. `steps`: a
    budget grid's current cap (its runs end with validation episodes only)."""
    root = ensure_dataset(collect_config(config, task, cell))
    encoders_from = ensure_dataset(collect_config(config, task))
    encoders = encoder_dir(config, encoders_from)
    for camera in cell.cameras:
        ensure_encoder(config, encoders_from, camera)
    start = time.perf_counter()
    # waits where a retried Ray task finds its first try's lock still held (an NFS lease, locking.py)
    with ExitStack() as locks:
        for seed in seeds:
            locks.enter_context(exclusive(run_dir(config, task, cell, seed), wait=True))
        configs = [train_config(config, task, cell, seed, root, encoders, steps) for seed in seeds]
        if steps is not None and not config.timed:  # a budget grid's run may have trained in another grid
            for c in configs:
                adopt_run(c, Path(config.work_dir) / "runs", config.name)
        summaries = train_seeds(configs)
    return [run_result(config, task, cell, root, encoders, summary, start) for summary in summaries]


def test_run(
    config: ReproduceConfig, task: str, cell: CellSpec, seeds: list[int], budget: int, curves: list[dict]
) -> list[dict]:
    """A budget grid's runs of a cell, tested once at `budget` from the policies they kept
    there; their results (the training's wall time and curve from `curves`, to the cap)."""
    root = ensure_dataset(collect_config(config, task, cell))
    encoders = encoder_dir(config, ensure_dataset(collect_config(config, task)))
    configs = [train_config(config, task, cell, seed, root, encoders) for seed in seeds]
    results = []
    for summary, trained in zip(test_kept(configs, budget), curves, strict=True):
        result = run_result(config, task, cell, root, encoders, summary | {"wall_s": trained["wall_s"]}, 0.0)
        results.append(
            result
            | {
                "curve": trained["curve"],
                "budget": budget,
                "trained_to": trained["steps"],
                "recipe": budget_recipe(result["recipe"], budget),
            }
        )
    return results


def run_result(
    config: ReproduceConfig, task: str, cell: CellSpec, root: Path, encoders: Path, summary: dict, start: float
) -> dict:
    """A finished run's result file, from its summary and its folder."""
    seed = summary["seed"]
    recipe = run_recipe(config, task, cell, seed)
    out = Path(summary["checkpoint"]).parents[2]
    epsilon = json.loads((Path(summary["checkpoint"]) / "config.json").read_text())["epsilon"]
    result = {
        "experiment": config.name,
        "task": task,
        "cell": cell.label,
        "method": cell.method,
        "cameras": cell.cameras,
        "seed": seed,
        "dataset": root.name,
        "steps": summary["steps"],
        "final": summary["final"],
        "final_validation": summary["final_validation"],
        "epsilon": epsilon,
        **epsilon_scales(epsilon, cell.cameras, encoders),
        "encoders": {camera: encoder_fingerprint(encoders / camera) for camera in cell.cameras},
        "validation_seeds": summary["validation_seeds"],
        "eval_seeds": summary["eval_seeds"],
        "demonstration_success": _demonstration_success(root),
        # the training run's own wall time over all its sittings (older runs: this call's)
        "wall_s": summary.get("wall_s", round(time.perf_counter() - start, 1)),
        "train_steps_per_s": _median_steps_per_s(out / "log.csv"),
        "hardware": hardware(),
        # each sitting's start, precision and machine: a long run moves between machines
        "sittings": read_sittings(out),
        "curve": _read_curve(out / "eval.csv"),
        "recipe": recipe,
        # trained side by side with this many seeds (their shared wall time and steps/s above)
        "seeds_together": summary.get("seeds_together", 1),
    }
    if (adopted := out / ADOPTED).exists():  # started from another grid's run: its part of wall_s
        result["adopted_from"] = json.loads(adopted.read_text())
    return result


def _store(path: Path, result: dict) -> dict:
    """A finished run's result file, written atomically: a hard stop leaves the old file or
    the new one, never half of one."""
    path.parent.mkdir(parents=True, exist_ok=True)
    write_atomic(path, (json.dumps(result, indent=1) + "\n").encode())
    return result


def _read_curve(path: Path) -> list[list[float]]:
    """[step, mask_p, success_rate] of the validation evaluations (the learning curve)."""
    rows = validation_curve(read_run_csv(path))
    return [[r["step"], r["mask_p"], r["success_rate"]] for r in rows]


def _demonstration_success(root: Path) -> float:
    """The share of the dataset's demonstrations that reached the goal (0-1)."""
    return json.loads((root / "meta" / "murm_collection.json").read_text())["success_rate"]


def _median_steps_per_s(path: Path) -> float:
    rates = sorted(float(line.split(",")[-1]) for line in path.read_text().splitlines()[1:])
    return round(rates[len(rates) // 2], 1) if rates else 0.0


def build_datasets(executor, collections: list[CollectConfig], workers: int) -> None:
    """Collect the unfinished datasets: the all-clean and all-noisy ones first, then those
    with some noisy demonstrations, which copy their episodes from the first (donors.py)."""
    unfinished = [c for c in collections if not is_complete(c)]
    mixed = [c for c in unfinished if 0 < c.noisy_fraction < 1]
    _build_datasets(executor, [c for c in unfinished if c not in mixed], workers)
    _build_datasets(executor, mixed, workers)


def _build_datasets(executor, unfinished: list[CollectConfig], workers: int) -> None:
    """In shards merged afterwards where the executor shards (a dataset half-collected in one
    piece, or one copied from noise donors, is built in one piece), else whole. Of several
    collections of one recipe (Table 7's 250 ... 3000 demonstrations) only the largest is
    simulated, carrying on a finished smaller one where there is one (not when sharded); the
    others are then cut from it (`prefixes.py`)."""
    largest = {}  # of several collections of one recipe only the largest is simulated, the rest are cut from it
    for c in sorted(unfinished, key=lambda c: -c.episodes):
        largest.setdefault(c.recipe, c)
    todo = list(largest.values())
    sharded = {
        c.root: shard_ranges(c.episodes, executor.shard_episodes)
        for c in todo
        if executor.shard_episodes
        and not c.root.exists()
        and not noise_donors(c)
        and not any(n >= c.episodes for n in finished_siblings(c))
    }
    _run_all(executor, ensure_dataset, [(c,) for c in todo if c.root not in sharded], cpus=workers, gpus=0)
    shards = [(c, episodes) for c in todo if c.root in sharded for episodes in sharded[c.root]]
    _run_all(executor, collect_shard, shards, cpus=1, gpus=0)
    _run_all(executor, merge_shards, [(c, sharded[c.root]) for c in todo if c.root in sharded], cpus=1, gpus=0)
    _run_all(executor, ensure_dataset, [(c,) for c in unfinished if c not in todo], cpus=1, gpus=0)


def build_encoders(executor, config: ReproduceConfig, encoders: list[tuple[Path, str]]) -> None:
    """The grid's encoders: the kept ones copied in, the missing ones trained side by side, each
    kept beside the results as soon as its job finishes. A driver stopped in this stage (the
    end of a sitting, a failed job) loses no finished encoder: on a fresh machine the next
    sitting copies it back instead of training another draw."""
    fetch_kept_encoders(config, encoders)
    for (_, root, camera), _ in executor.map(ensure_encoder, [(config, root, camera) for root, camera in encoders]):
        keep_encoders(config, [(root, camera)])


def build_stages(executor, shipped: ReproduceConfig, todo: list[tuple]) -> None:
    """The datasets and encoders the runs `todo` ((config, task, cell, seed)) need: each
    cell's own dataset and its task's default one, whose encoders every cell uses."""
    needed = {
        c.root: c
        for _, task, cell, _ in todo
        for c in (collect_config(shipped, task, cell), collect_config(shipped, task))
    }
    build_datasets(executor, list(needed.values()), shipped.collection.workers)
    build_encoders(
        executor,
        shipped,
        sorted({(encoder_root(shipped, task), camera) for _, task, cell, _ in todo for camera in cell.cameras}),
    )


def remaining_time(elapsed_s: float, finished: int, left: int) -> str:
    """'; N runs left, about T' at this sitting's pace so far (runs side by side included)."""
    if not left:
        return ""
    hours = elapsed_s / finished * left / 3600
    runs = f"{left} run{'s' if left > 1 else ''} left"
    return f"; {runs}, about {hours:.1f} h" if hours >= 1 else f"; {runs}, about {max(hours * 60, 1):.0f} min"


def training_jobs(todo: list[tuple], together: bool) -> list[tuple]:
    """The runs to train as jobs: each cell's seeds in one job, trained side by side, or each
    seed its own job."""
    if not together:
        return [(shipped, task, cell, [seed]) for shipped, task, cell, seed in todo]
    cells: dict[tuple[str, str], tuple] = {}
    for shipped, task, cell, seed in todo:
        cells.setdefault((task, cell.label), (shipped, task, cell, []))[3].append(seed)
    return list(cells.values())


def _run_all(executor, fn, jobs: list[tuple], **resources) -> None:
    for _ in executor.map(fn, jobs, **resources):
        pass


def reproduce(config: ReproduceConfig, executor=None) -> Path:
    """Run the grid's unfinished runs on `executor` (default: one after another in this
    process): datasets, then encoders, then training runs, each stage's jobs side by side."""
    executor = executor or SerialExecutor()
    if config.timed and not isinstance(executor, SerialExecutor):
        print(f"{config.name} times its runs: they train one at a time in this process")
        executor = SerialExecutor()  # the one given stays its owner's to close
    for folder in (config.work_dir, config.results_dir):
        check_writable(Path(folder))
    config, choices, waiting = choose_views(config)
    if waiting:
        label, why = next(iter(waiting.items()))
        raise ValueError(f"cell {label} takes its cameras from another grid's results: {why}")
    out = Path(config.results_dir) / config.name
    with exclusive(out):  # one driver per grid; its jobs lock what they build in the work dir
        if choices:
            out.mkdir(parents=True, exist_ok=True)
            print(choices_markdown(choices), end="")
            write_atomic(out / CHOICES, (json.dumps(choices, indent=1) + "\n").encode())
        return _run_grid(config, executor, out)


def _run_budget_grid(
    config: ReproduceConfig,
    shipped: ReproduceConfig,
    executor,
    out: Path,
    grid_record: ReproduceConfig,
    grid: list[tuple],
) -> Path:
    """A budget grid (`budget`): every run to the cap on validation episodes, the cap doubled
    while a mean curve still rises at it, the budget chosen by the rule (budget.json,
    budget.md), then every run tested once at the budget (runs/)."""
    spec, curves_dir = config.budget, out / "curves"
    decision_file = out / "budget.json"
    # a later sitting starts at the cap an earlier one had reached
    cap = max(spec.cap, json.loads(decision_file.read_text())["cap"] if decision_file.exists() else 0)
    while True:
        todo = []
        for task, cell, seed in grid:
            curve = curves_dir / result_path(config, task, cell, seed).name
            if not stored_at(curve, run_recipe(config, task, cell, seed), cap):
                todo.append((shipped, task, cell, seed))
            elif not ready_to_test(config, task, cell, seed, cap):
                print(f"{curve.name}: curve stored to {cap:,}, its kept policies not in this work dir: trained again")
                todo.append((shipped, task, cell, seed))
        build_stages(executor, shipped, todo)
        # a timed grid (Table 1) trains each seed alone, one at a time: its time per update is a result
        jobs = [job + (cap,) for job in training_jobs(todo, together=config.stack_seeds and not config.timed)]
        started, finished = time.perf_counter(), 0
        for (_, task, cell, seeds, _), results in executor.map(train_run, jobs):
            for seed, result in zip(seeds, results, strict=True):
                finished += 1
                _store(curves_dir / result_path(config, task, cell, seed).name, result)
                print(
                    f"[{finished}/{len(todo)}] {task} {cell.label} seed {seed}: trained to {cap:,} updates "
                    f"(validation only)"
                    + remaining_time(time.perf_counter() - started, finished, len(todo) - finished),
                    flush=True,
                )
        curves = {
            (task, cell.label, seed): read_result(curves_dir / result_path(config, task, cell, seed).name)
            for task, cell, seed in grid
        }
        decision = choose_budget(spec, list(curves.values()), cap, len(config.seeds))
        write_atomic(decision_file, (json.dumps(decision, indent=1) + "\n").encode())
        write_atomic(out / "budget.md", budget_markdown(decision).encode())
        if decision["flat"] or cap >= spec.max_cap:
            break
        cap = min(2 * cap, spec.max_cap)
        print(f"{config.name}: a mean validation curve still rises at the cap; training every run on to {cap:,}")
    budget = decision["budget"]
    print(f"{config.name}: budget {budget:,} updates (budget.md); testing every run there", flush=True)
    todo = [
        (shipped, task, cell, seed)
        for task, cell, seed in grid
        if not stored_at(
            result_path(config, task, cell, seed), budget_recipe(run_recipe(config, task, cell, seed), budget), budget
        )
    ]
    jobs = [
        (*job, budget, [curves[(job[1], job[2].label, seed)] for seed in job[3]])
        for job in training_jobs(todo, together=True)
    ]
    for (_, task, cell, seeds, _, _), results in executor.map(test_run, jobs):
        for seed, result in zip(seeds, results, strict=True):
            _store(result_path(config, task, cell, seed), result)
    rows = write_tables(grid_record, grid_results(grid_record, out / "runs"), out)
    print(markdown_table(rows))
    return out


def _run_grid(config: ReproduceConfig, executor, out: Path) -> Path:
    out.mkdir(parents=True, exist_ok=True)
    grid_record = grid_so_far(config, out / "config.yaml")
    record = io.StringIO()
    draccus.dump(grid_record, record)
    write_atomic(out / "config.yaml", record.getvalue().encode())
    # jobs may run on other machines, in another working directory: absolute paths
    shipped = replace(config, work_dir=str(Path(config.work_dir).resolve()))
    grid = [(task, cell, seed) for task in config.tasks for cell in config.cells for seed in config.seeds]
    if config.budget is not None:
        return _run_budget_grid(config, shipped, executor, out, grid_record, grid)
    todo = []
    for task, cell, seed in grid:
        path, recipe = result_path(config, task, cell, seed), run_recipe(config, task, cell, seed)
        if path.exists():
            stored = read_result(path)
            if stored is not None and kept_as_finished(stored.get("recipe"), recipe):
                continue
            why = "it does not read (torn)" if stored is None else "its cell changed since it ran"
            print(
                f"{path.name}: {why} (set aside in {set_aside(path).parent}); "
                "it trains again, from its checkpoint where the change allows",
                flush=True,
            )
        reused = (
            None
            if config.timed
            else finished_elsewhere(
                config, recipe, list(cell.eval_mask_p), current_encoders(config, task, cell.cameras)
            )
        )
        if reused is not None:
            _store(path, reused | {"experiment": config.name, "cell": cell.label})
        else:
            todo.append((shipped, task, cell, seed))
    build_stages(executor, shipped, todo)
    if config.prepare_only:
        print(f"{config.name}: datasets and encoders ready; no run trained (prepare_only)", flush=True)
        return out
    started, finished = time.perf_counter(), 0
    jobs = training_jobs(todo, together=config.stack_seeds and not config.timed)
    for (_, task, cell, seeds), results in executor.map(train_run, jobs):
        for seed, result in zip(seeds, results, strict=True):
            finished += 1
            _store(result_path(config, task, cell, seed), result)
            print(
                f"[{len(grid) - len(todo) + finished}/{len(grid)}] {task} {cell.label} seed {seed}: "
                + ", ".join(
                    f"masking {r['mask_p']:.0%} {100 * r['success_rate']:.0f} %"
                    for r in final_evaluations(result, config.report_split)
                )
                + f" ({config.report_split})"
                + remaining_time(time.perf_counter() - started, finished, len(todo) - finished),
                flush=True,
            )
    rows = write_tables(grid_record, grid_results(grid_record, out / "runs"), out)
    print(markdown_table(rows))
    return out
