"""The `murm` command: one entry point for every stage of the pipeline."""

from __future__ import annotations

import argparse
from pathlib import Path


def _demo(args: argparse.Namespace) -> None:
    from lerobot_murm.demo import run_demo

    results = run_demo(Path(args.out), seed=args.seed)
    if not all(r["success"] for r in results):
        print("note: the noiseless scripted expert failed an episode (see the rollout PNGs)")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="murm", description="MURM: multi-view goal-conditioned offline RL")
    commands = parser.add_subparsers(dest="command", required=True)

    demo = commands.add_parser("demo", help="render every task's cameras and goals, run one expert episode each")
    demo.add_argument("--out", default="outputs/demo", help="folder for the PNGs (default: %(default)s)")
    demo.add_argument("--seed", type=int, default=0, help="episode seed (default: %(default)s)")
    demo.set_defaults(func=_demo)
    return parser


def main(argv: list[str] | None = None) -> None:
    args = build_parser().parse_args(argv)
    args.func(args)


if __name__ == "__main__":
    main()
