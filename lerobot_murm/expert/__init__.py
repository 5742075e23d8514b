"""Scripted experts that solve the MURM tasks from privileged state (paper 4.1)."""

from lerobot_murm.expert.scripted import (
    CALIBRATED_NOISE_STD,
    PAPER_NOISE_STD,
    ScriptedExpert,
    default_noise_std,
    noisy_action,
)

__all__ = ["CALIBRATED_NOISE_STD", "PAPER_NOISE_STD", "ScriptedExpert", "default_noise_std", "noisy_action"]
