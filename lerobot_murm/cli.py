"""The `murm` command: one entry point for every stage of the pipeline."""

from __future__ import annotations

import argparse
import os
import signal
import sys
from collections.abc import Callable, Iterator
from contextlib import ExitStack, contextmanager, nullcontext
from pathlib import Path

from lerobot_murm.library_logs import held_back


def _demo(args: argparse.Namespace) -> None:
    from lerobot_murm.demo import run_demo

    results = run_demo(Path(args.out), seed=args.seed)
    if not all(r["success"] for r in results):
        print("note: the noiseless scripted expert failed an episode (see the rollout PNGs)")


# the CollectConfig fields `murm collect` takes as options (first_episode is a shard's)
COLLECT_OPTIONS = (
    "task",
    "root",
    "episodes",
    "workers",
    "repo_id",
    "cameras",
    "image_size",
    "seed",
    "noise_std",
    "noisy_fraction",
    "resume",
    "overwrite",
    "flush_every",
)
# the VQVAEConfig fields `murm train-vqvae` takes as options
VQVAE_OPTIONS = ("steps", "batch_size", "seed", "image_size", "codebook_size")


def _collect(args: argparse.Namespace) -> None:
    from lerobot_murm.collection import CollectConfig, collect
    from lerobot_murm.config_args import config_arguments

    config = CollectConfig(**config_arguments(args, COLLECT_OPTIONS))
    summary = collect(config)
    print(f"{summary['episodes']} episodes in {config.root}, expert success {summary['success_rate']:.1%}")
    if args.push_to_hub:
        _push(argparse.Namespace(root=args.root, repo_id=config.repo_id, private=args.private))


def _push(args: argparse.Namespace) -> None:
    from lerobot_murm.publishing import push_dataset

    push_dataset(Path(args.root), args.repo_id, private=args.private)
    print(f"pushed {args.root} to https://huggingface.co/datasets/{args.repo_id}")


def _pull(args: argparse.Namespace) -> None:
    from lerobot_murm.checks import check_writable
    from lerobot_murm.publishing import pull_dataset

    check_writable(Path(args.root))
    dataset = pull_dataset(args.repo_id, Path(args.root))
    print(f"pulled {args.repo_id} into {args.root}: {dataset.meta.total_episodes} episodes, {len(dataset)} frames")


def _train_vqvae(args: argparse.Namespace) -> None:
    from dataclasses import replace

    from lerobot_murm.checks import check_writable
    from lerobot_murm.config_args import config_arguments
    from lerobot_murm.features import IMAGES_PREFIX
    from lerobot_murm.vqvae import VQVAEConfig
    from lerobot_murm.vqvae.frames import dataset_location
    from lerobot_murm.vqvae.train import train_vqvae

    config = replace(VQVAEConfig(), **config_arguments(args, VQVAE_OPTIONS))
    repo_id, root = dataset_location(args.dataset)
    camera = args.camera.removeprefix(IMAGES_PREFIX)  # the policy finds it as ENCODER_DIR/<camera>
    out = Path(args.out or f"outputs/vqvae/{Path(args.dataset).name}/{camera}")
    check_writable(out)
    metrics = train_vqvae(repo_id, root, args.camera, out, config, device=args.device)
    held = metrics["heldout"]
    print(
        f"{camera}: held-out PSNR {held['psnr_db']:.1f} dB (MSE {held['mse']:.5f}), codebook perplexity "
        f"{held['perplexity']:.0f}, {held['unused_codes']} unused codes; saved to {out}"
    )


def _encode(args: argparse.Namespace) -> None:
    from lerobot_murm.checks import check_writable
    from lerobot_murm.locking import exclusive
    from lerobot_murm.vqvae.encoder_files import check_encoder
    from lerobot_murm.vqvae.frames import dataset_location

    if args.to_dataset and Path(args.to_dataset).exists():
        raise SystemExit(f"murm encode: {args.to_dataset} exists; remove it or choose another --to-dataset folder")
    repo_id, root = dataset_location(args.dataset)
    cache_dir = Path(args.cache_dir)
    check_writable(cache_dir)
    for encoder in args.encoders:
        check_encoder(Path(encoder))  # a missing or torn encoder fails before any work
    with ExitStack() as locks:
        for written in [cache_dir] + ([Path(args.to_dataset)] if args.to_dataset else []):
            locks.enter_context(exclusive(written))
        _encode_locked(args, repo_id, root, cache_dir)


