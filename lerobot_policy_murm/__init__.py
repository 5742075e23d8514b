"""Entry point for LeRobot's plugin discovery: importing it registers MURM's env and policy types."""

import lerobot_murm  # noqa: F401
