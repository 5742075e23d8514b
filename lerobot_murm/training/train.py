"""`murm train --config configs/...yaml`: the fast trainer.

Batches come from the latents in memory (LatentReplay, over the latent cache of an image
dataset or the codes of a latent dataset: transitions, next states and hindsight goals
gathered by index), and go through the same `MurmPolicy.iql_loss`, optimizer preset and
target update as under `lerobot-train`; checkpoints are LeRobot's format
(`pretrained_model/` with the processors), so `lerobot-eval` loads them.

Output folder: `train_config.yaml`, `log.csv` (losses), `eval.csv` (success rate per
evaluation and masking level), `sittings.csv` (where each sitting started, its precision and
machine), `learning_curve.png`, `checkpoints/last/` (policy +
`training_state.pt`, written before every evaluation so an interrupted run resumes there,
with the evaluation a stop cut short first),
and `final_eval.json` (`run_folder.py` writes and reads these files).

With `seeds: [a, b, ...]` the seeds train side by side as one stacked model
(`seed_stack.py`) and evaluate together, each writing `output_dir/seed<k>/` exactly as a
run of that seed alone writes its folder (on a CPU without native bf16, where stacking
does not pay, they train one after another). Each seed checkpoints separately, so a run
stopped between two seeds' checkpoints resumes the seeds that lag until they catch up.
On CUDA every update is replayed from a CUDA graph (`cuda_graph.py`).
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable
from contextlib import ExitStack
from dataclasses import dataclass, field, replace
from enum import Enum
from pathlib import Path

import draccus
import torch
import yaml
from lerobot.configs import FeatureType
from lerobot.configs.policies import PreTrainedConfig
from lerobot.utils.feature_utils import dataset_to_policy_features

from lerobot_murm.checkpointing import CheckpointError, append_rows, set_aside_rows_after, write_atomic
from lerobot_murm.checks import check_writable
from lerobot_murm.device import resolve_device
from lerobot_murm.env import TASK_NAMES
from lerobot_murm.locking import exclusive
from lerobot_murm.policy.configuration_murm import MurmConfig
from lerobot_murm.policy.modeling_murm import LOGGED, MurmPolicy
from lerobot_murm.policy.precision import resolve_precision
from lerobot_murm.policy.replay import LatentReplay, replay_for_dataset
from lerobot_murm.training.cuda_graph import CudaGraph, Updates, make_capturable
from lerobot_murm.training.evaluate import (
    TEST_SEED,
    VALIDATION_SEED,
    EvaluationStopped,
    Evaluator,
    evaluation_seeds,
)
from lerobot_murm.training.learning_curve import plot_learning_curve, read_run_csv
from lerobot_murm.training.run_folder import (
    EVAL_COLUMNS,
    LOG_COLUMNS,
    SITTINGS_FILE,
    finished_summary,
    keep_policy,
    kept_policy,
    record_sitting,
    resume_state,
    save_checkpoint,
)
from lerobot_murm.training.seed_stack import stacking_pays, train_together
from lerobot_murm.training_loop import TrainingInterrupted, TrainingLoop
from lerobot_murm.vqvae.frames import dataset_location, open_dataset


@dataclass
class TrainConfig:
    dataset: str  # a dataset folder or a Hub repo id
    task: str = "place_in_box"  # the simulator task evaluations run
    policy: PreTrainedConfig | None = None  # `type: murm` and its fields
    output_dir: str = "outputs/train/murm"
    cache_dir: str = "outputs/latent_cache"
    steps: int = 50_000
    batch_size: int = 256
    seed: int = 0
    # several seeds trained side by side as one stacked model, each in output_dir/seed<k>
    # (as a run of that seed alone would write output_dir); empty: `seed` alone in output_dir
    seeds: list[int] = field(default_factory=list)
    # those seeds stacked (true) or one after another (false); default: stacked where it pays
    # (GPUs, CPUs with native bf16: seed_stack.stacking_pays)
    stack: bool | None = None
    device: str = "auto"
    cuda_graph: bool = True  # on CUDA, replay each update from a CUDA graph (cuda_graph.py)
    log_every: int = 250
    eval_every: int = 5_000
    eval_episodes: int = 20  # validation episodes per learning-curve point during training
    final_eval_episodes: int = 100  # at the end: this many validation and this many test episodes
    eval_mask_p: list[float] = field(default_factory=lambda: [0.0])  # masking levels evaluated
    # also evaluate, at the end, the authors' public code's masking protocol (one random
    # camera masked on a third of the steps; MurmConfig.eval_mask_mode)
    eval_authors_masking: bool = False
    eval_envs: int = 4  # simulators per seed (worker processes where the run has a core to spare: Evaluator)
    # episode i of the validation range has seed validation_seed + i: learning curves and every
    # choice are made on these; the test range (test_seed + i) gives the reported numbers only
    validation_seed: int = VALIDATION_SEED
    test_seed: int = TEST_SEED
    # also keep the policy of every evaluation step that is a multiple of this, in
    # checkpoints/<step>/pretrained_model: a budget grid tests its runs at a step it chooses
    # after training (`test_kept`); 0 keeps only the last
    keep_every: int = 0
    # evaluate on the test episodes at the end of training; false: validation episodes only
    # (a budget grid's runs are tested once, at the budget its rule picks)
    final_test: bool = True

    def __post_init__(self) -> None:
        if not isinstance(self.policy, MurmConfig):
            raise ValueError("the config needs a `policy:` section with `type: murm`")
        if self.task not in TASK_NAMES:
            raise ValueError(f"unknown task {self.task!r}; valid tasks: {list(TASK_NAMES)}")
        counts = {
            "steps": self.steps,
            "batch_size": self.batch_size,
            "eval_every": self.eval_every,
            "log_every": self.log_every,
            "eval_episodes": self.eval_episodes,
            "final_eval_episodes": self.final_eval_episodes,
            "eval_envs": self.eval_envs,
        }
        for name, value in counts.items():
            if value < 1:
                raise ValueError(f"{name} must be at least 1, got {value}")
        if self.seed < 0:
            raise ValueError(f"seed must be >= 0, got {self.seed}")
        if self.keep_every < 0 or (self.keep_every and self.keep_every % self.eval_every):
            raise ValueError(
                f"keep_every must be 0 or a multiple of eval_every ({self.eval_every}), got {self.keep_every}"
            )
        if (self.seeds and min(self.seeds) < 0) or len(set(self.seeds)) != len(self.seeds):
            raise ValueError(f"seeds must be distinct and >= 0, got {self.seeds}")
        if not self.eval_mask_p or not all(0.0 <= p < 1.0 for p in self.eval_mask_p):
            raise ValueError(f"eval_mask_p must be masking levels in [0, 1), got {self.eval_mask_p}")
        validation = range(
            self.validation_seed, self.validation_seed + max(self.eval_episodes, self.final_eval_episodes)
        )
        test = range(self.test_seed, self.test_seed + self.final_eval_episodes)
        if min(self.validation_seed, self.test_seed) < 0 or (
            validation.start < test.stop and test.start < validation.stop
        ):
            raise ValueError(
                f"validation seeds {validation.start}-{validation.stop - 1} and test seeds "
                f"{test.start}-{test.stop - 1} must be non-negative and disjoint"
            )


def build_policy(config: MurmConfig, dataset, device: torch.device) -> MurmPolicy:
    """A fresh policy with the dataset's features and the trained encoders, as lerobot-train makes it."""
    features = dataset_to_policy_features(dataset.meta.features)
    config.output_features = {k: f for k, f in features.items() if f.type is FeatureType.ACTION}
    config.input_features = {k: f for k, f in features.items() if k not in config.output_features}
    config.device = device.type
    policy = MurmPolicy(config)
    policy.load_encoders()
    return policy.to(device)