def _encode_locked(args: argparse.Namespace, repo_id: str, root: Path | None, cache_dir: Path) -> None:
    import json

    from lerobot_murm.checkpointing import write_atomic
    from lerobot_murm.collection.dataset import episode_successes
    from lerobot_murm.vqvae.frames import open_dataset
    from lerobot_murm.vqvae.latent_cache import build_latent_cache
    from lerobot_murm.vqvae.latent_distance import (
        distance_statistics,
        plot_distances,
        public_statistics,
        save_beside_encoder,
    )

    open_dataset(repo_id, root)  # a missing or unreadable dataset fails here, in one line
    successes = episode_successes(repo_id, root)
    stats, caches = [], []
    for encoder in args.encoders:
        cache = build_latent_cache(repo_id, root, Path(encoder), cache_dir, device=args.device)
        stats.append(distance_statistics(cache, successes))
        save_beside_encoder(stats[-1], Path(encoder))
        suggested = stats[-1]["suggested_epsilon"]
        print(f"{cache.camera}: {len(cache.indices)} frames cached; suggested epsilon {suggested:.2f}")
        caches.append(cache)
    public = [public_statistics(s) for s in stats]
    write_atomic(cache_dir / "epsilon.json", (json.dumps(public, indent=2) + "\n").encode())
    plot_distances(stats, cache_dir / "latent_distances.png")
    print(f"wrote {cache_dir / 'epsilon.json'} and {cache_dir / 'latent_distances.png'}")
    if args.to_dataset:
        _write_latents(args, repo_id, root, caches)


def _write_latents(args: argparse.Namespace, repo_id: str, root: Path | None, caches: list) -> None:
    import shlex

    from lerobot_murm.vqvae.frames import open_dataset
    from lerobot_murm.vqvae.latent_dataset import write_latent_dataset

    out = Path(args.to_dataset)
    latent_repo_id = args.repo_id or f"local/{out.name}"
    command = shlex.join(
        ["murm", "encode", "--dataset", args.dataset, "--encoders", *args.encoders, "--to-dataset", str(out)]
    )
    dataset = write_latent_dataset(
        open_dataset(repo_id, root), caches, [Path(e) for e in args.encoders], out, latent_repo_id, command
    )
    print(
        f"latent dataset {out}: {dataset.meta.total_episodes} episodes, {len(dataset)} frames, "
        f"codes of {', '.join(c.camera for c in caches)}"
    )
    if args.push_to_hub:
        _push(argparse.Namespace(root=out, repo_id=latent_repo_id, private=args.private))


def _check_encoders(args: argparse.Namespace) -> None:
    from lerobot_murm.vqvae.frames import dataset_location
    from lerobot_murm.vqvae.object_pixels import check_encoders, object_pixels_table

    repo_id, root = dataset_location(args.dataset)
    try:
        results = check_encoders(repo_id, root, [Path(e) for e in args.encoders], args.episodes, device=args.device)
    except ValueError as error:
        raise SystemExit(f"murm check-encoders: {error}") from None
    print(object_pixels_table(results))
    print("wrote object_pixels.json and object_reconstructions.png beside each encoder")


def _train(args: argparse.Namespace) -> None:
    from lerobot_murm.training.train import load_train_config, train

    for summary in train(load_train_config(args.config, args.overrides)):
        for row in summary["final"]:
            print(
                f"{summary['task']} {summary['method']} {'+'.join(summary['cameras'])} seed {summary['seed']} "
                f"masking {row['mask_p']:.0%}: success {100 * row['success_rate']:.1f} % "
                f"over {row['episodes']} episodes"
            )
        print(f"checkpoint: {summary['checkpoint']}")


