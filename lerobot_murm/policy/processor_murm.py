"""Pre- and post-processing of the MURM policy: LeRobot's defaults.

Images stay in [0, 1] (the encoders normalise them), actions are already in [-1, 1]:
every feature maps to IDENTITY, so the pipeline only renames, batches and moves to the
device. Keeping the default steps lets `lerobot-eval` override them by name.
"""

from __future__ import annotations

from typing import Any

import torch
from lerobot.processor import PolicyAction, PolicyProcessorPipeline, make_default_pre_post_processors

from lerobot_murm.policy.configuration_murm import MurmConfig


def make_murm_pre_post_processors(
    config: MurmConfig, dataset_stats: dict[str, dict[str, torch.Tensor]] | None = None
) -> tuple[
    PolicyProcessorPipeline[dict[str, Any], dict[str, Any]], PolicyProcessorPipeline[PolicyAction, PolicyAction]
]:
    return make_default_pre_post_processors(config, dataset_stats)