def transition_batch(replay: LatentReplay, batch_size: int, generator: torch.Generator) -> dict[str, torch.Tensor]:
    return replay.sample(batch_size, generator).transition()


def seed_configs(config: TrainConfig) -> list[TrainConfig]:
    """One config per seed: `seeds` each in output_dir/seed<k>, else `seed` in output_dir."""
    if not config.seeds:
        return [config]
    return [
        replace(config, seed=seed, seeds=[], output_dir=str(Path(config.output_dir) / f"seed{seed}"))
        for seed in config.seeds
    ]


@dataclass
class SeedRun:
    """One seed's run: its folder, policy, sampling generator and where it stands."""

    config: TrainConfig
    policy: MurmPolicy
    generator: torch.Generator
    step: int = 0
    earlier_s: float = 0.0  # wall time of earlier sittings
    optimizer_state: dict | None = None
    summary: dict | None = None

    @property
    def out(self) -> Path:
        return Path(self.config.output_dir)

    @property
    def last(self) -> Path:
        return self.out / "checkpoints" / "last"

    def keep(self, step: int) -> None:
        """A copy of the last checkpoint's policy as the policy at `step` (`keep_every`)."""
        keep_policy(self.out, step)


def train(config: TrainConfig) -> list[dict]:
    """Train `config` (each of its seeds); each seed's summary, as its final_eval.json holds it."""
    return train_seeds(seed_configs(config))


