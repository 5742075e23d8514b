"""Stage 5: the paper's experiments as grids (`murm reproduce`)."""
