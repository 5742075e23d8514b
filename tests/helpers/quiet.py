"""What a quiet run must not print: tracebacks, LeRobot's torchcodec probe, pybullet's C lines,
library warnings (LeRobot's device auto-selection among them)."""

LIBRARY_NOISE = ("Traceback", "torchcodec", "argv[0]", "pybullet build time", "WARNING")


def assert_quiet(output: str) -> None:
    found = [noise for noise in LIBRARY_NOISE if noise in output]
    assert not found, f"printed {found}:\n{output[-3000:]}"
