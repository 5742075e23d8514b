"""Both trainers for real, in subprocesses: `lerobot-train --policy.type=murm` with evaluation in
the simulator, `murm train` with resume, and `lerobot-eval` on either one's checkpoint."""

import csv
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
import torch
import yaml

from lerobot_murm.policy.precision import cpu_description, resolve_precision
from lerobot_murm.training.run_folder import DTYPE_NAMES, read_sittings

sys.path.insert(0, str(Path(__file__).parent / "helpers"))
from commands import OFFLINE, run, run_command
from quiet import assert_quiet

BIN = Path(sys.executable).parent
CAMERAS = "[global,adjacent]"
ENV_ARGS = ["--env.type=murm", "--env.task=place_in_box", "--env.image_size=16", f"--env.cameras={CAMERAS}"]

pytestmark = pytest.mark.slow


def lerobot_eval(checkpoint: Path, out: Path, *extra: str) -> dict:
    run_command(
        [
            BIN / "lerobot-eval",
            f"--policy.path={checkpoint}",
            *ENV_ARGS,
            "--eval.n_episodes=2",
            "--eval.batch_size=2",
            f"--output_dir={out}",
            *extra,
        ],
        cwd=out.parent,
    )
    return json.loads((out / "eval_info.json").read_text())["overall"]


def train_config(tiny_pipeline, tmp_path: Path, method: str, **fields) -> Path:
    """A `murm train` YAML on the tiny pipeline, writing under tmp_path/run."""
    root, encoders = tiny_pipeline
    policy = {"type": "murm", "method": method, "cameras": ["global", "adjacent"], "encoder_dir": str(encoders)}
    config = {
        "dataset": str(root),
        "task": "place_in_box",
        "output_dir": str(tmp_path / "run"),
        "cache_dir": str(tmp_path / "cache"),
        **fields,
        "policy": policy,
    }
    path = tmp_path / "train.yaml"
    path.write_text(yaml.safe_dump(config, sort_keys=False))
    return path


def test_lerobot_train_evaluates_in_the_simulator_and_lerobot_eval_loads_its_checkpoint(tiny_pipeline, tmp_path):
    root, encoders = tiny_pipeline
    log = run_command(
        [
            BIN / "lerobot-train",
            "--policy.type=murm",
            "--policy.method=dropout",
            f"--policy.cameras={CAMERAS}",
            f"--policy.encoder_dir={encoders}",
            "--dataset.repo_id=local/place_in_box",
            f"--dataset.root={root}",
            *ENV_ARGS,
            "--steps=4",
            "--batch_size=4",
            "--env_eval_freq=4",
            "--eval.n_episodes=1",
            "--eval.batch_size=1",
            "--save_freq=4",
            "--log_freq=1",
            f"--output_dir={tmp_path / 'run'}",
            "--num_workers=0",
            "--wandb.enable=false",
        ],
        cwd=tmp_path,
    )
    assert "critic_loss" in log and "actor_loss" in log and "value_loss" in log
    assert "pc_success" in log  # the evaluation in the simulator ran during training
    checkpoint = tmp_path / "run" / "checkpoints" / "last" / "pretrained_model"
    config = json.loads((checkpoint / "config.json").read_text())
    assert (
        config["type"] == "murm" and config["method"] == "dropout" and set(config["encoders"]) == {"global", "adjacent"}
    )
    overall = lerobot_eval(checkpoint, tmp_path / "eval", "--policy.eval_mask_p=0.5")
    assert overall["n_episodes"] == 2 and 0.0 <= overall["pc_success"] <= 100.0