def train_seeds(configs: list[TrainConfig]) -> list[dict]:
    """Runs that differ only in their seed and output folder, trained side by side. One
    writer per run folder (locking.py): two trainers of one folder used to write every log
    row twice."""
    first = configs[0]
    if any(replace(c, seed=first.seed, output_dir=first.output_dir) != first for c in configs):
        raise ValueError("seeds trained together must share every setting but their seed and output_dir")
    first.policy.load_encoder_settings()  # a wrong encoder_dir fails before any work
    with ExitStack() as locks:
        for c in configs:
            locks.enter_context(exclusive(Path(c.output_dir)))
        return _train_seeds(configs)


def _train_seeds(configs: list[TrainConfig]) -> list[dict]:
    first = configs[0]
    device = resolve_device(first.device)
    summaries = [finished_summary(c) for c in configs]
    todo = [c for c, summary in zip(configs, summaries, strict=True) if summary is None]
    if not todo:
        return summaries
    check_writable(Path(first.cache_dir))
    for c in todo:
        Path(c.output_dir).mkdir(parents=True, exist_ok=True)
    # every state first: a damaged run fails before the expensive steps
    states = [resume_state(Path(c.output_dir), Path(c.output_dir) / "checkpoints" / "last", device) for c in todo]
    sitting = time.perf_counter()  # a run's wall time counts its setup (latents, policy) and evaluations
    repo_id, root = dataset_location(first.dataset)
    dataset = open_dataset(repo_id, root)
    replay = replay_for_dataset(first.policy, dataset, Path(first.cache_dir), device)
    runs = [_open_run(c, state, dataset, replay, device) for c, state in zip(todo, states, strict=True)]
    together = stacking_pays(device) if first.stack is None else first.stack
    dtype = resolve_precision(first.policy.precision, device)
    for run in runs:  # this sitting in each run's record: its precision, seeds stacked and machine
        record_sitting(run.out, run.step, dtype, len(runs) if together else 1, device)
    while unfinished := [r for r in runs if r.summary is None]:
        start = min(r.step for r in unfinished)
        group = [r for r in unfinished if r.step == start]  # seeds a stopped run left behind catch up first
        until = min([r.step for r in unfinished if r.step > start] + [first.steps])
        for members in [group] if together else [[r] for r in group]:
            _train_members(members, until, replay, device, sitting)
    done = iter(r.summary for r in runs)
    return [summary if summary is not None else next(done) for summary in summaries]


def _open_run(config: TrainConfig, state: dict | None, dataset, replay: LatentReplay, device: torch.device) -> SeedRun:
    """The seed's policy built as a lone run builds it (its initialisation drawn from its seed),
    then its checkpoint loaded, or a step-0 checkpoint written (a run stopped before its first
    evaluation resumes too)."""
    torch.manual_seed(config.seed)
    generator = torch.Generator(device=device).manual_seed(config.seed)
    policy = build_policy(config.policy, dataset, device)
    policy.fit_latent_statistics(replay.latents)
    run = SeedRun(config, policy, generator)
    if state is None:
        optimizer = config.policy.get_optimizer_preset().build(policy.get_optim_params())
        save_checkpoint(run.last, policy, optimizer.state_dict(), 0, generator, 0.0)
        run.optimizer_state = optimizer.state_dict()
    else:
        policy.load_state_dict(state["policy"])
        generator.set_state(state["generator"])
        run.step, run.earlier_s, run.optimizer_state = state["step"], state.get("elapsed_s", 0.0), state["optimizer"]
        for name in ("log.csv", "eval.csv", SITTINGS_FILE):
            set_aside_rows_after(run.out / name, run.step)
        print(f"resuming from step {run.step} ({run.last})")
    write_config(config, run.out / "train_config.yaml")
    return run


