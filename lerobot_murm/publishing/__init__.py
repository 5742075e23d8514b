"""Publishing: demonstrations and latent datasets to and from the Hugging Face Hub, each with
its dataset card (templates in `datasets_cards/`).

It sits above the stages whose datasets it describes (collection, vqvae) and may import
them; no stage imports it.
"""

from lerobot_murm.publishing.card import render_card, render_latent_card
from lerobot_murm.publishing.hub import HubUnavailable, pull_dataset, push_dataset

__all__ = ["HubUnavailable", "pull_dataset", "push_dataset", "render_card", "render_latent_card"]