def test_murm_train_writes_curves_and_a_checkpoint_lerobot_eval_loads_and_resumes(tiny_pipeline, tmp_path):
    config = train_config(
        tiny_pipeline,
        tmp_path,
        "separated_q",
        steps=6,
        batch_size=32,
        log_every=2,
        eval_every=3,
        eval_episodes=1,
        final_eval_episodes=2,
        eval_mask_p=[0.0, 0.5],
        eval_envs=1,
    )
    out = run_command([BIN / "murm", "train", "--config", config], cwd=tmp_path)
    assert "masking 50%: success" in out
    assert_quiet(out)
    # its progress in a log file: whole lines naming the run, no carriage returns
    assert "\r" not in out and "murm train place_in_box separated_q-global+adjacent seed 0: 100%" in out
    run_dir = tmp_path / "run"
    for name in ("log.csv", "eval.csv", "learning_curve.png", "final_eval.json", "train_config.yaml"):
        assert (run_dir / name).exists(), name
    with (run_dir / "eval.csv").open() as f:
        evals = [(int(r["step"]), float(r["mask_p"]), r["split"]) for r in csv.DictReader(f)]
    assert evals == [
        (3, 0.0, "validation"),
        (3, 0.5, "validation"),
        (6, 0.0, "validation"),
        (6, 0.5, "validation"),
        (6, 0.0, "test"),
        (6, 0.5, "test"),
    ]  # the learning curve on validation seeds, then the test
    summary = json.loads((run_dir / "final_eval.json").read_text())
    assert [r["episodes"] for r in summary["final"]] == [2, 2]
    assert summary["validation_seeds"] == [200_000, 200_001] and summary["eval_seeds"] == [300_000, 300_001]
    # the run's own config reads back as the config it trained: run again, the run is finished
    again = run_command([BIN / "murm", "train", "--config", run_dir / "train_config.yaml"], cwd=tmp_path)
    assert "masking 50%: success" in again and "resuming" not in again

    # a finished run is not redone; asked for more steps it resumes from the checkpoint (its
    # evaluation at 6 steps kept beside), asked for fewer it refuses in one line
    assert "resuming" not in run_command([BIN / "murm", "train", "--config", config], cwd=tmp_path)
    state_file = run_dir / "checkpoints" / "last" / "training_state.pt"
    state = torch.load(state_file, weights_only=True)  # tensors and plain numbers only
    assert 0 < state["elapsed_s"] <= summary["wall_s"]
    torch.save(state | {"elapsed_s": 1000.0}, state_file)  # as if the first sitting had taken 1000 s
    out = run_command([BIN / "murm", "train", "--config", config, "--steps=8"], cwd=tmp_path)
    assert "resuming from step 6" in out
    with (run_dir / "log.csv").open() as f:
        assert [int(r["step"]) for r in csv.DictReader(f)] == [2, 4, 6, 8]
    assert json.loads((run_dir / "final_eval.json").read_text())["wall_s"] > 1000  # every sitting counts
    assert json.loads((run_dir / "final_eval_6.json").read_text()) == summary
    # each sitting that trained it: where it started, the dtype `precision: auto` gave there, the
    # seeds stacked with it and the machine (a finished run read back is no sitting)
    dtype = DTYPE_NAMES[resolve_precision("auto", torch.device("cpu"))]
    assert [(s["step"], s["precision"], s["seeds_together"], s["machine"]) for s in read_sittings(run_dir)] == [
        (0, dtype, 1, cpu_description()),
        (6, dtype, 1, cpu_description()),
    ]
    fewer = run(
        [BIN / "murm", "train", "--config", config, "--steps=4"],
        cwd=tmp_path,
        env={**os.environ, **OFFLINE},
        timeout=300,
    )
    assert fewer.returncode != 0 and "is trained to 8 steps, more than the 4 asked" in fewer.stderr
    assert "Traceback" not in fewer.stderr

    overall = lerobot_eval(Path(summary["checkpoint"]), tmp_path / "eval")
    assert overall["n_episodes"] == 2