def config_dict(config: TrainConfig) -> dict:
    """The config as plain YAML data. draccus leaves LeRobot's str-valued enums (FeatureType,
    NormalizationMode) as objects that YAML writes as Python objects no loader reads: here
    they are their names, as draccus writes any other enum."""

    def plain(value: object) -> object:
        if isinstance(value, Enum):
            return value.name
        if isinstance(value, dict):
            return {k: plain(v) for k, v in value.items()}
        if isinstance(value, list | tuple):
            return [plain(v) for v in value]
        return value

    return plain(draccus.encode(config))


def write_config(config: TrainConfig, path: Path) -> None:
    """The run's `train_config.yaml`, as `murm train --config` reads it back."""
    write_atomic(path, yaml.safe_dump(config_dict(config), sort_keys=False).encode())


class _RunConfigLoader(yaml.SafeLoader):
    """Also reads the train_config.yaml of runs from before `config_dict`, with each enum as
    `!!python/object/apply:<enum> [VALUE]` (LeRobot's enums are named by their values)."""


_RunConfigLoader.add_multi_constructor(
    "tag:yaml.org,2002:python/object/apply:", lambda loader, _, node: loader.construct_sequence(node)[0]
)


def read_config_dict(path: Path) -> dict | None:
    """A run folder's `train_config.yaml` as `config_dict` gives it; None if it does not read."""
    try:
        return yaml.load(Path(path).read_text(), _RunConfigLoader)
    except (OSError, yaml.YAMLError):
        return None


