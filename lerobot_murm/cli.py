"""The `murm` command: one entry point for every stage of the pipeline."""

from __future__ import annotations

import argparse
from pathlib import Path


def _demo(args: argparse.Namespace) -> None:
    from lerobot_murm.demo import run_demo

    results = run_demo(Path(args.out), seed=args.seed)
    if not all(r["success"] for r in results):
        print("note: the noiseless scripted expert failed an episode (see the rollout PNGs)")


def _collect(args: argparse.Namespace) -> None:
    from lerobot_murm.collection import CollectConfig, collect
    from lerobot_murm.collection.collect import CollectionInterrupted

    config = CollectConfig(
        task=args.task,
        root=Path(args.root),
        episodes=args.episodes,
        workers=args.workers,
        repo_id=args.repo_id,
        cameras=tuple(args.cameras.split(",")),
        image_size=args.image_size,
        seed=args.seed,
        noise_k=args.noise_k,
        noisy_fraction=args.noisy_fraction,
        resume=args.resume,
        overwrite=args.overwrite,
    )
    try:
        summary = collect(config)
    except CollectionInterrupted as stop:
        raise SystemExit(f"murm collect: {stop}") from None
    print(f"{summary['episodes']} episodes in {config.root}, expert success {summary['success_rate']:.1%}")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="murm", description="MURM: multi-view goal-conditioned offline RL")
    commands = parser.add_subparsers(dest="command", required=True)

    demo = commands.add_parser("demo", help="render every task's cameras and goals, run one expert episode each")
    demo.add_argument("--out", default="outputs/demo", help="folder for the PNGs (default: %(default)s)")
    demo.add_argument("--seed", type=int, default=0, help="episode seed (default: %(default)s)")
    demo.set_defaults(func=_demo)

    col = commands.add_parser("collect", help="collect scripted-expert demonstrations into a LeRobotDataset")
    col.add_argument("--task", required=True, help="place_in_box, place_in_random_box or pick_up")
    col.add_argument("--root", required=True, help="dataset folder (created; never overwritten silently)")
    col.add_argument("--episodes", type=int, default=1000, help="episodes to have in the end (default: %(default)s)")
    col.add_argument("--workers", type=int, default=2, help="simulator processes (default: %(default)s)")
    col.add_argument("--repo-id", default=None, help="Hub id, e.g. user/murm_place_in_box (default: local/murm_TASK)")
    col.add_argument("--cameras", default="global,adjacent,side,top,active", help="comma-separated (default: all five)")
    col.add_argument("--image-size", type=int, default=48)
    col.add_argument("--seed", type=int, default=0, help="base seed: episode i depends on it and i alone")
    col.add_argument("--noise-k", type=float, default=1.0, help="expert noise k in a* + k N(0, 0.1) (default: 1)")
    col.add_argument("--noisy-fraction", type=float, default=1.0, help="share of noisy episodes (default: 1)")
    col.add_argument("--resume", action="store_true", help="carry on an interrupted or shorter collection")
    col.add_argument("--overwrite", action="store_true", help="delete an existing dataset at --root first")
    col.set_defaults(func=_collect)
    return parser


def main(argv: list[str] | None = None) -> None:
    args = build_parser().parse_args(argv)
    args.func(args)


if __name__ == "__main__":
    main()