def test_a_stop_signal_to_the_trainer_and_its_simulator_workers_saves_a_checkpoint(tiny_pipeline, tmp_path):
    """Ctrl-C in a terminal or `pkill -f murm` signal the simulator workers as well as the trainer."""
    config = train_config(
        tiny_pipeline, tmp_path, "concat", steps=1_000_000, batch_size=8, log_every=2, eval_every=1_000_000, eval_envs=2
    )
    env = {**os.environ, "HF_HUB_OFFLINE": "1", "OMP_NUM_THREADS": "2"}  # two cores: simulator worker processes
    trainer = subprocess.Popen(
        [str(BIN / "murm"), "train", "--config", str(config)],
        cwd=tmp_path,
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,
    )
    log = tmp_path / "run" / "log.csv"
    while not log.exists() and trainer.poll() is None:  # the workers exist before the first logged step
        time.sleep(0.2)
    os.killpg(trainer.pid, signal.SIGTERM)
    _, stderr = trainer.communicate(timeout=300)
    assert trainer.returncode == 1 and "stopped at step" in stderr, stderr[-3000:]
    assert "BrokenPipeError" not in stderr and "EOFError" not in stderr, stderr[-3000:]
    state = torch.load(tmp_path / "run" / "checkpoints" / "last" / "training_state.pt", weights_only=True)
    assert state["step"] >= 2


def test_a_stop_during_a_validation_ends_it_and_the_resumed_run_validates_that_step_first(tiny_pipeline, tmp_path):
    """SIGTERM (or Ctrl-C) while a run evaluates its validation episodes: the evaluation ends
    at its next episode instead of running to its end, the step's checkpoint is already
    written, and the resumed run evaluates that step before it trains on. What it writes
    equals an unbroken run's."""
    fields = {
        "steps": 6,
        "batch_size": 8,
        "log_every": 3,
        "eval_every": 3,
        "eval_episodes": 20,  # one at a time, about 10 s: the stop comes long before the 20th
        "final_eval_episodes": 2,
        "eval_envs": 1,
    }
    config = train_config(tiny_pipeline, tmp_path, "concat", **fields)
    unbroken = tmp_path / "unbroken"
    run_command([BIN / "murm", "train", "--config", config, f"--output_dir={unbroken}"], cwd=tmp_path)

    trainer = subprocess.Popen(
        [str(BIN / "murm"), "train", "--config", str(config)],
        cwd=tmp_path,
        env={**os.environ, "HF_HUB_OFFLINE": "1"},
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,
    )
    log = tmp_path / "run" / "log.csv"
    try:  # step 3 is logged just before its checkpoint and validation
        while trainer.poll() is None and not (log.exists() and "\n3," in log.read_text()):
            time.sleep(0.05)
        assert trainer.poll() is None, "the run ended before it could be stopped"
        os.killpg(trainer.pid, signal.SIGTERM)
        _, stderr = trainer.communicate(timeout=300)
    finally:
        if trainer.poll() is None:
            os.killpg(trainer.pid, signal.SIGKILL)
    assert trainer.returncode == 1 and "stopped at step 3" in stderr, stderr[-3000:]
    state = torch.load(tmp_path / "run" / "checkpoints" / "last" / "training_state.pt", weights_only=True)
    assert state["step"] == 3
    eval_csv = tmp_path / "run" / "eval.csv"
    assert not eval_csv.exists() or "\n3," not in eval_csv.read_text()  # the cut evaluation wrote nothing

    out = run_command([BIN / "murm", "train", "--config", config], cwd=tmp_path)
    assert "resuming from step 3" in out

    def outcomes(run_dir: Path) -> list[tuple]:
        with (run_dir / "eval.csv").open() as f:
            return [(r["step"], r["mask_p"], r["split"], r["episodes"], r["success_rate"]) for r in csv.DictReader(f)]

    assert outcomes(tmp_path / "run") == outcomes(unbroken)
    assert [r[:3] for r in outcomes(unbroken)] == [
        ("3", "0.0", "validation"),
        ("6", "0.0", "validation"),
        ("6", "0.0", "test"),
    ]


