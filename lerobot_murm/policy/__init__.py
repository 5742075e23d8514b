"""Stage 4: goal-conditioned IQL on the latents (LeRobot policy type `murm`)."""

from lerobot_murm.policy.configuration_murm import MurmConfig

__all__ = ["MurmConfig"]
