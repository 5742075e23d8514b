"""The experiment grid `murm reproduce` runs: tasks x cells x seeds, each cell a training recipe.

A cell names a method and its cameras and may change the demonstrations (Table 7) or the
reward threshold (Table 2): on our encoders' scale (`epsilon`), on the paper's
(`paper_epsilon`, mapped) or as a quantile of frame-to-goal distances (`epsilon_quantile`).
Every stage has defaults at the paper's scale; the YAML files in `configs/reproduce/` say
what each table varies.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import draccus

from lerobot_murm.collection import CollectConfig
from lerobot_murm.config_args import default_of
from lerobot_murm.env import CAMERA_NAMES, TASK_NAMES
from lerobot_murm.expert import default_noise_std
from lerobot_murm.policy.configuration_murm import MurmConfig
from lerobot_murm.training.train import TrainConfig
from lerobot_murm.vqvae import VQVAEConfig


# The specs' defaults are the stage configs' own (`default_of`), written once there.
@dataclass
class CollectionSpec:
    episodes: int = default_of(CollectConfig, "episodes")
    noise_std: float | None = default_of(CollectConfig, "noise_std")  # None: each task's calibrated std
    noisy_fraction: float = default_of(CollectConfig, "noisy_fraction")
    seed: int = default_of(CollectConfig, "seed")
    workers: int = default_of(CollectConfig, "workers")
    image_size: int = default_of(CollectConfig, "image_size")


@dataclass
class VQVAESpec:
    steps: int = default_of(VQVAEConfig, "steps")  # every camera trains this many steps (scene 3 on)
    batch_size: int = default_of(VQVAEConfig, "batch_size")
    # per-camera exceptions to `steps`; empty by default. Scene-2 grids gave the active camera
    # 5000 (their config.yaml records it); a table that compares cameras should not.
    camera_steps: dict[str, int] = field(default_factory=dict)


@dataclass
class TrainSpec:
    steps: int = 30_000  # a grid's own default (`murm train`'s is 50,000); the tables set theirs
    batch_size: int = default_of(TrainConfig, "batch_size")
    log_every: int = default_of(TrainConfig, "log_every")
    eval_every: int = default_of(TrainConfig, "eval_every")
    eval_episodes: int = default_of(TrainConfig, "eval_episodes")
    final_eval_episodes: int = default_of(TrainConfig, "final_eval_episodes")
    eval_envs: int = default_of(TrainConfig, "eval_envs")


@dataclass
class BudgetSpec:
    """A table's one budget, chosen on validation curves (study v2's protocol, REPORT.md):
    every run trains to `cap`, evaluated every `every` updates on `episodes` validation
    episodes; a cell's curve is its seeds' mean and flattens where `flattening.py` says (the
    pooled episodes of all seeds); the budget is the latest flattening point over the cells,
    tasks and masking levels, rounded up to `every`. A cell still rising at the cap doubles
    the cap for the whole table, up to `max_cap`. Every run is then tested once, at the
    budget, from the policy it kept there."""

    cap: int = 100_000
    every: int = 10_000
    episodes: int = 100
    at_least: int = 0  # the budget is at least this ...
    unless_flat_before: int = 0  # ... unless every curve flattens before this many updates
    max_cap: int = 400_000

    def check(self) -> None:
        """Called by the grid's config (draccus would hide this message behind its own)."""
        if min(self.every, self.episodes) < 1 or self.cap < self.every or self.cap % self.every:
            raise ValueError(
                f"budget: cap ({self.cap}) must be a positive multiple of every ({self.every}), and episodes at least 1"
            )
        if self.max_cap < self.cap or self.at_least > self.max_cap:
            raise ValueError(f"budget: max_cap ({self.max_cap}) must be at least cap ({self.cap}) and at_least")
        if self.at_least % self.every or self.unless_flat_before % self.every:
            raise ValueError(
                f"budget: at_least ({self.at_least}) and unless_flat_before ({self.unless_flat_before}) must be "
                f"multiples of every ({self.every}): a budget is one of the validation curves' points"
            )