def test_the_evaluator_leaves_the_callers_stop_signals_alone():
    """Gymnasium builds one simulator in the calling process to read the spaces; only the
    workers may ignore Ctrl-C and SIGTERM, or a later stop (encoder training) is lost."""
    from lerobot_murm.training.evaluate import Evaluator

    before = signal.getsignal(signal.SIGINT), signal.getsignal(signal.SIGTERM)
    with Evaluator("place_in_box", ["global"], image_size=16, num_envs=1):
        pass
    assert (signal.getsignal(signal.SIGINT), signal.getsignal(signal.SIGTERM)) == before


def test_simulators_in_this_process_run_the_very_episodes_the_worker_processes_run():
    """A job with one core steps its evaluation's simulators in its own process: the same
    observations and successes, step for step, as in worker processes."""
    from lerobot_murm.training.evaluate import Evaluator

    seeds = [200_000, 200_001, 200_002, 200_003]
    actions = np.random.default_rng(0).uniform(-1, 1, (40, 4, 4)).astype(np.float32)
    episodes = {}
    for processes in (True, False):
        with Evaluator(
            "place_in_box", ["global", "adjacent"], image_size=16, num_envs=2, policies=2, processes=processes
        ) as ev:
            assert isinstance(ev.envs, gym.vector.AsyncVectorEnv) == processes
            observation, _ = ev.envs.reset(seed=seeds)
            frames, successes = [observation["pixels"]], []
            for action in actions:
                observation, _, _, _, info = ev.envs.step(action)
                frames.append(observation["pixels"])
                successes.append(np.asarray(info["is_success"], bool))
        episodes[processes] = frames, successes
    (in_workers, worker_successes), (here, here_successes) = episodes[True], episodes[False]
    for a, b in zip(in_workers, here, strict=True):
        assert a.keys() == b.keys() and all(np.array_equal(a[key], b[key]) for key in a)
    assert np.array_equal(worker_successes, here_successes)
    assert not np.array_equal(in_workers[0]["global"], in_workers[-1]["global"])  # the arm moved


def _expert_episodes(processes: bool, hold_succeeded: bool) -> tuple[list, np.ndarray]:
    """Four simulators of an Evaluator through one episode: three driven by the scripted expert
    (they succeed), the fourth by random actions (it does not). As the evaluation does, a
    simulator whose episode has succeeded gets NaN actions when `hold_succeeded`. Every step's
    observations, and the step at which each episode first succeeded."""
    from lerobot_murm.env import EPISODE_STEPS
    from lerobot_murm.expert.scripted import ScriptedExpert
    from lerobot_murm.training.evaluate import Evaluator

    random_actions = np.random.default_rng(0).uniform(-1, 1, (EPISODE_STEPS, 4)).astype(np.float32)
    experts = [ScriptedExpert("place_in_box") for _ in range(3)]
    with Evaluator("place_in_box", ["global"], image_size=16, num_envs=4, processes=processes) as ev:
        observation, _ = ev.envs.reset(seed=[200_000, 200_001, 200_002, 200_003])
        steps, first_success = [observation], np.full(4, -1)
        for t in range(EPISODE_STEPS):
            rows = [{key: observation[key][i] for key in ("agent_pos", "environment_state")} for i in range(3)]
            action = np.stack([*(e.act(row) for e, row in zip(experts, rows, strict=True)), random_actions[t]])
            if hold_succeeded:
                action[first_success >= 0] = np.nan
            observation, _, _, _, info = ev.envs.step(action.astype(np.float32))
            steps.append(observation)
            first_success[(first_success < 0) & np.asarray(info["is_success"], bool)] = t + 1
    return steps, first_success


