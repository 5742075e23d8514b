"""Demonstrations: the noisy scripted expert's episodes written as a LeRobotDataset."""

from lerobot_murm.collection.collect import CollectConfig, collect
from lerobot_murm.collection.dataset import read_recipe
from lerobot_murm.collection.episodes import Episode, EpisodeRecipe, run_episode

__all__ = ["CollectConfig", "Episode", "EpisodeRecipe", "collect", "read_recipe", "run_episode"]
