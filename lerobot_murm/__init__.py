"""lerobot-murm: multi-view goal-conditioned offline RL (MURM) as a LeRobot plugin.

Importing this package registers the gymnasium ids `murm/*-v0`, the LeRobot env
type `murm` and the LeRobot policy type `murm`.
"""

from lerobot_murm.env import configuration_env  # noqa: F401  (registers the `murm` env type)
from lerobot_murm.policy import configuration_murm  # noqa: F401  (registers the `murm` policy type)

__version__ = "0.1.0"
