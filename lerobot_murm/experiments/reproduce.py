"""`murm reproduce --config configs/reproduce/<name>.yaml`: demonstrations -> VQ-VAEs -> IQL -> tables.

Every artefact is built once and found again by name under `work_dir`: a dataset by its
recipe, an encoder by its dataset (each task's default collection: `encoder_root`), camera
and steps, a latent cache by fingerprints, a
training run by its cell and seed (a half-finished run resumes from its checkpoint).
Each finished run writes a small JSON file under `results/<name>/runs/`; a rerun skips
those, so a long grid runs in as many sittings as it takes. A run another grid already
finished with the same recipe (Table 3's global camera is Table 4's single-view
baseline) is taken from there instead of trained again, when it was trained on the very
same encoders: the encoders a grid trains are kept beside the results (`results/encoders/`,
committed), since a VQ-VAE trained again on another machine is another draw. Missing pieces are rebuilt
deterministically from their seeds, in stages (datasets, encoders, runs) whose jobs run
side by side on an executor (`executors.py`: this process, `--jobs N` local processes,
or a Ray cluster).
"""

from __future__ import annotations

import io
import json
import time
from contextlib import ExitStack
from dataclasses import asdict, replace
from pathlib import Path

import draccus
import torch

from lerobot_murm.checkpointing import write_atomic
from lerobot_murm.checks import check_writable
from lerobot_murm.collection import CollectConfig, collect
from lerobot_murm.collection.dataset import episode_successes
from lerobot_murm.collection.prefixes import cut_from_larger, finished_siblings, noise_donors, start_from_smaller
from lerobot_murm.collection.shards import collect_shard, is_complete, merge_shards, shard_ranges
from lerobot_murm.device import resolve_device
from lerobot_murm.env import CAMERA_NAMES
from lerobot_murm.env.murm_env import SCENE_VERSION
from lerobot_murm.experiments.budget import budget_markdown, choose_budget
from lerobot_murm.experiments.configuration_reproduce import CellSpec, ReproduceConfig, load_reproduce_config
from lerobot_murm.experiments.executors import SerialExecutor
from lerobot_murm.experiments.results import final_evaluations, grid_results, markdown_table, read_result, write_tables
from lerobot_murm.expert import default_noise_std
from lerobot_murm.locking import exclusive
from lerobot_murm.policy.configuration_murm import MurmConfig
from lerobot_murm.policy.precision import cpu_description, resolve_precision
from lerobot_murm.training.learning_curve import read_run_csv, validation_curve
from lerobot_murm.training.train import TrainConfig, test_kept, train_seeds
from lerobot_murm.vqvae import VQVAEConfig
from lerobot_murm.vqvae.configuration_vqvae import LATENT_DISTANCE_FILE
from lerobot_murm.vqvae.encoder_files import (
    CONFIG_FILE,
    METRICS_FILE,
    WEIGHTS_FILE,
    encoder_fingerprint as fingerprint,
    save_encoder_files,
)
from lerobot_murm.vqvae.latent_cache import build_latent_cache
from lerobot_murm.vqvae.latent_distance import (
    QUANTILE_KEY,
    distance_statistics,
    epsilon_at_quantile,
    epsilon_on_paper_scale,
    paper_epsilon_on_our_scale,
    quantile_of_epsilon,
    read_statistics,
    save_beside_encoder,
)
from lerobot_murm.vqvae.object_pixels import OBJECT_PIXELS_FILE, check_encoders
from lerobot_murm.vqvae.train import train_vqvae


def dataset_root(config: ReproduceConfig, task: str, cell: CellSpec | None = None) -> Path:
    """Where the cell's demonstrations live (no cell: the collection's default recipe)."""
    c = config.collection
    episodes, noisy = config.cell_episodes(cell), config.cell_noisy_fraction(cell)
    std = default_noise_std(task) if c.noise_std is None else c.noise_std
    name = f"{task}-scene{SCENE_VERSION}-{episodes}ep-std{std:g}-noisy{noisy:g}-seed{c.seed}-{c.image_size}px"
    return Path(config.work_dir) / "datasets" / name


