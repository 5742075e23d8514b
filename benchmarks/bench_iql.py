"""IQL training speed: gradient steps/s per method in fp32 eager and in the default precision,
FLOP/s against a dense matmul of the precision used, and the fast trainer against
`lerobot-train` on the same latent dataset.

Not a test. Run it on an otherwise idle machine:

    .venv/bin/python benchmarks/bench_iql.py [--device cpu] [--repeats 5] [--widths both]
    .venv/bin/python benchmarks/bench_iql.py --lerobot-train-only [--num-workers 2]
    .venv/bin/python benchmarks/bench_iql.py --row-costs
    .venv/bin/python benchmarks/bench_iql.py --seeds-together 3 [--profile] [--eval-share]

Speed does not depend on the latents' content, so the replay holds random codebook
indices (100,000 frames, 1,000 episodes). A step is what `murm train` does: sample a
batch from the replay, `policy.forward`, backward, optimizer step, `policy.update()`.
Each case runs fp32 and the default (`precision: auto`) in alternating blocks on the same
policy (ABAB...), and the medians are compared, so machine noise hits both alike.
`--lerobot-train(-only)` writes such random codes as a latent dataset (`murm encode
--to-dataset`'s writer, with random encoders), then measures `murm train`'s step on it
and the stock `lerobot-train --policy.type=murm` on it, alternately.
`--seeds-together K` measures `murm train`'s update of K seeds stacked (seed_stack.py)
against one seed alone, in alternating blocks (aggregate seed-updates/s), for single view
and separated Q with two cameras at the paper's widths in the default precision;
`--profile` says where each one's step goes, `--eval-share` what share of a K-seed cell's
wall time (the reproduce defaults) goes to evaluating in the simulator.
"""

from __future__ import annotations

import argparse
import os
import platform
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from dataclasses import asdict
from pathlib import Path

import numpy as np
import torch
from lerobot.configs import FeatureType, PolicyFeature
from lerobot.datasets.io_utils import hf_transform_to_torch
from lerobot.datasets.lerobot_dataset import LeRobotDataset
from torch.utils.flop_counter import FlopCounterMode

from lerobot_murm.experiments.configuration_reproduce import TrainSpec
from lerobot_murm.features import LATENTS_PREFIX, goal_image_key, image_key, is_goal
from lerobot_murm.policy.configuration_murm import MurmConfig
from lerobot_murm.policy.modeling_murm import MurmPolicy
from lerobot_murm.policy.precision import matmul_precision, resolve_precision
from lerobot_murm.policy.replay import LatentReplay, replay_for_dataset
from lerobot_murm.training.cuda_graph import CudaGraph, Updates, make_capturable
from lerobot_murm.training.evaluate import Evaluator, evaluation_seeds
from lerobot_murm.training.seed_stack import LoneSeed, SeedStack
from lerobot_murm.training.train import build_policy, transition_batch
from lerobot_murm.vqvae import VQVAEConfig
from lerobot_murm.vqvae.code_packing import unpack_codes
from lerobot_murm.vqvae.latent_cache import LatentCache
from lerobot_murm.vqvae.latent_dataset import write_latent_dataset
from lerobot_murm.vqvae.modeling_vqvae import VQVAE

CASES = [("single", 1), ("concat", 2), ("dropout", 2), ("separated_q", 2), ("dropout", 3), ("separated_q", 3)]
CAMERAS = ["global", "adjacent", "side"]
PRECISIONS = {"fp32": "fp32", "default": "auto"}  # label -> MurmConfig.precision
# `per_camera`: 128 units per camera for V, the policy and a whole-state Q, 128 per separated-Q
# head (the default); `fixed`: 128 everywhere (the widths before the per-camera rule)
WIDTHS = {"per_camera": True, "fixed": False}  # label -> MurmConfig.width_per_camera