def _train_members(runs: list[SeedRun], until: int, replay: LatentReplay, device: torch.device, sitting: float) -> None:
    """Train `runs` (all at one step) together to step `until`, evaluating and checkpointing
    each as it would alone; at the end of training, their final evaluations and summaries."""
    config = runs[0].config
    policy_config: MurmConfig = config.policy
    if len(runs) > 1:
        print(f"training seeds {', '.join(str(r.config.seed) for r in runs)} side by side from step {runs[0].step}")
    updater = train_together([r.policy for r in runs])
    updater.load_optimizer_states([r.optimizer_state for r in runs])
    generators = [r.generator for r in runs]
    graph = CudaGraph(generators) if device.type == "cuda" and config.cuda_graph else None
    if graph is not None:
        make_capturable(updater.optimizer)
    updates = Updates(lambda: updater.step(replay.sample_stacked(config.batch_size, generators)), graph, device=device)
    # which run a bar is: `murm reproduce --jobs N` shows N of them at once
    label = f"{config.task} {policy_config.method}-{'+'.join(policy_config.cameras)}"
    if policy_config.view_dropout and policy_config.method != "dropout":  # separated Q's variants
        label += f" +{'actor' if policy_config.dropout_scope == 'actor' else 'view'} dropout"
    if policy_config.hindsight_goals:  # the hindsight grid's two cells of one method train side by side
        label += " +hindsight goals"
    seeds = f" seed{'s' if len(runs) > 1 else ''} {','.join(str(r.config.seed) for r in runs)}"
    loop = TrainingLoop(until, start=runs[0].step, desc=f"murm train {label}{seeds}")
    elapsed = lambda run: run.earlier_s + time.perf_counter() - sitting  # noqa: E731

    def checkpoint() -> None:
        updater.write_back()
        for k, run in enumerate(runs):
            run.step = loop.step
            run.optimizer_state = updater.optimizer_state(k)
            save_checkpoint(run.last, run.policy, run.optimizer_state, loop.step, run.generator, elapsed(run))

    image_size = policy_config.encoder_config(policy_config.cameras[0]).image_size
    with Evaluator(config.task, policy_config.cameras, image_size, config.eval_envs, len(runs)) as evaluator:

        def run_evaluation(at_step: int, eval_seeds: list[int], split: str, authors: bool = False) -> list[list[dict]]:
            """Each seed's rows of eval.csv; `EvaluationStopped` if a stop is asked for meanwhile."""
            return evaluation_rows(
                evaluator,
                updater.write_back(),
                eval_seeds,
                config.eval_mask_p,
                authors,
                at_step,
                split,
                stop=lambda: loop.stop_requested,
            )

        seeds = evaluation_seeds(config.eval_episodes, config.validation_seed)

        def validate(missing: list[SeedRun]) -> None:
            """This step's validation point, for the runs `missing` it (the seeds evaluate
            together; each run writes its own rows). The step's checkpoint is written first, so
            a stop during the evaluation loses no training: the resumed run validates first."""
            if config.keep_every and loop.step % config.keep_every == 0:
                for run in runs:
                    run.keep(loop.step)
            rows = run_evaluation(loop.step, seeds, "validation")
            for run, own in zip(runs, rows, strict=True):
                if any(run is m for m in missing):
                    append_rows(run.out / "eval.csv", EVAL_COLUMNS, own)
                    plot_learning_curve(run.out)
            loop.show(success=f"{rows[0][0]['success_rate']:.2f}")

        window_start, window_first = time.perf_counter(), loop.step
        with loop:
            try:
                if missing := unvalidated(runs, loop.step):  # a stop cut this step's validation short
                    validate(missing)
                while loop.running():
                    updates()
                    loop.advance()
                    if loop.every(config.log_every) or loop.finished:
                        means = updates.read().tolist()  # the only host synchronisation of the loop
                        rate = (loop.step - window_first) / (time.perf_counter() - window_start)
                        for run, values in zip(runs, means, strict=True):
                            row = dict(zip(LOGGED, values, strict=True)) | {"step": loop.step, "steps_per_s": rate}
                            append_rows(run.out / "log.csv", LOG_COLUMNS, [row])
                        loop.show(critic=f"{means[0][1]:.3f}", q=f"{means[0][3]:.1f}")
                        window_start, window_first = time.perf_counter(), loop.step
                    if loop.every(config.eval_every) and not loop.finished:
                        checkpoint()
                        validate(runs)
                        window_start = time.perf_counter()  # the window's rate leaves the evaluation out
            except EvaluationStopped:
                # this step is checkpointed, and again below with the cut evaluation's seconds in its
                # wall time; its validation comes first when the run resumes
                pass
            checkpoint()
            if loop.interrupted:
                raise TrainingInterrupted(f"stopped at step {loop.step}; run the same command again to resume")
            if until < config.steps:  # caught up with the seeds ahead: they all go on together
                return
            # a stop during the final evaluation ends it: the resumed run evaluates again
            validation_seeds = evaluation_seeds(config.final_eval_episodes, config.validation_seed)
            test_seeds = evaluation_seeds(config.final_eval_episodes, config.test_seed)
            try:
                final_validation = run_evaluation(
                    loop.step, validation_seeds, "validation", config.eval_authors_masking
                )
                final = (
                    run_evaluation(loop.step, test_seeds, "test", config.eval_authors_masking)
                    if config.final_test
                    else [[] for _ in runs]
                )
            except EvaluationStopped:
                raise TrainingInterrupted(
                    f"stopped at step {loop.step} in its final evaluation; run the same command again to finish it"
                ) from None
            if config.keep_every:
                for run in runs:
                    run.keep(loop.step)
    for run, validation_rows, test_rows in zip(runs, final_validation, final, strict=True):
        append_rows(run.out / "eval.csv", EVAL_COLUMNS, validation_rows + test_rows)
        plot_learning_curve(run.out)
        run.summary = {
            "method": policy_config.method,
            "cameras": policy_config.cameras,
            "task": config.task,
            "steps": loop.step,
            "seed": run.config.seed,
            "validation_seeds": [validation_seeds[0], validation_seeds[-1]],
            "eval_seeds": [test_seeds[0], test_seeds[-1]] if config.final_test else None,  # the test range
            "final_validation": validation_rows,
            "final": test_rows,
            "checkpoint": str(run.last / "pretrained_model"),
            "wall_s": round(elapsed(run), 1),
            "seeds_together": len(runs),  # its wall time and steps/s are those of all of them
        }
        write_atomic(run.out / "final_eval.json", (json.dumps(run.summary, indent=2) + "\n").encode())


def unvalidated(runs: list[SeedRun], step: int) -> list[SeedRun]:
    """The runs at an evaluation step before their last whose eval.csv has no validation point
    there: a stop came during that evaluation, or the run caught up to `step` with the seeds
    ahead (a training that ends at a step does not validate there)."""
    config = runs[0].config
    if step == 0 or step % config.eval_every or step >= config.steps:
        return []
    return [
        run
        for run in runs
        if not any(r["split"] == "validation" and r["step"] == step for r in read_run_csv(run.out / "eval.csv"))
    ]