@contextmanager
def _sigterm_as_ctrl_c() -> Iterator[None]:
    """SIGTERM (`kill`, a scheduler's preemption) stops a grid's driver as Ctrl-C does: its
    jobs save their checkpoints, its pool closes and it says where it stopped. Left to its
    default, SIGTERM ended the driver at once, silently, and multiprocessing's resource
    tracker then reported the pool's semaphores as leaked. A second SIGTERM is ignored while
    the jobs save (kill -9 still ends everything; the jobs then stop with their driver)."""

    def interrupt(*_: object) -> None:
        signal.signal(signal.SIGTERM, signal.SIG_IGN)
        raise KeyboardInterrupt

    previous = signal.signal(signal.SIGTERM, interrupt)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


def _reproduce(args: argparse.Namespace) -> None:
    from lerobot_murm.experiments.configuration_reproduce import load_reproduce_config
    from lerobot_murm.experiments.executors import make_executor
    from lerobot_murm.experiments.reproduce import reproduce
    from lerobot_murm.training_loop import TrainingInterrupted

    config = load_reproduce_config(args.config, args.overrides)
    if config.budget is not None:
        whole = load_reproduce_config(args.config)
        if (config.tasks, config.seeds, config.cells) != (whole.tasks, whole.seeds, whole.cells):
            raise ValueError(
                f"{config.name} chooses one budget over all its runs, so it runs whole: drop --tasks, --seeds "
                "and --cells (a stopped sitting resumes where it was)"
            )
    executor = make_executor(
        args.executor, args.jobs, args.address, args.cpus_per_task, args.gpus_per_task, args.shard_episodes
    )  # a bad flag: ValueError, one line
    with _sigterm_as_ctrl_c():
        try:
            out = reproduce(config, executor)
        except TrainingInterrupted as stop:
            raise TrainingInterrupted(f"{stop}; finished cells are kept") from None
        except KeyboardInterrupt:  # the driver of --jobs / --executor ray; its jobs save their checkpoints
            raise TrainingInterrupted(
                "stopped; finished cells are kept, run the same command again to resume"
            ) from None
        finally:
            executor.close()
    print(f"tables and figures: {out}")


def _status(args: argparse.Namespace) -> None:
    from lerobot_murm.experiments.best_views import choose_views
    from lerobot_murm.experiments.configuration_reproduce import load_reproduce_config
    from lerobot_murm.experiments.grid_status import (
        grid_status,
        hours_left,
        plot_status,
        status_markdown,
        time_left_line,
    )

    if args.plot and len(args.config) > 1:
        raise ValueError("--plot draws one grid's curves: give one --config with it")
    grids = []
    for path in args.config:
        config = load_reproduce_config(path, args.overrides)
        if config.prepare_only:
            print(
                f"{config.name}: builds datasets and encoders only, no training run (murm reproduce says where it is)"
            )
            continue
        config, _, waiting = choose_views(config)
        grids.append((config, grid_status(config), waiting))
    every_cell = [cell for _, cells, _ in grids for cell in cells]  # a later grid's cells costed by earlier ones'
    every_left = []
    for k, (config, cells, waiting) in enumerate(grids):
        left = [hours_left(cell, every_cell, config) for cell in cells]
        every_left += left
        print(("\n" if k else "") + status_markdown(config, cells, left, waiting), end="")
    if len(grids) > 1:
        print(f"\nall {len(grids)} grids: {time_left_line(every_left, 'to their caps; their tests come after')}")
    if args.plot:
        if plot_status(grids[0][1] if grids else [], Path(args.plot)):
            print(f"validation curves so far: {args.plot}")
        else:
            print("no validation point yet: no figure")