def collect_config(config: ReproduceConfig, task: str, cell: CellSpec | None = None) -> CollectConfig:
    root = dataset_root(config, task, cell)
    c = config.collection
    return CollectConfig(
        task=task,
        root=root,
        episodes=config.cell_episodes(cell),
        workers=c.workers,
        cameras=CAMERA_NAMES,
        image_size=c.image_size,
        seed=c.seed,
        noise_std=c.noise_std,  # None: the task's std
        noisy_fraction=config.cell_noisy_fraction(cell),
    )


def ensure_dataset(collect_config: CollectConfig) -> Path:
    """The dataset: already there, cut from a finished larger collection of its recipe, or
    collected (carrying a finished smaller one on, or resuming whatever ran before, on
    whichever machine; copying the episodes the all-clean and all-noisy collections hold).
    A job that finds another building it waits for it (locking.py)."""
    root = collect_config.root
    if is_complete(collect_config):
        return root
    with exclusive(root, wait=True):
        if is_complete(collect_config) or (not root.exists() and cut_from_larger(collect_config)):
            return root
        collect_config = start_from_smaller(collect_config)
        collect(replace(collect_config, resume=root.exists()), donors=noise_donors(collect_config))
    return root


def encoder_is_finished(out: Path, steps: int) -> bool:
    """A checkpoint trained to the end for `steps` (an interrupted one is trained again)."""
    if not (out / METRICS_FILE).exists():
        return False
    metrics = json.loads((out / METRICS_FILE).read_text())
    return not metrics["interrupted"] and metrics["steps"] == steps


def encoder_steps(config: ReproduceConfig, camera: str) -> int:
    return config.vqvae.camera_steps.get(camera, config.vqvae.steps)


def encoder_dir(config: ReproduceConfig, root: Path) -> Path:
    return Path(config.work_dir) / "vqvae" / f"{root.name}-{config.vqvae.steps}steps"


def encoder_root(config: ReproduceConfig, task: str) -> Path:
    """The dataset a task's encoders learn from: the default collection, whatever the cell's
    demonstrations. The paper trains one VQ-VAE per camera once (4.2) and encodes every
    experiment's states and goals with it (4.3); Table 7 varies what the policy learns from,
    not the encoders."""
    return dataset_root(config, task)


# the files beside an encoder's weights and config, `metrics.json` (what `encoder_is_finished` reads) copied last
BESIDE_ENCODER = (LATENT_DISTANCE_FILE, OBJECT_PIXELS_FILE, METRICS_FILE)


def kept_encoder_dir(config: ReproduceConfig, root: Path) -> Path:
    """Where a grid keeps the encoders it trained, beside its results (committed): a later
    sitting on a fresh machine encodes with the very same weights. A VQ-VAE trained again on
    another CPU is another draw (its latents and suggested epsilon differ), which would make
    the cells of one table differ by more than their recipes."""
    return Path(config.results_dir) / "encoders" / encoder_dir(config, root).name


def copy_encoder(source: Path, target: Path) -> None:
    with exclusive(target, wait=True):
        save_encoder_files(target, (source / WEIGHTS_FILE).read_bytes(), (source / CONFIG_FILE).read_bytes())
        for name in BESIDE_ENCODER:
            if (source / name).exists():
                write_atomic(target / name, (source / name).read_bytes())


def encoder_fingerprint(folder: Path) -> str | None:
    """What a run records of an encoder: the first 16 hex digits of its weights' sha256; None
    where there is no encoder."""
    return fingerprint(folder)[:16] if (folder / WEIGHTS_FILE).exists() else None


