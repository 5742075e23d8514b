"""VQ-VAE speed: training images/s and encoding images/s (the latent cache's inner loop).

Not a test. Run it on an otherwise idle machine:

    .venv/bin/python benchmarks/bench_vqvae.py [--device cpu]

Random uint8 images of the default 48x48 architecture: speed does not depend on content.
"""

from __future__ import annotations

import argparse
import statistics
import time

import numpy as np
import torch

from lerobot_murm.vqvae import VQVAE, VQVAEConfig
from lerobot_murm.vqvae.latent_cache import encode_images


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args()
    device = torch.device(args.device)
    config = VQVAEConfig()
    model = VQVAE(config).to(device)
    optimizer = torch.optim.Adam(model.parameters(), lr=config.learning_rate)
    images = np.random.default_rng(0).integers(0, 256, (8192, 48, 48, 3), dtype=np.uint8)

    def train_rate(steps: int = 10) -> float:
        start = time.perf_counter()
        for i in range(steps):
            batch = torch.from_numpy(images[i * config.batch_size : (i + 1) * config.batch_size]).to(device)
            loss = model(batch)["loss"]
            optimizer.zero_grad()
            loss.backward()
            optimizer.step()
        return steps * config.batch_size / (time.perf_counter() - start)

    def encode_rate() -> float:
        model.eval()
        start = time.perf_counter()
        encode_images(model, [images], len(images), device)
        model.train()
        return len(images) / (time.perf_counter() - start)

    train_rate(2), encode_rate()  # warm-up
    train = statistics.median(train_rate() for _ in range(args.repeats))
    encode = statistics.median(encode_rate() for _ in range(args.repeats))
    print(f"device {device}, threads {torch.get_num_threads()}, batch {config.batch_size}")
    print(f"training: {train:.0f} images/s  ->  {15 * 60 * train / 1e3:.0f}k images in 15 minutes")
    print(f"encoding: {encode:.0f} images/s  ->  100,000 frames x 2 cameras in {2e5 / encode:.0f} s")


if __name__ == "__main__":
    main()