def _report(args: argparse.Namespace) -> None:
    from lerobot_murm.experiments.report import update_readme, write_report

    if not Path(args.results).is_dir():
        raise FileNotFoundError(f"no results folder {args.results} (murm reproduce writes it)")
    preface = Path(args.preface).read_text() if args.preface else ""
    print(f"wrote {write_report(Path(args.results), Path(args.out), preface)}")
    if args.readme and Path(args.readme).exists():
        filled = update_readme(Path(args.results), Path(args.readme))
        print(f"{args.readme}: results of {', '.join(filled) or 'no grid'} refreshed")


def _config_file(value: str) -> str:
    """`--config`: a missing or unreadable file is bad input (exit 2), found before any work."""
    if not Path(value).is_file() or not os.access(value, os.R_OK):
        raise argparse.ArgumentTypeError(f"no readable config file {value}")
    return value


class OneLineErrors(argparse.ArgumentParser):
    """A subcommand's bad arguments in one line (exit 2) instead of its whole usage. Options
    generated from a stage config (`generated_options`) are added when the subcommand is
    parsed, so that `murm` imports a stage's code only for that stage's command."""

    generated_options: Callable[[argparse.ArgumentParser], None] | None = None

    def error(self, message: str) -> None:
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")

    def parse_known_args(self, args=None, namespace=None):
        if self.generated_options is not None:
            add, self.generated_options = self.generated_options, None
            add(self)
        return super().parse_known_args(args, namespace)


def _collect_options(parser: argparse.ArgumentParser) -> None:
    from lerobot_murm.collection import CollectConfig
    from lerobot_murm.config_args import add_config_arguments

    add_config_arguments(parser, CollectConfig, COLLECT_OPTIONS)


