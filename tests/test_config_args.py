"""Each setting defined once: `murm collect` and `murm train-vqvae` read their options from the
stage configs' fields (config_args.py), defaults and help included."""

import dataclasses

from lerobot_murm.cli import COLLECT_OPTIONS, VQVAE_OPTIONS, build_parser
from lerobot_murm.collection import CollectConfig
from lerobot_murm.config_args import field_comments
from lerobot_murm.vqvae import VQVAEConfig


def collect_help() -> str:
    parser = build_parser()
    (commands,) = [a for a in parser._actions if a.dest == "command"]
    sub = commands.choices["collect"]
    sub.parse_known_args(["--task", "pick_up", "--root", "out"])  # adds the generated options
    return sub.format_help()


def parsed(argv: list[str]):
    args, extra = build_parser().parse_known_args(argv)
    assert extra == []
    return args


def test_collect_options_are_the_config_fields_with_their_defaults():
    args = parsed(["collect", "--task", "pick_up", "--root", "out"])
    config = CollectConfig(**{name: getattr(args, name) for name in COLLECT_OPTIONS})
    defaults = {f.name: f.default for f in dataclasses.fields(CollectConfig) if f.name not in ("task", "root")}
    assert config == CollectConfig(task="pick_up", root="out", **{k: defaults[k] for k in COLLECT_OPTIONS[2:]})
    args = parsed(["collect", "--task", "pick_up", "--root", "out", "--cameras", "global,top", "--resume"])
    assert args.cameras == ("global", "top") and args.resume is True and args.noise_std is None


def test_train_vqvae_options_are_the_config_fields():
    args = parsed(["train-vqvae", "--dataset", "d", "--camera", "global", "--batch-size", "64"])
    assert (args.steps, args.batch_size, args.seed) == (VQVAEConfig().steps, 64, VQVAEConfig().seed)
    assert set(VQVAE_OPTIONS) <= {f.name for f in dataclasses.fields(VQVAEConfig)}


def test_the_help_is_the_field_comment():
    comments = field_comments(CollectConfig)
    assert comments["workers"] == "simulator processes"
    assert comments["noise_std"].startswith("expert noise std")  # the comment lines above the field
    assert "first_episode" in comments
    text = collect_help()
    assert "simulator processes (default: 2)" in text and "--noise-k" not in text