def fetch_kept_encoders(config: ReproduceConfig, encoders: list[tuple[Path, str]]) -> None:
    """Into the work dir, each kept encoder that is not trained there (before `ensure_encoder`)."""
    for root, camera in encoders:
        out, kept = encoder_dir(config, root) / camera, kept_encoder_dir(config, root) / camera
        steps = encoder_steps(config, camera)
        if not encoder_is_finished(out, steps) and encoder_is_finished(kept, steps):
            copy_encoder(kept, out)


def keep_encoders(config: ReproduceConfig, encoders: list[tuple[Path, str]]) -> None:
    """Beside the results, each finished encoder of the work dir not kept there yet (a kept
    encoder is never replaced: the runs that record its fingerprint were trained on it)."""
    for root, camera in encoders:
        out, kept = encoder_dir(config, root) / camera, kept_encoder_dir(config, root) / camera
        steps = encoder_steps(config, camera)
        if encoder_is_finished(out, steps) and not encoder_is_finished(kept, steps):
            copy_encoder(out, kept)


def current_encoders(config: ReproduceConfig, task: str, cameras: list[str]) -> dict[str, str] | None:
    """The fingerprints of the encoders a run of `task` on `cameras` would encode with now
    (the work dir's, else the kept ones); None while one of them is yet to be trained."""
    root, found = encoder_root(config, task), {}
    for camera in cameras:
        trained = [
            folder / camera
            for folder in (encoder_dir(config, root), kept_encoder_dir(config, root))
            if encoder_is_finished(folder / camera, encoder_steps(config, camera))
        ]
        if not trained:
            return None
        found[camera] = encoder_fingerprint(trained[0])
    return found


def ensure_encoder(config: ReproduceConfig, root: Path, camera: str) -> Path:
    """A camera's VQ-VAE in `<encoder_dir>/<camera>`, with its epsilon statistics and its object
    check (`murm check-encoders`) beside it. A job that finds another making it waits for it
    (locking.py), then finishes what is left."""
    out = encoder_dir(config, root) / camera
    steps = encoder_steps(config, camera)
    checked = (out / OBJECT_PIXELS_FILE).exists() or not config.object_check_episodes
    if encoder_is_finished(out, steps) and _has_statistics(out) and checked:
        return out
    device = str(resolve_device(config.device))
    repo_id = f"local/{root.name}"
    with exclusive(out, wait=True):
        if not encoder_is_finished(out, steps):
            vq_config = replace(VQVAEConfig(), steps=steps, batch_size=config.vqvae.batch_size)
            train_vqvae(repo_id, root, camera, out, vq_config, device=device)
            (out / OBJECT_PIXELS_FILE).unlink(missing_ok=True)  # it was about the encoder trained before
        if not _has_statistics(out):
            cache = build_latent_cache(repo_id, root, out, Path(config.work_dir) / "latent_cache", device=device)
            save_beside_encoder(distance_statistics(cache, episode_successes(repo_id, root)), out)
        if not (out / OBJECT_PIXELS_FILE).exists() and config.object_check_episodes:
            try:
                check_encoders(repo_id, root, [out], config.object_check_episodes, device=device)
            except ValueError as error:  # a diagnostic: the grid goes on without it
                print(f"object check of {camera} skipped: {error}")
    return out


def _has_statistics(encoder: Path) -> bool:
    """`murm encode`'s epsilon statistics beside the encoder, of the current kind."""
    return (encoder / LATENT_DISTANCE_FILE).exists() and QUANTILE_KEY in read_statistics(encoder)


def run_dir(config: ReproduceConfig, task: str, cell: CellSpec, seed: int) -> Path:
    return Path(config.work_dir) / "runs" / config.name / task / cell.label / f"seed{seed}"


def result_path(config: ReproduceConfig, task: str, cell: CellSpec, seed: int) -> Path:
    return Path(config.results_dir) / config.name / "runs" / f"{task}__{cell.label}__seed{seed}.json"


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