def _vqvae_options(parser: argparse.ArgumentParser) -> None:
    from lerobot_murm.config_args import add_config_arguments
    from lerobot_murm.vqvae import VQVAEConfig

    add_config_arguments(parser, VQVAEConfig, VQVAE_OPTIONS)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="murm", description="MURM: multi-view goal-conditioned offline RL")
    parser.add_argument("--debug", action="store_true", help=f"errors show their traceback (or set {DEBUG_VARIABLE}=1)")
    commands = parser.add_subparsers(dest="command", required=True, parser_class=OneLineErrors)

    demo = commands.add_parser("demo", help="render every task's cameras and goals, run one expert episode each")
    demo.add_argument("--out", default="outputs/demo", help="folder for the PNGs (default: %(default)s)")
    demo.add_argument("--seed", type=int, default=0, help="episode seed (default: %(default)s)")
    demo.set_defaults(func=_demo)

    col = commands.add_parser("collect", help="collect scripted-expert demonstrations into a LeRobotDataset")
    col.generated_options = _collect_options  # --task, --root, ... --flush-every: CollectConfig's fields
    col.add_argument("--push-to-hub", action="store_true", help="push to --repo-id when done")
    col.add_argument("--private", action="store_true", help="with --push-to-hub: a private Hub repo")
    col.set_defaults(func=_collect)

    push = commands.add_parser("push", help="push a collected dataset and its card to the Hugging Face Hub")
    push.add_argument("--root", required=True, help="the dataset folder")
    push.add_argument("--repo-id", required=True, help="e.g. user/murm_place_in_box")
    push.add_argument("--private", action="store_true")
    push.set_defaults(func=_push)

    pull = commands.add_parser("pull", help="download a dataset from the Hugging Face Hub")
    pull.add_argument("--repo-id", required=True)
    pull.add_argument("--root", required=True, help="folder to download into")
    pull.set_defaults(func=_pull)

    vq = commands.add_parser("train-vqvae", help="train one camera's VQ-VAE on a LeRobotDataset's camera stream")
    vq.add_argument("--dataset", required=True, help="a dataset folder or a Hub repo id")
    vq.add_argument("--camera", required=True, help="an image or video stream: laptop or observation.images.laptop")
    vq.generated_options = _vqvae_options  # --steps, --batch-size, --seed, ...: VQVAEConfig's fields
    vq.add_argument("--out", default=None, help="checkpoint folder (default: outputs/vqvae/DATASET/CAMERA)")
    vq.add_argument("--device", default="auto", help="cpu, cuda or auto (default)")
    vq.set_defaults(func=_train_vqvae)

    enc = commands.add_parser("encode", help="build the latent cache and the epsilon statistics (and a latent dataset)")
    enc.add_argument("--dataset", required=True, help="a dataset folder or a Hub repo id")
    enc.add_argument("--encoders", nargs="+", required=True, help="VQ-VAE checkpoint folders, one per camera")
    enc.add_argument("--cache-dir", default="outputs/latent_cache")
    enc.add_argument("--device", default="cpu")
    enc.add_argument(
        "--to-dataset",
        default=None,
        metavar="DIR",
        help="also write a LeRobotDataset of the cameras' codes, without images, to this new folder",
    )
    enc.add_argument("--repo-id", default=None, help="with --to-dataset: its Hub id (default: local/DIR's name)")
    enc.add_argument("--push-to-hub", action="store_true", help="with --to-dataset: push it to --repo-id")
    enc.add_argument("--private", action="store_true", help="with --push-to-hub: a private Hub repo")
    enc.set_defaults(func=_encode)

    check = commands.add_parser(
        "check-encoders",
        help="reconstruction error on the object's pixels of held-out frames (simulated again for the masks)",
    )
    check.add_argument("--dataset", required=True, help="the dataset folder the encoders were trained on")
    check.add_argument("--encoders", nargs="+", required=True, help="VQ-VAE checkpoint folders, one per camera")
    check.add_argument("--episodes", type=int, default=None, help="at most this many held-out episodes (default: all)")
    check.add_argument("--device", default="cpu")
    check.set_defaults(func=_check_encoders)

    tr = commands.add_parser(
        "train",
        help="train a MURM policy fast from the latent cache (resumes when rerun)",
        epilog="Further --key=value arguments override the YAML, e.g. --steps=1000 --policy.method=dropout; "
        "--seeds=[0,1,2] trains three seeds side by side (in output_dir/seed0, ...)",
    )
    tr.add_argument(
        "--config", required=True, type=_config_file, help="a YAML file, e.g. configs/place_in_box/separated_q.yaml"
    )
    tr.set_defaults(accepts_overrides=True)  # any further --key=value overrides the YAML (draccus)

    rep = commands.add_parser(
        "reproduce",
        help="run an experiment grid from demonstrations to tables (skips finished runs)",
        epilog="Further --key=value arguments override the YAML, e.g. --seeds=[0] --train.steps=1000",
    )
    rep.add_argument("--config", required=True, type=_config_file, help="e.g. configs/reproduce/smoke.yaml")
    rep.add_argument(
        "--executor",
        choices=["local", "ray"],
        default="local",
        help="local (default) or ray: every stage a Ray task (needs the [ray] extra and a shared work_dir)",
    )
    rep.add_argument(
        "--jobs",
        type=int,
        default=1,
        help="local executor: runs at once, each with cores/JOBS torch threads (default: %(default)s)",
    )
    rep.add_argument(
        "--address", default=None, help="ray: the cluster's address (default: RAY_ADDRESS, else a new local one)"
    )
    rep.add_argument(
        "--cpus-per-task", type=int, default=1, help="ray: CPUs (torch threads) per encoder or training task"
    )
    rep.add_argument(
        "--gpus-per-task", type=float, default=0.0, help="ray: GPUs per encoder or training task (e.g. 1 or 0.25)"
    )
    rep.add_argument(
        "--shard-episodes", type=int, default=100, help="ray: episodes per collection task (default: %(default)s)"
    )
    rep.set_defaults(func=_reproduce, accepts_overrides=True)

    st = commands.add_parser(
        "status",
        help="where a grid stands: each cell's state, step, validation success and time left (reads only)",
        epilog="Give the grid's own --work_dir=... and --results_dir=... overrides if it ran with them",
    )
    st.add_argument(
        "--config",
        required=True,
        action="append",
        type=_config_file,
        help="the grid's config, e.g. configs/reproduce/table3.yaml; given again for each grid of a study "
        "(cells not started are costed by any grid's like cells, and the time left summed)",
    )
    st.add_argument("--plot", default=None, metavar="PNG", help="also draw the seeds' mean validation curves so far")
    st.set_defaults(func=_status, accepts_overrides=True)

    report = commands.add_parser("report", help="REPORT.md: every finished grid in results/ beside the paper's tables")
    report.add_argument("--results", default="results")
    report.add_argument("--out", default="REPORT.md")
    report.add_argument("--preface", default="docs/report_preface.md", help="Markdown put before the tables")
    report.add_argument(
        "--readme", default="README.md", help="its <!-- results:NAME --> blocks get NAME's table; '' leaves it alone"
    )
    report.set_defaults(func=_report)
    tr.set_defaults(func=_train)
    return parser


