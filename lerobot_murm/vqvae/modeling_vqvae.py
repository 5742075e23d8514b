"""The VQ-VAE: strided convolutions 48 -> 24 -> 12, residual blocks, a 1x1 projection to
the 5-dim embedding, and an EMA codebook with a straight-through estimator.

The quantiser is written here rather than taken from a library: it is about forty
lines, it needs dead-code restarts and an exact index -> vector decode for the latent
cache, and it keeps the dependency list short.
"""

from __future__ import annotations

from pathlib import Path

import torch
import torch.nn.functional as F
from safetensors.torch import load_file, save
from torch import nn

from lerobot_murm.vqvae.configuration_vqvae import VQVAEConfig
from lerobot_murm.vqvae.encoder_files import WEIGHTS_FILE, check_encoder, incomplete, save_encoder_files

QUANTIZE_CHUNK_ROWS = 2048


class ResidualBlock(nn.Module):
    def __init__(self, channels: int, hidden: int):
        super().__init__()
        self.block = nn.Sequential(
            nn.ReLU(), nn.Conv2d(channels, hidden, 3, padding=1), nn.ReLU(inplace=True), nn.Conv2d(hidden, channels, 1)
        )

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x + self.block(x)


class VectorQuantizerEMA(nn.Module):
    """Nearest-codebook-vector quantisation; the codebook follows an EMA of its assignments."""

    def __init__(self, codebook_size: int, dim: int, decay: float, dead_code_threshold: float):
        super().__init__()
        self.decay, self.dead_code_threshold = decay, dead_code_threshold
        codebook = torch.randn(codebook_size, dim)
        self.register_buffer("codebook", codebook)
        self.register_buffer("ema_count", torch.ones(codebook_size))
        self.register_buffer("ema_sum", codebook.clone())

    def indices(self, z: torch.Tensor) -> torch.Tensor:
        """(B, D, H, W) encoder outputs -> (B, H, W) codebook indices.

        argmin ||x - c||^2 = argmax (x.c - ||c||^2 / 2): one fused addmm per chunk of
        rows, small enough to stay in cache (twice as fast as the plain distance matrix).
        `max(1).indices` rather than `argmax(1)`: the same first-maximum index, and twice
        as fast on CPU.
        """
        flat = z.permute(0, 2, 3, 1).reshape(-1, z.shape[1])
        bias = -0.5 * self.codebook.pow(2).sum(1)
        codebook_t = self.codebook.T.contiguous()
        nearest = [torch.addmm(bias, rows, codebook_t).max(1).indices for rows in flat.split(QUANTIZE_CHUNK_ROWS)]
        return torch.cat(nearest).view(z.shape[0], z.shape[2], z.shape[3])

    def lookup(self, indices: torch.Tensor) -> torch.Tensor:
        """(B, H, W) indices -> (B, D, H, W) codebook vectors."""
        return self.codebook[indices].permute(0, 3, 1, 2).contiguous()

    def forward(self, z: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Quantised z (straight-through gradient), commitment loss, indices."""
        indices = self.indices(z)
        quantized = self.lookup(indices)
        if self.training:
            self._ema_update(z, indices)
        commitment = F.mse_loss(z, quantized.detach())
        return z + (quantized - z).detach(), commitment, indices

    @torch.no_grad()
    def _ema_update(self, z: torch.Tensor, indices: torch.Tensor) -> None:
        flat = z.permute(0, 2, 3, 1).reshape(-1, z.shape[1])
        onehot = F.one_hot(indices.reshape(-1), self.codebook.shape[0]).type_as(flat)
        self.ema_count.mul_(self.decay).add_(onehot.sum(0), alpha=1 - self.decay)
        self.ema_sum.mul_(self.decay).add_(onehot.T @ flat, alpha=1 - self.decay)
        n = self.ema_count.sum()
        count = (self.ema_count + 1e-5) / (n + self.codebook.shape[0] * 1e-5) * n  # Laplace smoothing
        self.codebook.copy_(self.ema_sum / count.unsqueeze(1))
        dead = self.ema_count < self.dead_code_threshold
        if dead.any():  # restart unused codes on random encoder outputs of this batch
            picks = flat[torch.randint(0, flat.shape[0], (int(dead.sum()),), device=flat.device)]
            self.codebook[dead] = picks
            self.ema_sum[dead] = picks
            self.ema_count[dead] = 1.0


class VQVAE(nn.Module):
    def __init__(self, config: VQVAEConfig):
        super().__init__()
        self.config = config
        c, h, r = 3, config.hidden_channels, config.residual_channels
        self.encoder = nn.Sequential(
            nn.Conv2d(c, h // 2, 4, stride=2, padding=1),
            nn.ReLU(inplace=True),
            nn.Conv2d(h // 2, h, 4, stride=2, padding=1),
            *[ResidualBlock(h, r) for _ in range(config.num_residual_blocks)],
            nn.ReLU(inplace=True),
            nn.Conv2d(h, config.embedding_dim, 1),
        )
        self.quantizer = VectorQuantizerEMA(
            config.codebook_size, config.embedding_dim, config.ema_decay, config.dead_code_threshold
        )
        self.decoder = nn.Sequential(
            nn.Conv2d(config.embedding_dim, h, 3, padding=1),
            *[ResidualBlock(h, r) for _ in range(config.num_residual_blocks + 1)],
            nn.ReLU(inplace=True),
            nn.ConvTranspose2d(h, h // 2, 4, stride=2, padding=1),
            nn.ReLU(inplace=True),
            nn.ConvTranspose2d(h // 2, c, 4, stride=2, padding=1),
        )

    # --- images <-> network range -------------------------------------------------------
    def _check(self, images: torch.Tensor) -> None:
        size = self.config.image_size
        if images.ndim != 4 or tuple(images.shape[1:]) not in ((3, size, size), (size, size, 3)):
            raise ValueError(
                f"the {self.config.camera} VQ-VAE was trained on {size}x{size} RGB images; "
                f"got a batch of shape {tuple(images.shape)}"
            )

    def preprocess(self, images: torch.Tensor) -> torch.Tensor:
        """uint8 (B, H, W, 3) or (B, 3, H, W), or float in [0, 1] -> float (B, 3, H, W) in [-0.5, 0.5]."""
        self._check(images)
        if images.shape[-1] == 3:
            images = images.permute(0, 3, 1, 2)
        if images.dtype == torch.uint8:  # one new tensor, then in place: the encoder's hot path
            return images.float().div_(255.0).sub_(0.5)
        return images.float() - 0.5

    @staticmethod
    def postprocess(x: torch.Tensor) -> torch.Tensor:
        return (x + 0.5).clamp(0, 1)

    # --- the model ----------------------------------------------------------------------
    def forward(self, images: torch.Tensor) -> dict[str, torch.Tensor]:
        x = self.preprocess(images)
        quantized, commitment, indices = self.quantizer(self.encoder(x))
        reconstruction = self.decoder(quantized)
        recon_loss = F.mse_loss(reconstruction, x)
        return {
            "loss": recon_loss + self.config.commitment_cost * commitment,
            "recon_loss": recon_loss,
            "commitment": commitment,
            "indices": indices,
            "reconstruction": reconstruction,
        }

    @torch.no_grad()
    def encode_indices(self, images: torch.Tensor) -> torch.Tensor:
        """Images -> (B, 12, 12) codebook indices (what the latent cache stores)."""
        return self.quantizer.indices(self.encoder(self.preprocess(images)))

    @torch.no_grad()
    def latents_from_indices(self, indices: torch.Tensor) -> torch.Tensor:
        """(B, 12, 12) indices -> (B, 720) latents: the codebook vectors, flattened."""
        return self.quantizer.lookup(indices.long()).flatten(1)

    @torch.no_grad()
    def encode(self, images: torch.Tensor) -> torch.Tensor:
        """Images -> (B, 720) latents."""
        return self.latents_from_indices(self.encode_indices(images))

    @torch.no_grad()
    def decode(self, latents: torch.Tensor) -> torch.Tensor:
        """(B, 720) latents -> images in [0, 1], (B, 3, H, W)."""
        g = self.config.grid_size
        return self.postprocess(self.decoder(latents.view(-1, self.config.embedding_dim, g, g)))

    # --- checkpoints --------------------------------------------------------------------
    def save(self, directory: Path) -> None:
        """Weights and config, replacing any encoder in `directory` atomically (encoder_files.py)."""
        weights = save({k: v.contiguous() for k, v in self.state_dict().items()})
        save_encoder_files(Path(directory), weights, self.config.to_json().encode())

    @classmethod
    def load(cls, directory: Path, device: str | torch.device = "cpu") -> VQVAE:
        directory = Path(directory)
        model = cls(VQVAEConfig(**check_encoder(directory)))
        try:
            model.load_state_dict(load_file(directory / WEIGHTS_FILE, device=str(device)))
        except RuntimeError as error:  # the two files of different saves (an encoder torn before saves were atomic)
            why = f"{WEIGHTS_FILE} does not fit its config: {str(error).splitlines()[0]}"
            raise incomplete(directory, why) from None
        return model.to(device).eval()
