"""One VQ-VAE per camera: images to 720-number latents (paper 3.1, 4.2)."""

from lerobot_murm.vqvae.configuration_vqvae import VQVAEConfig
from lerobot_murm.vqvae.modeling_vqvae import VQVAE

__all__ = ["VQVAE", "VQVAEConfig"]
