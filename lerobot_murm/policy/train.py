"""`murm train --config configs/...yaml`: the fast trainer.

Batches come from the latents in memory (LatentReplay, over the latent cache of an image
dataset or the codes of a latent dataset: transitions, next states and hindsight goals
gathered by index), and go through the same `MurmPolicy.forward`,
optimizer preset and `update()` as under `lerobot-train`; checkpoints are LeRobot's
format (`pretrained_model/` with the processors), so `lerobot-eval` loads them.

Output folder: `train_config.yaml`, `log.csv` (losses), `eval.csv` (success rate per
evaluation and masking level), `learning_curve.png`, `checkpoints/last/` (policy +
`training_state.pt`, written at every evaluation so an interrupted run resumes there),
and `final_eval.json`.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass, field
from pathlib import Path

import draccus
import numpy as np
import torch
from lerobot.configs.policies import PreTrainedConfig
from lerobot.utils.feature_utils import dataset_to_policy_features
from lerobot.configs import FeatureType

from lerobot_murm.checkpointing import (
    COMPLETE_MARK,
    CheckpointError,
    append_rows,
    last_logged_step,
    load_state,
    recover,
    save_state,
    set_aside_rows_after,
    staging_folder,
    swap_in,
    write_atomic,
)
from lerobot_murm.checks import check_writable
from lerobot_murm.device import resolve_device
from lerobot_murm.env import TASK_NAMES
from lerobot_murm.locking import exclusive
from lerobot_murm.policy.configuration_murm import MurmConfig
from lerobot_murm.policy.evaluate import TEST_SEED, VALIDATION_SEED, Evaluator, evaluation_seeds
from lerobot_murm.policy.learning_curve import plot_learning_curve
from lerobot_murm.policy.modeling_murm import MurmPolicy
from lerobot_murm.policy.processor_murm import make_murm_pre_post_processors
from lerobot_murm.policy.replay import LatentReplay, replay_for_dataset
from lerobot_murm.training_loop import TrainingInterrupted, TrainingLoop
from lerobot_murm.vqvae.frames import dataset_location, open_dataset

LOG_COLUMNS = ["step", "value_loss", "critic_loss", "actor_loss", "q", "v", "reward", "adv_weight", "steps_per_s"]
EVAL_COLUMNS = ["step", "mask_p", "success_rate", "episodes", "seconds", "split", "mask_mode"]


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
    device: str = "auto"
    log_every: int = 250
    eval_every: int = 5_000
    eval_episodes: int = 20  # validation episodes per learning-curve point during training
    final_eval_episodes: int = 100  # at the end: this many validation and this many test episodes
    eval_mask_p: list[float] = field(default_factory=lambda: [0.0])  # masking levels evaluated
    # also evaluate, at the end, the authors' public code's masking protocol (one random
    # camera masked on a third of the steps; MurmConfig.eval_mask_mode)
    eval_authors_masking: bool = False
    eval_envs: int = 4  # simulator processes
    # episode i of the validation range has seed validation_seed + i: learning curves and every
    # choice are made on these; the test range (test_seed + i) gives the reported numbers only
    validation_seed: int = VALIDATION_SEED
    test_seed: int = TEST_SEED

    def __post_init__(self) -> None:
        if not isinstance(self.policy, MurmConfig):
            raise ValueError("the config needs a `policy:` section with `type: murm`")
        if self.task not in TASK_NAMES:
            raise ValueError(f"unknown task {self.task!r}; valid tasks: {list(TASK_NAMES)}")
        counts = {"steps": self.steps, "batch_size": self.batch_size, "eval_every": self.eval_every,
                  "log_every": self.log_every, "eval_episodes": self.eval_episodes,
                  "final_eval_episodes": self.final_eval_episodes, "eval_envs": self.eval_envs}
        for name, value in counts.items():
            if value < 1:
                raise ValueError(f"{name} must be at least 1, got {value}")
        if self.seed < 0:
            raise ValueError(f"seed must be >= 0, got {self.seed}")
        if not self.eval_mask_p or not all(0.0 <= p < 1.0 for p in self.eval_mask_p):
            raise ValueError(f"eval_mask_p must be masking levels in [0, 1), got {self.eval_mask_p}")
        validation = range(self.validation_seed, self.validation_seed + max(self.eval_episodes, self.final_eval_episodes))
        test = range(self.test_seed, self.test_seed + self.final_eval_episodes)
        if min(self.validation_seed, self.test_seed) < 0 or (validation.start < test.stop and test.start < validation.stop):
            raise ValueError(f"validation seeds {validation.start}-{validation.stop - 1} and test seeds "
                             f"{test.start}-{test.stop - 1} must be non-negative and disjoint")


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


def save_checkpoint(folder: Path, policy: MurmPolicy, optimizer, step: int, generator: torch.Generator,
                    elapsed_s: float) -> None:
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
        "optimizer": optimizer.state_dict(),
        "generator": generator.get_state(),
        "torch_rng": torch.get_rng_state(),
        "policy": policy.state_dict(),
        "elapsed_s": elapsed_s,  # wall time of all sittings so far, so a resumed run reports its whole time
    }
    save_state(state, tmp / COMPLETE_MARK)
    swap_in(folder)


def _resume_state(out: Path, last: Path, device: torch.device) -> dict | None:
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


def train(config: TrainConfig) -> dict:
    """Train, or resume, the run in `config.output_dir`; its summary. One writer per run
    folder (locking.py): two trainers of one folder used to write every log row twice."""
    config.policy.load_encoder_settings()  # a wrong encoder_dir fails before any work
    with exclusive(Path(config.output_dir)):
        return _train(config)


def _train(config: TrainConfig) -> dict:
    device = resolve_device(config.device)
    out = Path(config.output_dir)
    out.mkdir(parents=True, exist_ok=True)
    finished = out / "final_eval.json"
    if finished.exists():  # a finished run is never redone; asked for more steps, it trains on
        summary = json.loads(finished.read_text())
        if summary["steps"] == config.steps:
            return summary
        if summary["steps"] > config.steps:
            raise CheckpointError(f"{out} is trained to {summary['steps']} steps, more than the {config.steps} asked; "
                                  "move it away or set another output_dir")
        finished.rename(out / f"final_eval_{summary['steps']}.json")  # kept: the evaluation at that step
    check_writable(Path(config.cache_dir))
    last = out / "checkpoints" / "last"
    state = _resume_state(out, last, device)  # before the expensive steps: a damaged run fails now
    # the clock starts here: a run's wall time counts its setup (latents, policy) and evaluations
    loop = TrainingLoop(config.steps, start=state["step"] if state else 0,
                        earlier_s=state.get("elapsed_s", 0.0) if state else 0.0, desc="murm train")
    policy_config: MurmConfig = config.policy
    torch.manual_seed(config.seed)
    generator = torch.Generator(device=device).manual_seed(config.seed)

    repo_id, root = dataset_location(config.dataset)
    dataset = open_dataset(repo_id, root)
    replay = replay_for_dataset(policy_config, dataset, Path(config.cache_dir), device)
    policy = build_policy(policy_config, dataset, device)
    policy.fit_latent_statistics(replay.latents)
    optimizer = policy_config.get_optimizer_preset().build(policy.get_optim_params())

    if state is not None:
        policy.load_state_dict(state["policy"])
        optimizer.load_state_dict(state["optimizer"])
        generator.set_state(state["generator"])
        torch.set_rng_state(state["torch_rng"])
        for name in ("log.csv", "eval.csv"):
            set_aside_rows_after(out / name, loop.step)
        print(f"resuming from step {loop.step} ({last})")
    else:  # a step-0 checkpoint: a run stopped before its first evaluation resumes too
        save_checkpoint(last, policy, optimizer, 0, generator, 0.0)
    draccus.dump(config, (out / "train_config.yaml").open("w"))

    seeds = evaluation_seeds(config.eval_episodes, config.validation_seed)
    image_size = policy_config.encoder_config(policy_config.cameras[0]).image_size
    with Evaluator(config.task, policy_config.cameras, image_size, config.eval_envs) as evaluator:

        def run_evaluation(at_step: int, eval_seeds: list[int], split: str, authors: bool = False) -> list[dict]:
            levels = [(mask_p, "paper") for mask_p in config.eval_mask_p] + ([(1 / 3, "authors")] if authors else [])
            rows = []
            for mask_p, mode in levels:
                result = evaluator.evaluate(policy, eval_seeds, mask_p, mode)
                rows.append({"step": at_step, "mask_p": round(mask_p, 4), "success_rate": result.success_rate,
                             "episodes": len(eval_seeds), "seconds": round(result.seconds, 1), "split": split,
                             "mask_mode": mode})
            return rows

        policy.train()
        window: list[dict] = []
        window_start = time.perf_counter()
        with loop:
            while loop.running():
                loss, info = policy.forward(transition_batch(replay, config.batch_size, generator))
                optimizer.zero_grad(set_to_none=True)
                loss.backward()
                optimizer.step()
                policy.update()
                loop.advance()
                window.append(info)
                if loop.every(config.log_every) or loop.finished:
                    row = {k: float(np.mean([w[k] for w in window])) for k in LOG_COLUMNS[1:-1]}
                    row |= {"step": loop.step, "steps_per_s": len(window) / (time.perf_counter() - window_start)}
                    append_rows(out / "log.csv", LOG_COLUMNS, [row])
                    loop.show(critic=f"{row['critic_loss']:.3f}", q=f"{row['q']:.1f}")
                    window, window_start = [], time.perf_counter()
                if loop.every(config.eval_every) and not loop.finished:
                    rows = run_evaluation(loop.step, seeds, "validation")
                    append_rows(out / "eval.csv", EVAL_COLUMNS, rows)
                    loop.show(success=f"{rows[0]['success_rate']:.2f}")
                    save_checkpoint(last, policy, optimizer, loop.step, generator, loop.elapsed())
                    plot_learning_curve(out)
                    window_start = time.perf_counter()
            save_checkpoint(last, policy, optimizer, loop.step, generator, loop.elapsed())
            if loop.interrupted:
                raise TrainingInterrupted(f"stopped at step {loop.step}; run the same command again to resume")
            # inside the loop's stop handling: a stop request during the final evaluation waits for it
            validation_seeds = evaluation_seeds(config.final_eval_episodes, config.validation_seed)
            final_validation = run_evaluation(loop.step, validation_seeds, "validation", config.eval_authors_masking)
            test_seeds = evaluation_seeds(config.final_eval_episodes, config.test_seed)
            final = run_evaluation(loop.step, test_seeds, "test", config.eval_authors_masking)
    append_rows(out / "eval.csv", EVAL_COLUMNS, final_validation + final)
    plot_learning_curve(out)
    summary = {
        "method": policy_config.method,
        "cameras": policy_config.cameras,
        "task": config.task,
        "steps": loop.step,
        "seed": config.seed,
        "validation_seeds": [validation_seeds[0], validation_seeds[-1]],
        "eval_seeds": [test_seeds[0], test_seeds[-1]],  # the test range
        "final_validation": final_validation,
        "final": final,
        "checkpoint": str(last / "pretrained_model"),
        "wall_s": round(loop.elapsed(), 1),
    }
    write_atomic(out / "final_eval.json", (json.dumps(summary, indent=2) + "\n").encode())
    return summary


def load_train_config(path: str | Path, overrides: list[str] | None = None) -> TrainConfig:
    return draccus.parse(TrainConfig, config_path=str(path), args=overrides or [], exit_on_error=False)
