"""The fast trainer of `murm train`: IQL on the latents in memory (`policy/replay.py`), seeds
stacked side by side, evaluation in the simulator, learning curves, checkpoints in LeRobot's
format (so `lerobot-eval` loads them).

It sits above `policy/` (what `lerobot-eval` loads, which imports nothing of this package)
and below `experiments/`, which runs it for every cell of a grid.
"""
