"""How any camera's frames reach an encoder's square input: one rule, for training and acting.

A robot's cameras record at their own sizes (an SO-101's laptop and phone cameras at
480x640); the VQ-VAE takes `image_size` x `image_size` (the paper's 48). The frames are
centre-cropped to a square (the shorter side) and area-averaged down to the encoder's side
(torch's `area` interpolation: each output pixel the mean of the input pixels it covers,
no aliasing). The encoder's side is `image_size`, or the square's own side where that is
smaller (never upsampled), rounded down to a multiple of 4 (two stride-2 convolutions).
Frames already at the encoder's side, as `murm collect` writes them, pass untouched.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

RESIZE_RULE = "center_crop_area"  # what an encoder's config records as its `resize`


def encoder_side(height: int, width: int, image_size: int) -> int:
    """The side of the square images an encoder of `image_size` trains on, from frames of this size."""
    side = min(height, width, image_size) // 4 * 4
    if side < 4:
        raise ValueError(f"frames of {height}x{width} are too small for an encoder (at least 4x4)")
    return side


def fit_images(images: torch.Tensor, side: int) -> torch.Tensor:
    """(..., 3, H, W) uint8 or float images -> (..., 3, side, side) of the same dtype, by RESIZE_RULE."""
    height, width = images.shape[-2:]
    if height == width == side:
        return images
    crop = min(height, width)
    top, left = (height - crop) // 2, (width - crop) // 2
    square = images[..., top : top + crop, left : left + crop].reshape(-1, *images.shape[-3:-2], crop, crop)
    resized = F.interpolate(square.float(), size=(side, side), mode="area")
    if images.dtype == torch.uint8:
        resized = resized.round_().clamp_(0, 255)
    return resized.to(images.dtype).reshape(*images.shape[:-2], side, side)
