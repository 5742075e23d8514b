"""The rules for reusing earlier work: a run's recipe (everything that decides what it trains),
whether a stored result was trained by it (`same_recipe`, `same_run`, `kept_as_finished`), a finished run
of another grid taken instead of training it again (`finished_elsewhere`: Table 3's global
camera is Table 4's single-view baseline, when trained on the very same encoders), results
their cell no longer produces set aside, and the grid a results folder records
(`grid_so_far`: a sitting that runs part of a grid adds to it).
"""

from __future__ import annotations

import copy
import json
import shutil
from dataclasses import asdict, replace
from pathlib import Path

from lerobot_murm.checkpointing import COMPLETE_MARK, load_state, staging_folder
from lerobot_murm.device import resolve_device
from lerobot_murm.experiments.artifacts import (
    dataset_root,
    encoder_root,
    result_path,
    run_dir,
)
from lerobot_murm.experiments.configuration_reproduce import CellSpec, ReproduceConfig, load_reproduce_config
from lerobot_murm.experiments.results import read_result
from lerobot_murm.locking import FolderInUse, exclusive
from lerobot_murm.policy.configuration_murm import MurmConfig
from lerobot_murm.policy.precision import resolve_precision
from lerobot_murm.training.run_folder import kept_policy
from lerobot_murm.training.train import TrainConfig, config_dict, read_config_dict


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


def same_run(stored: dict | None, recipe: dict) -> bool:
    """Whether a grid's stored run is its cell's run: trained by the cell's recipe, or by it on
    a machine where `precision: auto` resolved otherwise (bf16 on CPUs with native bf16, fp32
    elsewhere; the `precision` grid found no difference beyond the seeds' spread). Without this
    a grid that moves between machines would set aside, and train or test again, every run it
    has. A cell that names its precision keeps it. Each run records its sittings' precision and
    machine; another grid's runs are taken only for the very same recipe (`finished_elsewhere`)."""
    if stored is None:
        return False
    if same_recipe(stored, recipe):
        return True
    return "precision" not in recipe["policy"] and same_recipe(stored | {"precision": recipe["precision"]}, recipe)


def kept_as_finished(stored: dict | None, recipe: dict) -> bool:
    """Whether a grid's stored run stands as its cell's finished run (`same_run`); a run of an
    earlier setting that recorded no recipe is kept as it is."""
    return stored is None or same_run(stored, recipe)


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


def budget_recipe(recipe: dict, budget: int) -> dict:
    """A budget grid's run as tested: its recipe at `budget` updates."""
    return recipe | {"train": recipe["train"] | {"steps": budget}}


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


def stored_at(path: Path, recipe: dict, steps: int) -> bool:
    """Whether a budget grid's result at `path` holds its run at `steps` updates, trained by
    `recipe`. A result of another recipe (its cell changed, or an earlier study's run of the
    same name) is set aside; its run trains again, from its checkpoint where it can."""
    stored = read_result(path) if path.exists() else None
    if stored is not None and not same_run(stored.get("recipe"), recipe):
        print(f"{path.name}: another recipe than its cell's (set aside in {set_aside(path).parent})", flush=True)
        return False
    return stored is not None and stored["steps"] == steps


def tested_at_budget(config: ReproduceConfig, task: str, cell: CellSpec, seed: int) -> bool:
    """Whether a budget grid's run has its test result stored, trained by its cell's recipe."""
    path = result_path(config, task, cell, seed)
    result = read_result(path) if path.exists() else None
    recipe = run_recipe(config, task, cell, seed)
    return result is not None and same_run(result.get("recipe"), budget_recipe(recipe, result["steps"]))


def ready_to_test(config: ReproduceConfig, task: str, cell: CellSpec, seed: int, cap: int) -> bool:
    """Whether a budget grid's run, its curve stored to `cap`, can be tested at any budget its
    table may choose: tested already, or its policy kept at every validation step up to `cap`
    in this work dir. A curve committed from another machine (a new machine has none of the
    old work dir) is not enough: its run trains again here, rather than the grid failing at
    the test, after hours of its other cells, for want of the policies."""
    if tested_at_budget(config, task, cell, seed):
        return True
    run, every = run_dir(config, task, cell, seed), config.budget.every
    return all(kept_policy(run, step).exists() for step in range(every, cap + 1, every))


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


ADOPTED = "adopted.json"  # in a run folder started from another grid's: from where, at which step


def _comparable(run: dict) -> dict:
    """A run's config as two grids' runs of one recipe share it: all but its folder, its
    current cap and the features its policy reads off the dataset when it is built."""
    policy = {k: v for k, v in run["policy"].items() if k not in ("input_features", "output_features")}
    return {k: v for k, v in run.items() if k not in ("output_dir", "steps")} | {"policy": policy}


def adopt_run(config: TrainConfig, runs: Path, grid: str) -> Path | None:
    """Start a budget grid's run that has not started here from another grid's run of the
    very same config (every field but its folder and cap) trained no further than this cap:
    its folder (checkpoints, kept policies, logs) is copied, not shared (one writer per
    folder), and the run goes on from its checkpoint as if it had trained here. Table 4's
    rendered-goal cells are the hindsight grid's, Table 3's place_in_box global camera is
    Table 2's default epsilon. Returns the folder taken, or None."""
    own = Path(config.output_dir)
    if own.exists():
        return None
    probe = copy.deepcopy(config)
    probe.policy.load_encoder_settings()  # as a run's stored config has them (and epsilon)
    wanted = _comparable(config_dict(probe))
    for donor in sorted(Path(runs).glob(f"*/{config.task}/*/{own.name}")):
        if donor.parents[2].name == grid or not (donor / "checkpoints" / "last" / COMPLETE_MARK).exists():
            continue
        stored = read_config_dict(donor / "train_config.yaml")
        if stored is None or _comparable(stored) != wanted:
            continue
        try:
            with exclusive(donor):  # not while its own grid trains it
                state = load_state(donor / "checkpoints" / "last" / COMPLETE_MARK)
                step = state["step"]
                if step > config.steps:
                    continue
                staging = staging_folder(own)  # emptied: a copy a crash cut short starts again
                shutil.copytree(donor, staging)
        except FolderInUse:
            continue
        for named in [staging / "train_config.yaml", *staging.glob("final_eval*.json")]:  # the folder it now is
            named.write_text(named.read_text().replace(str(donor), str(own)))
        # the run's wall time goes on from the other grid's: what that grid paid is said here
        taken = {"from": str(donor), "step": step, "wall_s": state.get("elapsed_s", 0.0)}
        (staging / ADOPTED).write_text(json.dumps(taken) + "\n")
        staging.rename(own)
        print(f"{own}: starts from {donor} at step {step:,} (the same run, trained by another grid)", flush=True)
        return donor
    return None