def policy_overrides(method: str, cameras: list[str], policy: dict) -> dict:
    """The policy fields that differ from the method's defaults: a cell that spells a default
    out (Table 1's 128 units) trains the same run as one that leaves it out."""
    common = {"method": method, "cameras": list(cameras)}
    default, given = MurmConfig(**common), MurmConfig(**common, **policy)
    return {key: value for key, value in policy.items() if getattr(given, key) != getattr(default, key)}


def same_recipe(stored: dict | None, recipe: dict) -> bool:
    """Whether a stored run was trained by `recipe` (policies compared by what differs from
    their method's defaults, so that recipes stored before that rule still match)."""
    if stored is None:
        return False
    return stored | {"policy": policy_overrides(stored["method"], stored["cameras"], stored["policy"])} == recipe


def kept_as_finished(stored: dict | None, recipe: dict, cell: CellSpec) -> bool:
    """Whether a grid's stored run stands as its cell's finished run: trained by the cell's
    recipe, or by it on a machine where `precision: auto` resolved otherwise (bf16 on CPUs
    with native bf16, fp32 elsewhere; the `precision` grid found no difference beyond the
    seeds' spread). Without this a grid moved to another machine would set aside and train
    again every run it has. Each run records its precision; another grid's runs are taken
    only for the very same recipe (`finished_elsewhere`)."""
    if stored is None or same_recipe(stored, recipe):  # None: an earlier setting's run, kept as it is
        return True
    return "precision" not in cell.policy and same_recipe(stored | {"precision": recipe["precision"]}, recipe)


def set_aside(path: Path) -> Path:
    """Move a result its cell no longer produces to `runs/superseded/` (kept, never overwritten)."""
    folder = path.parent / "superseded"
    folder.mkdir(exist_ok=True)
    target, n = folder / path.name, 0
    while target.exists():
        n += 1
        target = folder / f"{path.stem}.{n}{path.suffix}"
    return path.rename(target)


def run_recipe(config: ReproduceConfig, task: str, cell: CellSpec, seed: int) -> dict:
    """Everything that decides what a run trains (not its name, grid or evaluation masks)."""
    scales = {
        k: v for k, v in (("paper_epsilon", cell.paper_epsilon), ("epsilon_quantile", cell.epsilon_quantile)) if v
    }
    dataset, encoders = dataset_root(config, task, cell).name, encoder_root(config, task).name
    return json.loads(
        json.dumps(
            {  # as it reads back from a result file
                "task": task,
                "dataset": dataset,
                **({"encoder_dataset": encoders} if encoders != dataset else {}),
                "method": cell.method,
                "cameras": list(cell.cameras),
                "epsilon": cell.epsilon,
                **scales,
                "policy": policy_overrides(cell.method, cell.cameras, cell.policy),
                "vqvae": asdict(config.vqvae),
                "train": asdict(config.train) | {"steps": config.cell_steps(cell)},
                "seed": seed,
                **({"budget": asdict(config.budget)} if config.budget else {}),
                # what `precision: auto` resolves to here: a bf16 run is not an fp32 run's twin
                "precision": str(
                    resolve_precision(cell.policy.get("precision", "auto"), resolve_device(config.device))
                ),
            }
        )
    )


def finished_elsewhere(
    config: ReproduceConfig, recipe: dict, mask_ps: list[float], encoders: dict[str, str] | None
) -> dict | None:
    """A result of another grid with the same recipe, trained on the very encoders given (by
    fingerprint; runs from before fingerprints were recorded are never taken) and evaluated
    at every masking level asked, cut down to those levels; None if there is none."""
    if encoders is None:
        return None
    for path in sorted(Path(config.results_dir).glob("*/runs/*.json")):
        if path.parent.parent.name == config.name:
            continue
        result = read_result(path)
        if result is None or "validation_seeds" not in result:  # an earlier setting's run, chosen on its test seeds
            continue
        if not same_recipe(result.get("recipe"), recipe) or not set(mask_ps) <= {r["mask_p"] for r in result["final"]}:
            continue
        if result.get("encoders") != encoders:
            continue
        return result | {
            "final": [r for r in result["final"] if r["mask_p"] in mask_ps],
            "curve": [point for point in result["curve"] if point[1] in mask_ps],
            "reused_from": f"{path.parent.parent.name}/{path.stem}",
        }
    return None


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
        summaries = train_seeds([train_config(config, task, cell, seed, root, encoders, steps) for seed in seeds])
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