@dataclass
class BestViewsSpec:
    """A cell whose cameras another budget grid chooses: the views that did best alone (the
    paper's procedure, section 5.2). Ranked by each single-view cell's seeds' mean unmasked
    validation success at that grid's final budget on `task` (`best_views.py`); the cell gets
    its cameras when its grid runs, and adds nothing if another cell already has them."""

    grid: str = "table3"  # the budget grid whose single-view cells rank the cameras
    task: str = "place_in_box"  # the task they are ranked on
    count: int = 2  # how many of the best views the cell takes

    def check(self) -> None:
        if self.task not in TASK_NAMES:
            raise ValueError(f"best_views.task: unknown task {self.task!r}; choose from {list(TASK_NAMES)}")
        if not 1 <= self.count <= len(CAMERA_NAMES):
            raise ValueError(f"best_views.count must be 1 to {len(CAMERA_NAMES)}, got {self.count}")
        if not self.grid:
            raise ValueError("best_views.grid: name the grid that ranks the views")


@dataclass
class CellSpec:
    method: str
    cameras: list[str] = field(default_factory=list)  # empty where `best_views` chooses them
    label: str = ""  # default: method and cameras
    eval_mask_p: list[float] = field(default_factory=lambda: [0.0])
    eval_authors_masking: bool = False  # also the authors' code's masking protocol (an extra row)
    epsilon: list[float] | None = None  # per camera, on our encoders' scale; default: `murm encode`'s suggestion
    # per camera, on the paper's scale (Table 2), mapped to ours by the ratio to the paper's
    # chosen 2.0 (latent_distance.paper_epsilon_on_our_scale)
    paper_epsilon: list[float] | None = None
    epsilon_quantile: list[float] | None = None  # per camera, a share (0-1) of random frames' goal distances
    episodes: int | None = None  # demonstrations (Table 7); default: the collection's
    noisy_fraction: float | None = None  # share of noisy demonstrations (Table 7)
    # every demonstration noisy, at this multiple of the task's calibrated noise std (Table 7's
    # other reading of the paper's a = a* + k N(0, 0.1): k as a scale, not a share)
    noise_scale: float | None = None
    policy: dict = field(default_factory=dict)  # any other MurmConfig field
    steps: int | None = None  # updates of this cell's runs; default: the grid's train.steps
    best_views: BestViewsSpec | None = None  # cameras chosen by another grid's results, when this one runs

    def __post_init__(self) -> None:
        if self.best_views is not None:
            self.best_views.check()
            if self.cameras:
                raise ValueError(f"cell {self.label or self.method}: best_views chooses its cameras; leave cameras out")
        elif not self.cameras:
            raise ValueError(f"cell {self.label or self.method}: no cameras")
        if not self.label:
            self.label = self.default_label()
        given = {
            k: v
            for k, v in (
                ("epsilon", self.epsilon),
                ("paper_epsilon", self.paper_epsilon),
                ("epsilon_quantile", self.epsilon_quantile),
            )
            if v is not None
        }
        if len(given) > 1:
            raise ValueError(
                f"cell {self.label}: set one of epsilon, paper_epsilon, epsilon_quantile, not {list(given)}"
            )
        if given and self.best_views is not None:
            raise ValueError(f"cell {self.label}: per-camera {list(given)} need named cameras, not best_views")
        for key, values in given.items():
            if len(values) != len(self.cameras):
                raise ValueError(f"cell {self.label}: {len(values)} {key} values for {len(self.cameras)} cameras")
        if any(v <= 0 for v in (self.epsilon or []) + (self.paper_epsilon or [])):
            raise ValueError(f"cell {self.label}: epsilon values must be positive")
        if self.steps is not None and self.steps < 1:
            raise ValueError(f"cell {self.label}: steps must be at least 1, got {self.steps}")
        if any(not 0 < q < 1 for q in self.epsilon_quantile or []):
            raise ValueError(f"cell {self.label}: epsilon_quantile values must be in (0, 1)")
        if self.noise_scale is not None and (self.noise_scale <= 0 or self.noisy_fraction is not None):
            raise ValueError(
                f"cell {self.label}: noise_scale must be positive and makes every demonstration noisy "
                "(do not set noisy_fraction with it)"
            )

    def default_label(self) -> str:
        if self.best_views is not None:
            return f"{self.method}-best{self.best_views.count}-of-{self.best_views.grid}"
        return f"{self.method}-{'+'.join(self.cameras)}"

    def checked_cameras(self) -> list[str]:
        """The cameras the config's checks build the cell with: its own, or any `count` for a
        `best_views` cell (no check depends on which)."""
        return list(self.cameras) or list(CAMERA_NAMES[: self.best_views.count])


