"""Scripted experts that solve the MURM tasks from privileged state (paper 4.1)."""

from lerobot_murm.expert.scripted import ScriptedExpert, noisy_action

__all__ = ["ScriptedExpert", "noisy_action"]