def synthetic_cache(camera: str, frames: int = 100_000, episodes: int = 1_000, seed: int = 0) -> LatentCache:
    config = VQVAEConfig()
    rng = np.random.default_rng(seed)
    g = config.grid_size
    return LatentCache(
        camera=camera,
        indices=rng.integers(0, config.codebook_size, (frames, g, g)).astype(np.uint16),
        goal_indices=rng.integers(0, config.codebook_size, (episodes, g, g)).astype(np.uint16),
        codebook=rng.normal(size=(config.codebook_size, config.embedding_dim)).astype(np.float32),
        episode_index=np.repeat(np.arange(episodes), frames // episodes),
        frame_index=np.tile(np.arange(frames // episodes), episodes),
    )


def make_policy(method: str, cameras: list[str], device: torch.device, **fields) -> MurmPolicy:
    encoders = {c: asdict(VQVAEConfig(camera=c)) for c in cameras}
    image = PolicyFeature(type=FeatureType.VISUAL, shape=(3, 48, 48))
    config = MurmConfig(method=method, cameras=cameras, encoders=encoders, epsilon=[2.0] * len(cameras), **fields)
    config.input_features = {k: image for c in cameras for k in (image_key(c), goal_image_key(c))}
    config.output_features = {"action": PolicyFeature(type=FeatureType.ACTION, shape=(4,))}
    return MurmPolicy(config).to(device)


def matmul_gflops(device: torch.device, dtype: torch.dtype = torch.float32, n: int = 2048, repeats: int = 7) -> float:
    a, b = torch.randn(n, n, device=device, dtype=dtype), torch.randn(n, n, device=device, dtype=dtype)
    a @ b
    rates = []
    for _ in range(repeats):
        _sync(device)
        start = time.perf_counter()
        a @ b
        _sync(device)
        rates.append(2 * n**3 / (time.perf_counter() - start) / 1e9)
    return statistics.median(rates)


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize()


def measure(
    method: str, n_cameras: int, widths: str, batch: int, device: torch.device, steps: int, repeats: int
) -> dict:
    """Per precision label: steps/s (sampling included), update ms on a fixed batch, sample ms."""
    cameras = CAMERAS[:n_cameras]
    policy = make_policy(method, cameras, device, width_per_camera=WIDTHS[widths]).train()
    caches = [synthetic_cache(c, seed=i) for i, c in enumerate(cameras)]
    actions = np.random.default_rng(0).uniform(-1, 1, (len(caches[0].indices), 4)).astype(np.float32)
    replay = LatentReplay(caches, actions, policy.config.epsilon, policy.config.her_ratio, device=device)
    optimizer = policy.config.get_optimizer_preset().build(policy.get_optim_params())
    generator = torch.Generator(device=device).manual_seed(0)

    def update(transitions: dict) -> None:
        loss, _ = policy.forward(transitions)
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        optimizer.step()
        policy.update()

    transitions = transition_batch(replay, batch, generator)
    with FlopCounterMode(display=False) as counter:
        update(transitions)
    flops = counter.get_total_flops()
    step_times = {label: [] for label in PRECISIONS}
    update_times = {label: [] for label in PRECISIONS}
    cpu_times = {label: [] for label in PRECISIONS}  # process CPU time: what a shared machine's load spares
    for repeat in range(repeats + 1):  # the first round warms both precisions up and is not counted
        for label, precision in PRECISIONS.items():
            policy.config.precision = precision
            _sync(device)
            start, cpu_start = time.perf_counter(), time.process_time()
            for _ in range(steps):
                update(transition_batch(replay, batch, generator))
            _sync(device)
            step_s, cpu_s = (time.perf_counter() - start) / steps, (time.process_time() - cpu_start) / steps
            start = time.perf_counter()
            for _ in range(steps):
                update(transitions)
            _sync(device)
            if repeat:
                step_times[label].append(step_s)
                cpu_times[label].append(cpu_s)
                update_times[label].append((time.perf_counter() - start) / steps)
    c = policy.config
    hidden = f"{c.hidden_units if method == 'separated_q' else c.shared_width}/{c.shared_width}/{c.shared_width}"
    result = {"method": method, "cameras": n_cameras, "widths": widths, "gflop": flops / 1e9, "hidden": hidden}
    for label in PRECISIONS:
        step_s, update_s = statistics.median(step_times[label]), statistics.median(update_times[label])
        result[label] = {
            "steps_per_s": 1 / step_s,
            "update_ms": 1e3 * update_s,
            "sample_ms": 1e3 * (step_s - update_s),
            "gflops": flops / update_s / 1e9,
            "cpu_ms": 1e3 * statistics.median(cpu_times[label]),
        }
    result["speedup"] = result["default"]["steps_per_s"] / result["fp32"]["steps_per_s"]
    result["cpu_speedup"] = result["fp32"]["cpu_ms"] / result["default"]["cpu_ms"]
    return result


def cpu_model() -> str:
    try:
        lscpu = subprocess.run(["lscpu"], capture_output=True, text=True, check=True).stdout
        return next(line for line in lscpu.splitlines() if line.startswith("Model name")).split(":", 1)[1].strip()
    except (OSError, subprocess.CalledProcessError, StopIteration):
        return platform.processor() or "unknown"


def write_random_latent_dataset(folder: Path, cameras: list[str], episodes: int, frames: int = 100) -> Path:
    """Random codes of `cameras` as a latent dataset in folder/latents, with random encoders in
    folder/vqvae (what lerobot-train's policy checks the codes against)."""
    source = LeRobotDataset.create(
        "local/source",
        fps=10,
        root=folder / "source",
        use_videos=False,
        features={
            "action": {"dtype": "float32", "shape": (4,), "names": None},
            "next.reward": {"dtype": "float32", "shape": (1,), "names": None},
        },
    )
    rng = np.random.default_rng(0)
    for _ in range(episodes):
        for action in rng.uniform(-1, 1, (frames, 4)).astype(np.float32):
            source.add_frame({"action": action, "next.reward": np.zeros(1, np.float32), "task": "random"})
        source.save_episode()
    source.finalize()
    source = LeRobotDataset("local/source", root=folder / "source")
    caches, encoder_dirs = [], []
    for i, camera in enumerate(cameras):
        encoder = VQVAE(VQVAEConfig(camera=camera))
        encoder_dirs.append(folder / "vqvae" / camera)
        encoder.save(encoder_dirs[-1])
        cache = synthetic_cache(camera, episodes * frames, episodes, seed=i)
        cache.codebook = encoder.quantizer.codebook.detach().numpy()
        caches.append(cache)
    write_latent_dataset(source, caches, encoder_dirs, folder / "latents", "local/latents")
    return folder / "latents"


def fast_s_per_step(policy: MurmPolicy, replay: LatentReplay, batch: int, steps: int, device: torch.device) -> float:
    """`murm train`'s loop (sample, forward, backward, Adam, Polyak) on `replay`: seconds a step,
    CPU time on the CPU and wall time (synchronised) on a GPU."""
    optimizer = policy.config.get_optimizer_preset().build(policy.get_optim_params())
    generator = torch.Generator(device=device).manual_seed(0)
    clock = time.process_time if device.type == "cpu" else time.perf_counter
    _sync(device)
    start = clock()
    for _ in range(steps):
        loss, _ = policy.forward(transition_batch(replay, batch, generator))
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        optimizer.step()
        policy.update()
    _sync(device)
    return (clock() - start) / steps


def lerobot_train_s(
    latents: Path,
    encoder_dir: Path,
    cameras: list[str],
    batch: int,
    steps: int,
    num_workers: int,
    threads: int | None,
    device: torch.device,
) -> float:
    """Seconds of a whole stock `lerobot-train --policy.type=murm` run on the latent dataset: on
    the CPU its CPU time, data-loader workers included; on a GPU its wall time. `threads`: its
    torch threads (OMP_NUM_THREADS), as this process's. Started as `python -m` (the console
    script's own module), so it runs wherever this interpreter's packages are."""
    env = {**os.environ, "HF_HUB_OFFLINE": "1", **({"OMP_NUM_THREADS": str(threads)} if threads else {})}
    before, start = resource.getrusage(resource.RUSAGE_CHILDREN), time.perf_counter()
    with tempfile.TemporaryDirectory() as out:
        subprocess.run(
            [
                sys.executable,
                "-m",
                "lerobot.scripts.lerobot_train",
                "--policy.type=murm",
                "--policy.method=separated_q",
                f"--policy.cameras=[{','.join(cameras)}]",
                f"--policy.encoder_dir={encoder_dir}",
                "--policy.epsilon=[2.0,2.0]",
                f"--policy.device={device.type}",
                "--dataset.repo_id=local/latents",
                f"--dataset.root={latents}",
                f"--batch_size={batch}",
                f"--steps={steps}",
                "--save_checkpoint=false",
                f"--num_workers={num_workers}",
                f"--output_dir={out}/run",
                "--wandb.enable=false",
            ],
            capture_output=True,
            check=True,
            env=env,
        )
    if device.type != "cpu":
        return time.perf_counter() - start
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    return after.ru_utime + after.ru_stime - before.ru_utime - before.ru_stime


def row_costs(episodes: int = 100, rows: int = 2000) -> None:
    """CPU ms per row of what LeRobot's loader reads from a two-camera latent dataset: its codes
    packed (the layout), unpacked to 144 int16 an image (the layout before), without the goal
    codes and without any: where `lerobot-train`'s extra time goes."""
    with tempfile.TemporaryDirectory() as folder:
        dataset = LeRobotDataset("local/latents", root=write_random_latent_dataset(Path(folder), CAMERAS[:2], episodes))
        dataset[0]  # loads the table
        table = dataset.hf_dataset
        codes = [c for c in table.column_names if c.startswith(LATENTS_PREFIX)]
        without_codes = table.remove_columns(codes)
        without_goals = table.remove_columns([c for c in codes if is_goal(c)])
        encoder = VQVAEConfig()
        unpacked = without_codes
        for column in codes:
            packed = np.stack(table.with_format("numpy")[column])
            indices = unpack_codes(packed, encoder.codebook_size, encoder.grid_size**2)
            unpacked = unpacked.add_column(column, list(indices.astype(np.int16)))
        for part in (without_codes, without_goals, unpacked):
            part.set_transform(hf_transform_to_torch)
        picked = np.random.default_rng(0).integers(0, len(dataset), rows).tolist()

        def ms_per_row(read) -> float:
            start = time.process_time()
            for i in picked:
                read(i)
            return 1e3 * (time.process_time() - start) / rows

        print("| what is read | CPU ms per row |\n|---|---:|")
        for label, read in (
            ("`LeRobotDataset.__getitem__`", dataset.__getitem__),
            ("the row through `datasets` with LeRobot's torch transform, codes packed", table.__getitem__),
            ("the same, codes as 144 int16 an image (the layout before)", unpacked.__getitem__),
            ("the same, packed, without the goal-code columns", without_goals.__getitem__),
            ("the same without any code column", without_codes.__getitem__),
            ("the row as Arrow (no conversion)", table.with_format("arrow").__getitem__),
        ):
            print(f"| {label} | {ms_per_row(read):.3f} |")


def compare_trainers(
    batch: int,
    num_workers: int,
    repeats: int,
    threads: int | None,
    steps: int = 150,
    episodes: int = 1000,
    device: torch.device = torch.device("cpu"),
) -> None:
    """Time per update of murm train and of lerobot-train, alternately, on one latent dataset
    (separated Q, two cameras). lerobot-train's per-step time is the difference between a run of
    `steps` + 10 and one of 10 updates, so its start (imports, loading the dataset) cancels out.
    On the CPU it is CPU time, not wall time: it does not depend on what else the machine runs,
    and on a machine whose cores are busy (2 here) updates/s is inversely proportional to it. On
    a GPU it is wall time (the machine is assumed idle), which is what a GPU user waits for."""
    cameras = CAMERAS[:2]
    unit = "CPU ms" if device.type == "cpu" else "wall ms"
    with tempfile.TemporaryDirectory() as folder:
        latents = write_random_latent_dataset(Path(folder), cameras, episodes)
        encoder_dir = Path(folder) / "vqvae"
        config = MurmConfig(method="separated_q", cameras=cameras, encoder_dir=str(encoder_dir), epsilon=[2.0, 2.0])
        policy = build_policy(config, LeRobotDataset("local/latents", root=latents), device).train()
        replay = replay_for_dataset(config, LeRobotDataset("local/latents", root=latents), None, device)
        fast, slow = [], []
        for _ in range(repeats):
            fast.append(fast_s_per_step(policy, replay, batch, steps, device))
            short = lerobot_train_s(latents, encoder_dir, cameras, batch, 10, num_workers, threads, device)
            long = lerobot_train_s(latents, encoder_dir, cameras, batch, steps + 10, num_workers, threads, device)
            slow.append((long - short) / steps)
            print(
                f"  {unit} per update: murm train {1e3 * fast[-1]:.1f}, lerobot-train {1e3 * slow[-1]:.1f} "
                f"(its start: {short:.1f} s)",
                flush=True,
            )
    f, s = statistics.median(fast), statistics.median(slow)
    print(
        f"\nseparated_q, 2 cameras, batch {batch}, {episodes * 100} frames, device {device}, torch threads "
        f"{torch.get_num_threads()}, lerobot-train --num_workers={num_workers}: "
        f"{unit} per update: murm train {1e3 * f:.1f}, lerobot-train {1e3 * s:.1f}"
    )
    print(f"lerobot-train / murm train: {f / s:.2f}")


SEED_CASES = [("single", 1), ("separated_q", 2)]


def seed_policies(method: str, cameras: list[str], device: torch.device, seeds: int) -> list[MurmPolicy]:
    """Policies of `seeds` seeds (own initialisations) sharing one set of encoders, as a cell's."""
    policies = []
    for seed in range(seeds):
        torch.manual_seed(seed)
        policies.append(make_policy(method, cameras, device).train())
        policies[-1].encoders.load_state_dict(policies[0].encoders.state_dict())
    return policies


def seed_setup(method: str, n_cameras: int, seeds: int, batch: int, device: torch.device, graph: bool = False):
    """A lone seed's and a K-seed stack's `murm train` updates (sampling, update, logged values
    summed on the device) over one synthetic replay."""
    cameras = CAMERAS[:n_cameras]
    policies = seed_policies(method, cameras, device, seeds + 1)
    caches = [synthetic_cache(c, seed=i) for i, c in enumerate(cameras)]
    actions = np.random.default_rng(0).uniform(-1, 1, (len(caches[0].indices), 4)).astype(np.float32)
    c = policies[0].config
    replay = LatentReplay(caches, actions, c.epsilon, c.her_ratio, device=device)
    for policy in policies:
        policy.fit_latent_statistics(replay.latents)
    lone, stack = LoneSeed(policies[0]), SeedStack(policies[1:])

    def updates(updater, generators) -> Updates:
        if graph:
            make_capturable(updater.optimizer)
        return Updates(
            lambda: updater.step(replay.sample_stacked(batch, generators)),
            CudaGraph(generators) if graph else None,
            device=device,
        )

    generators = [torch.Generator(device=device).manual_seed(s) for s in range(seeds + 1)]
    return replay, lone, stack, updates(lone, generators[:1]), updates(stack, generators[1:]), generators


def measure_seeds(
    method: str,
    n_cameras: int,
    seeds: int,
    batch: int,
    device: torch.device,
    steps: int,
    repeats: int,
    graph: bool = False,
) -> dict:
    """Seed-updates/s of one seed alone and of `seeds` stacked, in alternating blocks."""
    _, _, _, lone, stacked, _ = seed_setup(method, n_cameras, seeds, batch, device, graph)
    wall = {"lone": [], "stack": []}
    cpu = {"lone": [], "stack": []}
    for repeat in range(repeats + 1):  # the first round warms up and is not counted
        for label, updates in (("lone", lone), ("stack", stacked)):
            _sync(device)
            start, cpu_start = time.perf_counter(), time.process_time()
            for _ in range(steps):
                updates()
            updates.read()  # the trainer reads the losses back every log_every steps
            if repeat:
                wall[label].append((time.perf_counter() - start) / steps)
                cpu[label].append((time.process_time() - cpu_start) / steps)
    lone_s, stack_s = statistics.median(wall["lone"]), statistics.median(wall["stack"])
    return {
        "method": method,
        "cameras": n_cameras,
        "lone": 1 / lone_s,
        "stack": seeds / stack_s,
        "ratio": seeds * lone_s / stack_s,
        "cpu_ratio": seeds * statistics.median(cpu["lone"]) / statistics.median(cpu["stack"]),
    }


def profile_seeds(method: str, n_cameras: int, seeds: int, batch: int, device: torch.device, repeats: int = 15) -> None:
    """CPU ms per seed of each part of the update, alone and stacked: what stacking shares."""
    replay, lone, stack, _, _, generators = seed_setup(method, n_cameras, seeds, batch, device)

    def ms(fn) -> float:
        for _ in range(3):
            fn()
        times = []
        for _ in range(repeats):
            start = time.process_time()
            fn()
            times.append(time.process_time() - start)
        return 1e3 * statistics.median(times)

    def parts_of(updater, gens) -> dict[str, float]:
        batch_ = replay.sample_stacked(batch, gens)

        def forward_backward() -> None:
            if isinstance(updater, SeedStack):
                loss = updater.loss(batch_)[0].sum()
            else:
                with matmul_precision(updater._precision, device):
                    loss = updater.policies[0].iql_loss({k: v[0] for k, v in batch_.transition().items()})[0]
            loss.backward()

        def forward() -> None:
            with torch.no_grad():
                if isinstance(updater, SeedStack):
                    updater.loss(batch_)
                else:
                    with matmul_precision(updater._precision, device):
                        updater.policies[0].iql_loss({k: v[0] for k, v in batch_.transition().items()})

        parts = {"sample": ms(lambda: replay.sample_stacked(batch, gens)), "forward (no grad)": ms(forward)}
        parts["forward + backward"] = ms(lambda: (updater.optimizer.zero_grad(set_to_none=True), forward_backward()))
        parts["Adam"] = ms(updater.optimizer.step)
        polyak = updater.update_targets if isinstance(updater, SeedStack) else updater.policies[0].update
        parts["Polyak"] = ms(polyak)
        parts["whole update"] = ms(lambda: updater.step(replay.sample_stacked(batch, gens)))
        return parts

    rows = [
        (label, len(gens), parts_of(updater, gens))
        for label, updater, gens in (("alone", lone, generators[:1]), (f"{seeds} stacked", stack, generators[1:]))
    ]
    print(f"\n{method}, {n_cameras} camera(s): CPU ms per seed (medians of {repeats})\n")
    print("| part | " + " | ".join(label for label, *_ in rows) + " | stacked / alone |")
    print("|---|" + "---:|" * (len(rows) + 1))
    for part in rows[0][2]:
        values = [parts[part] / k for _, k, parts in rows]
        print(f"| {part} | " + " | ".join(f"{v:.2f}" for v in values) + f" | {values[1] / values[0]:.2f} |")


def eval_share(seeds: int, device: torch.device, repeats: int = 1) -> None:
    """Share of a `seeds`-seed separated-Q cell's wall time spent evaluating, at the reproduce
    defaults (TrainSpec: evaluations every eval_every updates, the final validation and test
    evaluations), from a timed stacked evaluation of eval_episodes episodes in the simulator
    (48x48, two cameras, random encoders: an episode's cost does not depend on the policy)
    and the stacked training rate."""
    spec = TrainSpec()
    cameras = CAMERAS[:2]
    rate = measure_seeds("separated_q", 2, seeds, spec.batch_size, device, 20, 3)
    for k, seeds_per_s in ((1, rate["lone"]), (seeds, rate["stack"])):
        policies = seed_policies("separated_q", cameras, device, k)
        with Evaluator("place_in_box", cameras, 48, spec.eval_envs, policies=k) as evaluator:
            evaluator.evaluate(policies, evaluation_seeds(spec.eval_envs, 0))  # the workers' first episodes
            seconds = min(
                evaluator.evaluate(policies, evaluation_seeds(spec.eval_episodes, 200_000))[0].seconds
                for _ in range(repeats)
            )
        evaluations = spec.steps // spec.eval_every - 1  # the last one is the final evaluation
        eval_s = seconds * (evaluations + 2 * spec.final_eval_episodes / spec.eval_episodes)
        train_s = spec.steps * k / seeds_per_s
        print(
            f"{k} seed(s): {spec.eval_episodes} episodes each in {seconds:.1f} s; a cell of {spec.steps} updates: "
            f"training {train_s / 60:.0f} min, evaluating {eval_s / 60:.0f} min: "
            f"{100 * eval_s / (eval_s + train_s):.0f} % of its wall time evaluating"
        )


def gpu_seeds(batch: int, device: torch.device, steps: int, repeats: int) -> None:
    """On a GPU: separated Q, two cameras; one seed's updates/s with and without a CUDA graph,
    and aggregate seed-updates/s of 1, 3, 10 and 30 stacked seeds with it."""
    print(f"GPU: {torch.cuda.get_device_name(device)}; torch {torch.__version__}, batch {batch}\n")
    print("| seeds stacked | CUDA graph | one seed alone, updates/s | stacked, seed-updates/s |\n|---:|---|---:|---:|")
    for seeds, graph in ((1, False), (1, True), (3, True), (10, True), (30, True)):
        r = measure_seeds("separated_q", 2, seeds, batch, device, steps, repeats, graph)
        print(f"| {seeds} | {'yes' if graph else 'no'} | {r['lone']:.0f} | {r['stack']:.0f} |", flush=True)


def seeds_together(
    seeds: int, batch: int, device: torch.device, steps: int, repeats: int, profile: bool, share: bool
) -> None:
    results = [measure_seeds(m, n, seeds, batch, device, steps, repeats) for m, n in SEED_CASES]
    print(
        f"CPU: {cpu_model()}; device {device}, torch {torch.__version__}, threads {torch.get_num_threads()}, "
        f"batch {batch}, default precision {str(resolve_precision('auto', device)).removeprefix('torch.')}, "
        f"load average {os.getloadavg()[0]:.1f} at the end\n"
    )
    print("| method | cameras | one seed alone, updates/s | seeds stacked, seed-updates/s | ratio | CPU-time ratio |")
    print("|---|---:|---:|---:|---:|---:|")
    for r in results:
        print(
            f"| {r['method']} | {r['cameras']} | {r['lone']:.1f} | {r['stack']:.1f} | {r['ratio']:.2f} | "
            f"{r['cpu_ratio']:.2f} |"
        )
    print(f"\nseeds together, {seeds} seeds: {min(r['ratio'] for r in results):.2f}")
    if profile:
        for m, n in SEED_CASES:
            profile_seeds(m, n, seeds, batch, device)
    if share:
        eval_share(seeds, device)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--threads", type=int, default=None, help="torch threads (default: torch's choice)")
    parser.add_argument("--batch-size", type=int, default=256)
    parser.add_argument("--steps", type=int, default=30)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument(
        "--widths",
        choices=[*WIDTHS, "both"],
        default="both",
        help="per_camera: 128 units per camera (the default); fixed: 128 units everywhere",
    )
    parser.add_argument(
        "--cases", nargs="*", default=None, metavar="METHOD:CAMERAS", help="e.g. separated_q:2 (default: all six)"
    )
    parser.add_argument("--lerobot-train", action="store_true", help="also compare with lerobot-train")
    parser.add_argument("--lerobot-train-only", action="store_true", help="only compare with lerobot-train")
    parser.add_argument("--num-workers", type=int, default=2, help="lerobot-train's --num_workers")
    parser.add_argument("--episodes", type=int, default=1000, help="episodes of 100 frames in the latent dataset")
    parser.add_argument("--row-costs", action="store_true", help="only the per-row cost of LeRobot's loader")
    parser.add_argument(
        "--seeds-together",
        type=int,
        default=0,
        metavar="K",
        help="only K seeds stacked against one alone (single view, separated Q with two cameras)",
    )
    parser.add_argument("--profile", action="store_true", help="with --seeds-together: where each update goes")
    parser.add_argument("--eval-share", action="store_true", help="with --seeds-together: the share spent evaluating")
    parser.add_argument("--gpu-seeds", action="store_true", help="only the CUDA-graph and 1/3/10/30-seed table (GPU)")
    args = parser.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    if args.row_costs:
        return row_costs()
    if args.gpu_seeds:
        return gpu_seeds(args.batch_size, torch.device(args.device), args.steps, args.repeats)
    if args.seeds_together:
        return seeds_together(
            args.seeds_together,
            args.batch_size,
            torch.device(args.device),
            args.steps,
            args.repeats,
            args.profile,
            args.eval_share,
        )
    if args.lerobot_train_only:
        return compare_trainers(
            args.batch_size,
            args.num_workers,
            args.repeats,
            args.threads,
            args.steps,
            args.episodes,
            torch.device(args.device),
        )
    device = torch.device(args.device)
    cases = [(m, int(n)) for m, n in (c.split(":") for c in args.cases)] if args.cases else CASES
    widths = list(WIDTHS) if args.widths == "both" else [args.widths]
    default_dtype = resolve_precision("auto", device)
    dtypes = {"fp32": torch.float32, "default": default_dtype}
    peak_before = {label: matmul_gflops(device, dtype) for label, dtype in dtypes.items()}
    results = [
        measure(m, n, w, args.batch_size, device, args.steps, args.repeats)
        for w in widths
        for m, n in cases
        if not (w == "fixed" and n == 1 and len(widths) > 1)
    ]  # the same at 1 camera
    # the better of two measurements: the stricter ratio
    peak = {label: max(peak_before[label], matmul_gflops(device, dtype)) for label, dtype in dtypes.items()}
    print(
        f"CPU: {cpu_model()}; device {device}, torch {torch.__version__}, threads {torch.get_num_threads()}, "
        f"batch {args.batch_size}, default precision {str(default_dtype).removeprefix('torch.')}"
    )
    print(
        f"dense 2048^3 matmul: fp32 {peak['fp32']:.0f} GFLOP/s, default {peak['default']:.0f} GFLOP/s "
        f"(before the runs {peak_before['fp32']:.0f} / {peak_before['default']:.0f})\n"
    )
    print(
        "| method | cameras | hidden (Q/V/policy) | fp32 steps/s | default steps/s | speedup | "
        "update ms fp32 / default | sample ms | GFLOP/update | % of fp32 peak, fp32 | % of default peak, default | "
        "CPU ms/step fp32 / default | CPU-time speedup |"
    )
    print("|---|---:|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|")
    for r in results:
        f, d = r["fp32"], r["default"]
        print(
            f"| {r['method']} | {r['cameras']} | {r['hidden']} | "
            f"{f['steps_per_s']:.1f} | {d['steps_per_s']:.1f} | {r['speedup']:.2f}x | "
            f"{f['update_ms']:.1f} / {d['update_ms']:.1f} | {d['sample_ms']:.1f} | {r['gflop']:.2f} | "
            f"{100 * f['gflops'] / peak['fp32']:.0f} % | {100 * d['gflops'] / peak['default']:.0f} % | "
            f"{f['cpu_ms']:.1f} / {d['cpu_ms']:.1f} | {r['cpu_speedup']:.2f}x |"
        )
    two = [r for r in results if r["cameras"] == 2]
    if two:  # the smallest over the two-camera cases: the claim holds for every method and width
        wall, cpu = [r["speedup"] for r in two], [r["cpu_speedup"] for r in two]
        print(
            f"\nspeedup over fp32 eager, two cameras: {min(wall):.2f} (smallest of {len(two)} cases; "
            f"median {statistics.median(wall):.2f}; in CPU time: smallest {min(cpu):.2f}, median "
            f"{statistics.median(cpu):.2f})"
        )
    by_case = {(r["method"], r["cameras"]): r for r in results if r["widths"] == widths[0]}
    if ("single", 1) in by_case:
        single = by_case[("single", 1)]["default"]["steps_per_s"]
        print(
            f"\ntime per step relative to single-view, {widths[0]} widths, default precision "
            "(paper Table 5: dropout 1.05, separated Q 1.55):"
        )
        for (method, n), r in by_case.items():
            if n > 1:
                print(f"  {method} with {n} cameras: {single / r['default']['steps_per_s']:.2f}")
    if args.lerobot_train:
        compare_trainers(
            args.batch_size, args.num_workers, args.repeats, args.threads, episodes=args.episodes, device=device
        )


if __name__ == "__main__":
    sys.exit(main())