@dataclass
class ReproduceConfig:
    name: str
    tasks: list[str] = field(default_factory=lambda: list(TASK_NAMES))
    cells: list[CellSpec] = field(default_factory=list)
    seeds: list[int] = field(default_factory=lambda: [0, 1, 2])
    collection: CollectionSpec = field(default_factory=CollectionSpec)
    vqvae: VQVAESpec = field(default_factory=VQVAESpec)
    train: TrainSpec = field(default_factory=TrainSpec)
    work_dir: str = "outputs/murm"  # datasets, encoders, caches, runs (large, not in git)
    results_dir: str = "results"  # small result files, tables and figures (committed)
    device: str = "auto"
    # which evaluation episodes the grid's tables show: "test" (the reported numbers) or
    # "validation" (grids that choose a setting: the test episodes are never looked at)
    report_split: str = "test"
    # held-out episodes per task simulated again to score each new encoder on the object's
    # pixels (object_pixels.json beside it, as `murm check-encoders`); 0: no check
    object_check_episodes: int = 20
    # a grid whose numbers are times (Table 5): its runs train one at a time in the driver,
    # whatever --jobs or --executor say, and none is taken from another grid (those shared
    # the machine with other runs)
    timed: bool = False
    # a grid that chooses update counts (`updates`): the report says where each run's
    # validation curve flattens, by the rule in experiments/flattening.py
    choose_updates: bool = False
    # build the grid's datasets and encoders (kept beside the results), then stop before any
    # training run: the long shared stages of a study, ahead of the protocol its runs follow
    prepare_only: bool = False
    # train each cell's seeds side by side as one stacked model (training/seed_stack.py), in one
    # job; false: every seed its own job. Timed grids never stack.
    stack_seeds: bool = True
    # one budget for every cell, chosen on validation curves (BudgetSpec); none: each cell
    # trains `train.steps` (or its own `steps`) and is tested at the end
    budget: BudgetSpec | None = None

    def __post_init__(self) -> None:
        unknown = [t for t in self.tasks if t not in TASK_NAMES]
        if unknown:
            raise ValueError(f"unknown tasks {unknown}; choose from {list(TASK_NAMES)}")
        if not self.cells:
            raise ValueError("the grid has no cells")
        for cell in self.cells:
            bad = [c for c in cell.cameras if c not in CAMERA_NAMES]
            if bad:
                raise ValueError(f"cell {cell.label}: unknown cameras {bad}; choose from {list(CAMERA_NAMES)}")
        if self.report_split not in ("test", "validation"):
            raise ValueError(f"report_split must be 'test' or 'validation', got {self.report_split!r}")
        labels = [c.label for c in self.cells]
        if len(set(labels)) != len(labels):
            raise ValueError(f"cell labels must be unique, got {labels}")
        if not self.seeds or min(self.seeds) < 0:
            raise ValueError(f"seeds must be a non-empty list of numbers >= 0, got {self.seeds}")
        if self.budget is not None:
            self.budget.check()
            if any(cell.steps for cell in self.cells):
                raise ValueError("a grid with a budget trains every cell alike: no cell may set steps")
            if self.report_split != "test":
                raise ValueError("a grid with a budget reports test numbers (report_split: test)")
        self.validate_stages()

    def cell_episodes(self, cell: CellSpec | None = None) -> int:
        """Demonstrations in the cell's dataset (no cell: the collection's default)."""
        return (cell and cell.episodes) or self.collection.episodes

    def cell_noisy_fraction(self, cell: CellSpec | None = None) -> float:
        """Share of noisy demonstrations in the cell's dataset (no cell: the collection's default)."""
        if cell is not None and cell.noise_scale is not None:
            return 1.0
        return self.collection.noisy_fraction if cell is None or cell.noisy_fraction is None else cell.noisy_fraction

    def cell_noise_std(self, task: str, cell: CellSpec | None = None) -> float | None:
        """The noise std of the cell's noisy demonstrations (None: the task's calibrated std)."""
        if cell is not None and cell.noise_scale is not None:
            return cell.noise_scale * (self.collection.noise_std or default_noise_std(task))
        return self.collection.noise_std

    def cell_steps(self, cell: CellSpec) -> int:
        """Updates of the cell's runs (a budget grid: its first cap)."""
        return self.budget.cap if self.budget else cell.steps or self.train.steps

    def train_settings(self, cell: CellSpec, steps: int | None = None) -> dict:
        """The TrainConfig fields a cell's runs share (`steps`: a budget grid's current cap).
        A budget grid evaluates every `budget.every` updates on its validation episodes, keeps
        the policy there and leaves the test episodes to the budget (`test_kept`)."""
        t, b = self.train, self.budget
        settings = {
            "steps": steps or self.cell_steps(cell),
            "batch_size": t.batch_size,
            "log_every": t.log_every,
            "eval_every": t.eval_every,
            "eval_episodes": t.eval_episodes,
            "final_eval_episodes": t.final_eval_episodes,
            "eval_mask_p": list(cell.eval_mask_p),
            "eval_envs": t.eval_envs,
            "eval_authors_masking": cell.eval_authors_masking,
        }
        if b is not None:
            settings |= {
                "eval_every": b.every,
                "eval_episodes": b.episodes,
                "final_eval_episodes": b.episodes,
                "keep_every": b.every,
                "final_test": False,
            }
        return settings

    def validate_stages(self) -> None:
        """Every stage's config of every cell, built as the grid will build it (no disk): a
        bad method, camera, policy field or number fails now, not after hours of collection."""
        unknown = [c for c in self.vqvae.camera_steps if c not in CAMERA_NAMES]
        if unknown:
            raise ValueError(f"vqvae.camera_steps: unknown cameras {unknown}; choose from {list(CAMERA_NAMES)}")
        for steps in {self.vqvae.steps, *self.vqvae.camera_steps.values()}:
            VQVAEConfig(steps=steps, batch_size=self.vqvae.batch_size)
        c = self.collection
        for cell in self.cells:
            try:
                policy = MurmConfig(
                    method=cell.method,
                    cameras=cell.checked_cameras(),
                    epsilon=cell.epsilon,
                    device="cpu",
                    **cell.policy,
                )
                for task in self.tasks:
                    CollectConfig(
                        task=task,
                        root=Path(self.work_dir),
                        episodes=self.cell_episodes(cell),
                        workers=c.workers,
                        image_size=c.image_size,
                        seed=c.seed,
                        noise_std=self.cell_noise_std(task, cell),
                        noisy_fraction=self.cell_noisy_fraction(cell),
                    )
                    TrainConfig(dataset="", task=task, policy=policy, seed=min(self.seeds), **self.train_settings(cell))
            except (TypeError, ValueError) as error:
                raise ValueError(f"cell {cell.label}: {error}") from error


def load_reproduce_config(path: str | Path, overrides: list[str] | None = None) -> ReproduceConfig:
    return draccus.parse(ReproduceConfig, config_path=str(path), args=overrides or [], exit_on_error=False)
