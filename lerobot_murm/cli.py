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
        noise_std=args.noise_std,
        resume=args.resume,
        overwrite=args.overwrite,
    )
    try:
        summary = collect(config)
    except CollectionInterrupted as stop:
        raise SystemExit(f"murm collect: {stop}") from None
    print(f"{summary['episodes']} episodes in {config.root}, expert success {summary['success_rate']:.1%}")
    if args.push_to_hub:
        _push(argparse.Namespace(root=args.root, repo_id=config.repo_id, private=args.private))


def _push(args: argparse.Namespace) -> None:
    from lerobot_murm.collection.hub import HubUnavailable, push_dataset

    try:
        push_dataset(Path(args.root), args.repo_id, private=args.private)
    except HubUnavailable as error:
        raise SystemExit(f"murm push: {error}") from None
    print(f"pushed {args.root} to https://huggingface.co/datasets/{args.repo_id}")


def _pull(args: argparse.Namespace) -> None:
    from lerobot_murm.collection.hub import HubUnavailable, pull_dataset

    try:
        dataset = pull_dataset(args.repo_id, Path(args.root))
    except HubUnavailable as error:
        raise SystemExit(f"murm pull: {error}") from None
    print(f"pulled {args.repo_id} into {args.root}: {dataset.meta.total_episodes} episodes, {len(dataset)} frames")


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
    col.add_argument("--noise-k", type=float, default=1.0, help="expert noise k in a* + k N(0, std) (default: 1)")
    col.add_argument("--noise-std", type=float, default=0.1, help="noise std (default: the paper's 0.1)")
    col.add_argument("--noisy-fraction", type=float, default=1.0, help="share of noisy episodes (default: 1)")
    col.add_argument("--resume", action="store_true", help="carry on an interrupted or shorter collection")
    col.add_argument("--overwrite", action="store_true", help="delete an existing dataset at --root first")
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
    return parser


def main(argv: list[str] | None = None) -> None:
    args = build_parser().parse_args(argv)
    args.func(args)


if __name__ == "__main__":
    main()
