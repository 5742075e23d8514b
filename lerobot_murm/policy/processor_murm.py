"""Pre- and post-processing of the MURM policy: LeRobot's defaults.

Images stay in [0, 1] (the encoders normalise them and resize them themselves); actions map
to the policy's [-1, 1] by the dataset's min and max (any robot's action: an SO-101's joint
positions in degrees, the simulator's end-effector steps already in [-1, 1]) and back when
the policy acts (`MurmConfig.normalization_mapping`). Keeping the default steps lets
`lerobot-eval` override them by name.
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
