"""The frame a rollout video shows: an overview of the scene beside what each camera sees and its goal.

`lerobot-eval` records `env.render()` and nothing else, so the env composes this frame
itself: the overview on the left, then one column per camera with the camera's
current image above its goal image, both as the policy receives them (48x48 by
default), enlarged without smoothing so the pixels stay the policy's pixels.
"""

from __future__ import annotations

import cv2
import numpy as np

LABEL_COLOUR = (255, 255, 255)
LABEL_OUTLINE = (0, 0, 0)


def tile_size(render_size: int) -> int:
    """The side of one camera tile: half the overview, even so that video encoders take the frame."""
    return max(render_size // 4, 1) * 2


def compose_frame(overview: np.ndarray, views: dict[str, np.ndarray], goals: dict[str, np.ndarray]) -> np.ndarray:
    """`overview` (2T x 2T) followed by a T-wide column per camera of `views`: view above goal.

    A camera without a goal image (an env made with `goal_images=False`) gets a black lower tile.
    """
    tile = overview.shape[0] // 2
    if overview.shape[:2] != (2 * tile, 2 * tile):
        raise ValueError(f"the overview must be square with an even side, got {overview.shape}")
    columns = [overview]
    for name, view in views.items():
        top = _labelled(_enlarged(view, tile), name)
        goal = goals.get(name)
        bottom = np.zeros_like(top) if goal is None else _labelled(_enlarged(goal, tile), f"{name} goal")
        columns.append(np.concatenate([top, bottom], axis=0))
    return np.concatenate(columns, axis=1)


def _enlarged(image: np.ndarray, size: int) -> np.ndarray:
    return cv2.resize(image, (size, size), interpolation=cv2.INTER_NEAREST)


def _labelled(tile: np.ndarray, text: str) -> np.ndarray:
    """The tile with `text` in its top-left corner, white on a black outline (readable on any scene)."""
    tile = tile.copy()
    scale = tile.shape[0] / 320
    origin = (3, max(int(22 * scale), 8))
    for colour, thickness in ((LABEL_OUTLINE, 3), (LABEL_COLOUR, 1)):
        cv2.putText(tile, text, origin, cv2.FONT_HERSHEY_SIMPLEX, scale, colour, thickness, cv2.LINE_AA)
    return tile