@pytest.mark.parametrize("processes", [False, True])
def test_a_succeeded_episode_is_not_simulated_again_and_the_others_run_as_before(processes, monkeypatch):
    """An evaluation's episode succeeds if it ever succeeds, so its simulator skips the steps after
    its success (NaN actions): those steps are not simulated, and every step before them and every
    step of the other simulators is what a run that simulates every step gives, bit for bit."""
    from lerobot_murm.env.murm_env import MurmEnv

    simulated = []
    step = MurmEnv.step
    monkeypatch.setattr(MurmEnv, "step", lambda env, action: simulated.append(1) or step(env, action))
    full, full_success = _expert_episodes(processes, hold_succeeded=False)
    steps_full = len(simulated)
    held, held_success = _expert_episodes(processes, hold_succeeded=True)
    assert np.array_equal(full_success, held_success)
    assert list(full_success[:3] > 0) == [True] * 3 and full_success[3] == -1  # the expert's succeed, random's not
    for i, success_step in enumerate(held_success):
        last = len(full) - 1 if success_step < 0 else success_step
        for t in range(len(full)):
            expected = full[min(t, last)]  # after its success a held simulator repeats that step
            for key in ("agent_pos", "environment_state"):
                assert np.array_equal(held[t][key][i], expected[key][i])
            assert np.array_equal(held[t]["pixels"]["global"][i], expected["pixels"]["global"][i])
    if not processes:  # in worker processes the counter is theirs
        episode_steps = len(full) - 1
        assert len(simulated) - steps_full == sum(s if s > 0 else episode_steps for s in held_success)


def test_validation_and_test_seeds_must_be_disjoint(tiny_pipeline, tmp_path):
    from lerobot_murm.training.train import load_train_config

    config = train_config(tiny_pipeline, tmp_path, "separated_q")
    assert load_train_config(config).test_seed == 300_000
    with pytest.raises(Exception) as error:  # draccus wraps the config's ValueError
        load_train_config(config, ["--validation_seed=300050"])
    assert "validation seeds 300050-300149 and test seeds 300000-300099 must be" in str(
        error.value.__cause__ or error.value
    )


def _parameters(checkpoint: Path) -> dict[str, torch.Tensor]:
    from safetensors.torch import load_file

    return {k: v for k, v in load_file(checkpoint / "model.safetensors").items() if not k.startswith("encoders.")}


def test_seeds_trained_side_by_side_write_what_each_would_alone_and_a_lagging_seed_catches_up(tiny_pipeline, tmp_path):
    """`murm train --seeds=[0,1]`: seed 1 stacked against seed 1 alone (fp32), per-seed folders
    in the lone format (lerobot-eval loads them), and a seed that a stop left behind (seed 0,
    trained alone to step 4 here) trains on its own until the other catches up."""
    fields = {
        "steps": 8,
        "batch_size": 16,
        "log_every": 1,
        "eval_every": 4,
        "eval_episodes": 1,
        "final_eval_episodes": 1,
        "eval_envs": 1,
    }
    config = train_config(tiny_pipeline, tmp_path, "separated_q", **fields)
    # view dropout and hindsight goals: the stack's sampler draws the masks and goals a lone run draws
    policy = ["--policy.precision=fp32", "--policy.view_dropout=true", "--policy.hindsight_goals=true"]
    run_command(
        [BIN / "murm", "train", "--config", config, *policy, "--seed=1", f"--output_dir={tmp_path / 'alone'}"],
        cwd=tmp_path,
    )
    run_command(
        [
            BIN / "murm",
            "train",
            "--config",
            config,
            *policy,
            "--seed=0",
            "--steps=4",
            f"--output_dir={tmp_path / 'run' / 'seed0'}",
        ],
        cwd=tmp_path,
    )
    out = run_command(
        [BIN / "murm", "train", "--config", config, *policy, "--seeds=[0,1]", "--stack=true"], cwd=tmp_path
    )
    assert "resuming from step 4" in out and "training seeds 0, 1 side by side from step 4" in out
    # seed 0's first sitting trained it alone, the second stacked with seed 1; seed 1 has only that one
    assert [(s["step"], s["precision"], s["seeds_together"]) for s in read_sittings(tmp_path / "run" / "seed0")] == [
        (0, "fp32", 1),
        (4, "fp32", 2),
    ]
    assert [(s["step"], s["seeds_together"]) for s in read_sittings(tmp_path / "run" / "seed1")] == [(0, 2)]
    assert "murm train place_in_box separated_q-global+adjacent +view dropout +hindsight goals seeds 0,1: 100%" in out

    alone, stacked = tmp_path / "alone", tmp_path / "run" / "seed1"
    for name in ("log.csv", "eval.csv", "learning_curve.png", "final_eval.json", "train_config.yaml"):
        assert (stacked / name).exists() and (tmp_path / "run" / "seed0" / name).exists(), name
    with (alone / "log.csv").open() as f, (stacked / "log.csv").open() as g:
        lone_rows, stacked_rows = list(csv.DictReader(f)), list(csv.DictReader(g))
    assert [r["step"] for r in stacked_rows] == [str(s) for s in range(1, 9)]
    # the seed that trained alone to step 4 before it caught up still has its validation point there
    with (alone / "eval.csv").open() as f, (stacked / "eval.csv").open() as g:
        assert [(r["step"], r["split"]) for r in csv.DictReader(g)] == [
            (r["step"], r["split"]) for r in csv.DictReader(f)
        ]
    for column in ("value_loss", "critic_loss", "actor_loss"):  # the first update's losses: the same batch and weights
        assert float(stacked_rows[0][column]) == pytest.approx(float(lone_rows[0][column]), rel=1e-5)
    checkpoint = Path(json.loads((stacked / "final_eval.json").read_text())["checkpoint"])
    lone, ours = _parameters(alone / "checkpoints" / "last" / "pretrained_model"), _parameters(checkpoint)
    for name, value in lone.items():
        torch.testing.assert_close(ours[name], value, rtol=1e-5, atol=1e-5 * value.abs().max().item())
    assert lerobot_eval(checkpoint, tmp_path / "eval")["n_episodes"] == 2