DEBUG_VARIABLE = "MURM_DEBUG"  # set to 1: errors show their traceback, as with --debug


def _exit_code(error: Exception) -> int | None:
    """2 for bad input (usage; a missing or unreadable input: no such file or folder, a torn
    dataset or encoder), 1 for a failure the user can act on, None for a bug (which keeps its
    traceback)."""
    from draccus.utils import DraccusException

    from lerobot_murm.checkpointing import CheckpointError
    from lerobot_murm.collection.collect import CollectionInterrupted
    from lerobot_murm.collection.durability import UnrepairableCollection
    from lerobot_murm.locking import FolderInUse
    from lerobot_murm.publishing import HubUnavailable
    from lerobot_murm.training_loop import TrainingInterrupted
    from lerobot_murm.vqvae.encoder_files import IncompleteEncoder
    from lerobot_murm.vqvae.frames import UnreadableDataset

    if isinstance(error, ValueError | DraccusException | FileNotFoundError | UnreadableDataset | IncompleteEncoder):
        return 2
    failures = (
        OSError,
        CheckpointError,
        CollectionInterrupted,
        UnrepairableCollection,
        HubUnavailable,
        TrainingInterrupted,
        FolderInUse,
    )
    return 1 if isinstance(error, failures) else None


def _unwrap(error: Exception) -> Exception:
    """What draccus wrapped while decoding a config (a config's own validation error, a missing file)."""
    from draccus.utils import DraccusException

    while isinstance(error, DraccusException) and isinstance(error.__cause__, Exception):
        error = error.__cause__
    return error


def _one_line(error: Exception) -> str:
    text = " ".join(line.strip() for line in str(error).splitlines() if line.strip())
    if isinstance(error, OSError) and error.filename and str(error.filename) not in text:
        text = f"{text}: {error.filename}"
    return text or type(error).__name__


def main(argv: list[str] | None = None) -> None:
    """Run a command; its errors end in one line on stderr (exit 2: bad input, 1: failure),
    with what LeRobot and datasets logged as errors held back (library_logs.py)."""
    parser = build_parser()
    args, extra = parser.parse_known_args(argv)
    debug = args.debug or "--debug" in extra or os.environ.get(DEBUG_VARIABLE, "") not in ("", "0")
    extra = [e for e in extra if e != "--debug"]
    if extra and not getattr(args, "accepts_overrides", False):
        print(
            f"murm {args.command}: error: unrecognized arguments: {' '.join(extra)} (see murm {args.command} --help)",
            file=sys.stderr,
        )
        raise SystemExit(2)
    args.overrides = extra
    held = None
    try:
        with nullcontext() if debug else held_back() as held:
            args.func(args)
    except Exception as raised:
        error = _unwrap(raised)
        code = _exit_code(error)
        if debug or code is None:
            raise
        logged = f" and the {held.errors} errors LeRobot or datasets logged" if held and held.errors else ""
        print(f"murm {args.command}: {_one_line(error)} (--debug shows where{logged})", file=sys.stderr)
        raise SystemExit(code) from None
    if held and held.errors:
        print(
            f"murm {args.command}: note: LeRobot or datasets logged {held.errors} errors, the first: {held.first} "
            "(--debug shows them all)",
            file=sys.stderr,
        )


if __name__ == "__main__":
    main()
