"""Progress bars: in place on a terminal, one plain line at a time in a log file."""

import io
import os
import select
import sys
from pathlib import Path

from tqdm import tqdm

from lerobot_murm.progress import LogLines, progress
from lerobot_murm.training_loop import TrainingLoop

sys.path.insert(0, str(Path(__file__).parent / "helpers"))
from commands import run

MURM = Path(sys.executable).parent / "murm"


def test_a_log_file_gets_whole_lines_not_carriage_returns():
    log = io.StringIO()
    bar = progress(total=3, desc="murm train place_in_box single-global seeds 0,1,2", unit="step", file=log)
    assert isinstance(bar, LogLines)
    for _ in range(3):
        bar.set_postfix(refresh=False, critic=1.5)
        bar.update()
    bar.close()
    text = log.getvalue()
    lines = [line for line in text.splitlines() if line]
    assert "\r" not in text and "\x1b" not in text
    assert lines[0].startswith("murm train place_in_box single-global seeds 0,1,2:   0%") and "0/3" in lines[0]
    assert "3/3" in lines[-1] and "critic=1.5" in lines[-1]
    assert len(lines) == 2  # the start and the end: updates closer than a minute apart print nothing


def read_all(leader: int) -> str:
    """Everything written to a closed pseudo-terminal: a pty hands it over in as many reads as
    it likes (one read got only the first of the bar's writes on a busy machine)."""
    chunks = []
    while select.select([leader], [], [], 5.0)[0]:
        try:
            chunk = os.read(leader, 4096)
        except OSError:  # EIO: the follower is closed and everything was read
            break
        if not chunk:
            break
        chunks.append(chunk)
    os.close(leader)
    return b"".join(chunks).decode()


def test_a_terminal_gets_tqdms_bar_in_place():
    leader, follower = os.openpty()
    with os.fdopen(follower, "w") as terminal:
        bar = progress(total=2, desc="collect pick_up", unit="ep", file=terminal)
        assert type(bar) is tqdm
        bar.update(2)
        bar.close()
    output = read_all(leader)
    assert "\r" in output and "2/2" in output


def test_the_training_loops_figures_reach_the_log_line(capsys):
    loop = TrainingLoop(2, desc="murm train x")
    with loop:
        while loop.running():
            loop.advance()
            loop.show(critic=0.25)
    err = capsys.readouterr().err
    last = [line for line in err.splitlines() if line][-1]
    assert "\r" not in err and "2/2" in last and "critic=0.25" in last


def test_a_bad_progress_interval_is_one_clear_line(tmp_path):
    result = run(
        [str(MURM), "collect", "--task", "pick_up", "--episodes", "1", "--root", str(tmp_path / "ds")],
        env={**os.environ, "MURM_PROGRESS_EVERY_S": "soon", "HF_HUB_OFFLINE": "1"},
        timeout=300,
    )
    lines = [line for line in result.stderr.splitlines() if line.startswith("murm collect:")]
    assert result.returncode == 2 and len(lines) == 1, result.stderr[-2000:]
    assert "MURM_PROGRESS_EVERY_S must be a number of seconds >= 0, got 'soon'" in lines[0]
