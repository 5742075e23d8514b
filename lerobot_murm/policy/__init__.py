"""Stage 4: goal-conditioned IQL on the latents (LeRobot policy type `murm`): what
`lerobot-train` and `lerobot-eval` load (configuration, modeling, processor, IQL's losses and
networks, precision, the latent sampler). The fast trainer of `murm train` is `training/`."""

from lerobot_murm.policy.configuration_murm import MurmConfig

__all__ = ["MurmConfig"]
