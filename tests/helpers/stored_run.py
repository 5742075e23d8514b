"""A run's result file as `murm reproduce` stores it, with the fields the report reads."""


def stored_run(
    task: str,
    cell: str,
    method: str,
    cameras: list[str],
    steps: int = 20000,
    success: float = 0.5,
    curve: list | None = None,
    **extra,
) -> dict:
    final = [{"mask_p": 0.0, "success_rate": success, "episodes": 100}]
    return {
        "task": task,
        "cell": cell,
        "method": method,
        "cameras": cameras,
        "seed": 0,
        "steps": steps,
        "final": final,
        "final_validation": final,
        "wall_s": 360.0,
        "train_steps_per_s": 90.0,
        "hardware": "cpu",
        "curve": curve or [[steps, 0.0, success]],
    } | extra