def budget_recipe(recipe: dict, budget: int) -> dict:
    """A budget grid's run as tested: its recipe at `budget` updates."""
    return recipe | {"train": recipe["train"] | {"steps": budget}}


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
        "curve": _read_curve(out / "eval.csv"),
        "recipe": recipe,
        # trained side by side with this many seeds (their shared wall time and steps/s above)
        "seeds_together": summary.get("seeds_together", 1),
    }
    return result


def _store(path: Path, result: dict) -> dict:
    """A finished run's result file, written atomically: a hard stop leaves the old file or
    the new one, never half of one."""
    path.parent.mkdir(parents=True, exist_ok=True)
    write_atomic(path, (json.dumps(result, indent=1) + "\n").encode())
    return result


def grid_so_far(config: ReproduceConfig, stored: Path) -> ReproduceConfig:
    """The grid a results folder records (its config.yaml): a sitting that runs part of the
    grid (`--tasks=[pick_up]`, `--seeds=[1]`, or a copy of the config with fewer tasks) adds
    its tasks and seeds to the stored grid instead of replacing it, so the tables keep every
    column run before. Any other change is a new grid definition and replaces it."""
    if not stored.exists():
        return config
    try:
        before = load_reproduce_config(stored)
    except Exception:  # an unreadable record (torn): this sitting's grid stands
        return config
    if replace(before, tasks=config.tasks, seeds=config.seeds, stack_seeds=config.stack_seeds) != config:
        return config
    tasks = [*before.tasks, *(task for task in config.tasks if task not in before.tasks)]
    return replace(config, tasks=tasks, seeds=sorted({*before.seeds, *config.seeds}))


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
    out = Path(config.results_dir) / config.name
    with exclusive(out):  # one driver per grid; its jobs lock what they build in the work dir
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
        todo = [
            (shipped, task, cell, seed)
            for task, cell, seed in grid
            if not _stored_at(
                curves_dir / result_path(config, task, cell, seed).name, run_recipe(config, task, cell, seed), cap
            )
        ]
        needed = {
            c.root: c
            for _, task, cell, _ in todo
            for c in (collect_config(shipped, task, cell), collect_config(shipped, task))
        }
        build_datasets(executor, list(needed.values()), config.collection.workers)
        build_encoders(
            executor,
            shipped,
            sorted({(encoder_root(shipped, task), camera) for _, task, cell, _ in todo for camera in cell.cameras}),
        )
        jobs = [job + (cap,) for job in training_jobs(todo, together=config.stack_seeds)]
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
        if not _stored_at(
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


def _stored_at(path: Path, recipe: dict, steps: int) -> bool:
    """Whether a budget grid's result at `path` holds its run at `steps` updates, trained by
    `recipe`. A result of another recipe (its cell changed, or an earlier study's run of the
    same name) is set aside; its run trains again, from its checkpoint where it can."""
    stored = read_result(path) if path.exists() else None
    if stored is not None and not same_recipe(stored.get("recipe"), recipe):
        print(f"{path.name}: another recipe than its cell's (set aside in {set_aside(path).parent})", flush=True)
        return False
    return stored is not None and stored["steps"] == steps


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
            if stored is not None and kept_as_finished(stored.get("recipe"), recipe, cell):
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
    needed = {
        c.root: c
        for _, task, cell, _ in todo
        for c in (collect_config(shipped, task, cell), collect_config(shipped, task))
    }
    build_datasets(executor, list(needed.values()), config.collection.workers)
    build_encoders(
        executor,
        shipped,
        sorted({(encoder_root(shipped, task), camera) for _, task, cell, _ in todo for camera in cell.cameras}),
    )
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