def evaluation_rows(
    evaluator: Evaluator,
    policies: list[MurmPolicy],
    seeds: list[int],
    mask_ps: list[float],
    authors: bool,
    step: int,
    split: str,
    stop: Callable[[], bool] | None = None,
) -> list[list[dict]]:
    """Each policy's rows of eval.csv: its success on the episodes `seeds` at every masking
    level (and the authors' masking protocol where asked); `stop`: as `Evaluator.evaluate`."""
    levels = [(mask_p, "paper") for mask_p in mask_ps] + ([(1 / 3, "authors")] if authors else [])
    rows: list[list[dict]] = [[] for _ in policies]
    for mask_p, mode in levels:
        for own, result in zip(rows, evaluator.evaluate(policies, seeds, mask_p, mode, stop), strict=True):
            own.append(
                {
                    "step": step,
                    "mask_p": round(mask_p, 4),
                    "success_rate": result.success_rate,
                    "episodes": len(seeds),
                    "seconds": round(result.seconds, 1),
                    "split": split,
                    "mask_mode": mode,
                }
            )
    return rows


def test_kept(configs: list[TrainConfig], step: int) -> list[dict]:
    """Seeds' runs trained with `keep_every`, tested once at `step` (a budget chosen after
    training on their validation curves): each one's summary as a run finished at `step`
    would write it, its validation rows read from eval.csv. Kept in test_<step>.json, which a
    second call reads back."""
    first = configs[0]
    with ExitStack() as locks:
        for c in configs:
            locks.enter_context(exclusive(Path(c.output_dir)))
        stored = [Path(c.output_dir) / f"test_{step}.json" for c in configs]
        if all(path.exists() for path in stored):
            return [json.loads(path.read_text()) for path in stored]
        device = resolve_device(first.device)
        kept = [kept_policy(Path(c.output_dir), step) for c in configs]
        missing = [str(path) for path in kept if not path.exists()]
        if missing:
            raise CheckpointError(f"no policy kept at step {step}: {', '.join(missing)} (train with keep_every)")
        start = time.perf_counter()
        policies = [MurmPolicy.from_pretrained(path).to(device) for path in kept]
        test_seeds = evaluation_seeds(first.final_eval_episodes, first.test_seed)
        image_size = policies[0].config.encoder_config(policies[0].config.cameras[0]).image_size
        with Evaluator(first.task, policies[0].config.cameras, image_size, first.eval_envs, len(policies)) as evaluator:
            rows = evaluation_rows(
                evaluator, policies, test_seeds, first.eval_mask_p, first.eval_authors_masking, step, "test"
            )
        summaries = []
        for config, path, test_rows in zip(configs, stored, rows, strict=True):
            validation = [
                r | {"step": int(r["step"]), "episodes": int(r["episodes"])}
                for r in read_run_csv(Path(config.output_dir) / "eval.csv")
                if r["split"] == "validation" and r["step"] == step
            ]
            if {r["episodes"] for r in validation} != {first.final_eval_episodes}:
                raise CheckpointError(
                    f"{config.output_dir}/eval.csv has no validation rows of "
                    f"{first.final_eval_episodes} episodes at step {step}"
                )
            summary = {
                "method": first.policy.method,
                "cameras": first.policy.cameras,
                "task": first.task,
                "steps": step,
                "seed": config.seed,
                "validation_seeds": [first.validation_seed, first.validation_seed + first.final_eval_episodes - 1],
                "eval_seeds": [test_seeds[0], test_seeds[-1]],
                "final_validation": [{k: r[k] for k in EVAL_COLUMNS} for r in validation],
                "final": test_rows,
                "checkpoint": str(kept[configs.index(config)]),
                "test_s": round(time.perf_counter() - start, 1),
            }
            write_atomic(path, (json.dumps(summary, indent=2) + "\n").encode())
            summaries.append(summary)
        return summaries


def load_train_config(path: str | Path, overrides: list[str] | None = None) -> TrainConfig:
    return draccus.parse(TrainConfig, config_path=str(path), args=overrides or [], exit_on_error=False)