def test_seeds_side_by_side_killed_with_sigkill_resume_every_seed(tiny_pipeline, tmp_path):
    config = train_config(
        tiny_pipeline,
        tmp_path,
        "dropout",
        steps=60,
        batch_size=8,
        log_every=5,
        eval_every=20,
        eval_episodes=1,
        final_eval_episodes=1,
        eval_envs=1,
    )
    # stacked on any CPU (without native bf16 they would train one after another by default)
    command = [str(BIN / "murm"), "train", "--config", str(config), "--seeds=[0,1]", "--stack=true"]
    trainer = subprocess.Popen(
        command,
        cwd=tmp_path,
        env={**os.environ, "HF_HUB_OFFLINE": "1"},
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
        start_new_session=True,
    )
    states = [tmp_path / "run" / f"seed{s}" / "checkpoints" / "last" / "training_state.pt" for s in (0, 1)]

    def checkpointed_step(path: Path) -> int:
        try:
            return torch.load(path, weights_only=False)["step"]
        except Exception:  # not there yet, or being swapped in
            return 0

    try:
        deadline = time.monotonic() + 300
        while trainer.poll() is None and time.monotonic() < deadline and min(map(checkpointed_step, states)) < 20:
            time.sleep(0.1)
        assert trainer.poll() is None, "the run ended before it could be killed"
        os.killpg(trainer.pid, signal.SIGKILL)  # the trainer and its simulator workers, mid-run
        trainer.wait(timeout=60)
    finally:
        if trainer.poll() is None:
            os.killpg(trainer.pid, signal.SIGKILL)
    steps = [checkpointed_step(path) for path in states]
    out = run_command(command, cwd=tmp_path)
    for step in steps:
        assert f"resuming from step {step}" in out
    for seed in (0, 1):
        run_dir = tmp_path / "run" / f"seed{seed}"
        assert json.loads((run_dir / "final_eval.json").read_text())["steps"] == 60
        with (run_dir / "log.csv").open() as f:
            assert [int(r["step"]) for r in csv.DictReader(f)] == list(range(5, 65, 5))  # one row per step, none lost
