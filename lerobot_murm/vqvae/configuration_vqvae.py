"""VQ-VAE configuration (paper 3.1 and 4.2): 48x48x3 images to a 12x12 grid of 5-dim codes."""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass, field
from pathlib import Path

from lerobot_murm.vqvae.resize import RESIZE_RULE

LATENT_DISTANCE_FILE = "latent_distance.json"  # beside a checkpoint: `murm encode`'s epsilon statistics


@dataclass
class VQVAEConfig:
    """Architecture and training settings; saved beside the weights so a checkpoint describes itself."""

    camera: str = "global"
    # the input's side in pixels: frames of another size are centre-cropped to a square and
    # area-resized to it, or to the square's side where that is smaller (resize.py)
    image_size: int = 48
    hidden_channels: int = 64  # after the second strided convolution
    residual_channels: int = 32
    num_residual_blocks: int = 1  # in the encoder; the decoder has one more
    embedding_dim: int = 5  # paper: 12 x 12 x 5 = 720 numbers per image
    codebook_size: int = 512
    commitment_cost: float = 0.25
    ema_decay: float = 0.99  # EMA codebook updates (van den Oord et al. 2017, appendix)
    dead_code_threshold: float = 1.0  # codes used less than this (EMA count) are restarted
    # training
    steps: int = 2500  # training updates
    batch_size: int = 128  # images per update
    learning_rate: float = 1e-3
    holdout_fraction: float = 0.05  # whole episodes kept out for validation
    seed: int = 0  # initialisation, batches and the held-out split
    dataset: dict = field(default_factory=dict)  # what it was trained on (repo id, root, fingerprint)
    source_key: str | None = None  # the dataset stream it was trained on (None: an encoder older than the record)
    source_size: list[int] | None = None  # that stream's frames, [height, width]
    resize: str = RESIZE_RULE  # how those frames reach image_size (resize.py)

    def __post_init__(self) -> None:
        if self.steps < 1 or self.batch_size < 1:
            raise ValueError(f"steps and batch_size must be at least 1, got {self.steps} and {self.batch_size}")
        if not self.learning_rate > 0:
            raise ValueError(f"learning_rate must be positive, got {self.learning_rate}")
        if not 0.0 <= self.holdout_fraction < 1.0:
            raise ValueError(f"holdout_fraction must be in [0, 1), got {self.holdout_fraction}")
        if self.seed < 0:
            raise ValueError(f"seed must be >= 0, got {self.seed}")
        if self.image_size < 4 or self.image_size % 4:
            raise ValueError(f"image_size must be a multiple of 4 (two stride-2 convolutions), got {self.image_size}")
        if self.resize != RESIZE_RULE:
            raise ValueError(f"unknown resize {self.resize!r}; the one rule is {RESIZE_RULE!r}")

    @property
    def grid_size(self) -> int:
        return self.image_size // 4  # two stride-2 convolutions

    @property
    def latent_dim(self) -> int:
        return self.embedding_dim * self.grid_size**2

    def to_json(self) -> str:
        return json.dumps(asdict(self), indent=2) + "\n"

    @classmethod
    def load(cls, path: Path) -> VQVAEConfig:
        return cls(**json.loads(Path(path).read_text()))
