"""`murm` in the test's own process, for the one-line errors of bad input."""

import pytest

from lerobot_murm.cli import main


def murm_error(argv: list, capsys) -> tuple[int, str]:
    """Run `murm argv` in this process: (exit code, the one line of stderr)."""
    with pytest.raises(SystemExit) as stop:
        main([str(a) for a in argv])
    lines = [line for line in capsys.readouterr().err.splitlines() if line.startswith("murm")]
    assert len(lines) == 1, lines
    return stop.value.code, lines[0]
