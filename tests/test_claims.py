"""The claims list: verdicts from the grids' tables by the rules written before they ran."""

import csv
import shutil
from pathlib import Path

from lerobot_murm.experiments.claims import claims_table, judge_claims
from lerobot_murm.experiments.report import update_readme, write_report
from lerobot_murm.experiments.results import COLUMNS

REPO = Path(__file__).resolve().parents[1]
TASKS = ("place_in_box", "place_in_random_box", "pick_up")


def write_table(results: Path, grid: str, rows: list[tuple[str, str, float, float, float | None, int]]) -> None:
    """rows: (task, cell, masking, mean, std, seeds)."""
    (results / grid).mkdir(parents=True, exist_ok=True)
    with (results / grid / "table.csv").open("w", newline="") as f:
        writer = csv.DictWriter(f, COLUMNS)
        writer.writeheader()
        for task, cell, mask_p, mean, std, seeds in rows:
            writer.writerow({"task": task, "cell": cell, "method": cell.split("-")[0], "cameras": "global",
                             "mask_p": mask_p, "success_mean": mean, "success_std": std, "seeds": seeds,
                             "episodes_per_seed": 100, "steps": 20000, "wall_s_mean": 600.0,
                             "train_steps_per_s": 40.0})


def table4(results: Path, separated_q_masked: dict[str, float], tasks=TASKS) -> None:
    rows = []
    for task in tasks:
        rows += [(task, "single-global", 0.0, 40.0, 5.0, 3), (task, "single-global", 0.5, 2.0, 1.0, 3),
                 (task, "concat-global+adjacent", 0.5, 5.0, 2.0, 3),
                 (task, "dropout-global+adjacent", 0.5, 30.0, 4.0, 3),
                 (task, "separated_q-global+adjacent", 0.5, separated_q_masked[task], 4.0, 3)]
    write_table(results, "table4", rows)


def verdicts(results: Path) -> dict[str, str]:
    return {v.claim.text: v.verdict for v in judge_claims(results)}


def test_table4_claims_are_judged_per_task_and_combined(tmp_path):
    table4(tmp_path, {"place_in_box": 35.0, "place_in_random_box": 33.0, "pick_up": 10.0})
    found = verdicts(tmp_path)
    assert found["a single view fails under 50 % masking (paper 0 / 3 / 0 %)"] == "holds"
    assert found["concatenation fails under 50 % masking (paper 4 / 12 / 4 %)"] == "holds"
    assert found["MURM dropout stays successful under 50 % masking (paper 36 / 40 / 10 %)"] == "holds"
    # separated Q under half the single view (20) on pick_up only: partly
    assert found["MURM separated Q stays successful under 50 % masking (paper 38 / 44 / 15 %)"] == "partly"
    # best on two tasks, clearly below dropout (30 ± 4 vs 10 ± 4, 3 seeds) on pick_up: partly
    assert found["separated Q is the best method under masking"] == "partly"
    assert found["a fully noisy dataset is best"] == "not run yet"


def test_a_difference_within_noise_is_not_called(tmp_path):
    # 27 vs dropout's 30, both ± 4 over 3 seeds: 2 standard errors of the difference are 6.5 points
    table4(tmp_path, {task: 27.0 for task in TASKS})
    assert verdicts(tmp_path)["separated Q is the best method under masking"] == "partly"
    table4(tmp_path, {task: 12.0 for task in TASKS})
    assert verdicts(tmp_path)["separated Q is the best method under masking"] == "does not hold"
    table4(tmp_path, {task: 31.0 for task in TASKS})
    assert verdicts(tmp_path)["separated Q is the best method under masking"] == "holds"


def test_a_claim_judged_on_some_tasks_says_how_many(tmp_path):
    table4(tmp_path, {"place_in_box": 35.0}, tasks=("place_in_box",))
    assert verdicts(tmp_path)["separated Q is the best method under masking"] == "holds (1 of 3 run)"


def test_one_seed_cells_use_the_binomial_error_of_their_episodes(tmp_path):
    # one seed, 100 episodes: 30 % vs 20 % is 1.7 standard errors apart (not called), vs 10 % it is 3.5
    rows = [("place_in_box", f"single-global-{w}", 0.0, mean, None, 1)
            for w, mean in ((32, 30.0), (64, 10.0), (128, 20.0), (256, 5.0))]
    write_table(tmp_path, "table1", rows)
    assert verdicts(tmp_path)["128 units per layer give the highest success of the widths 32-256"] == "partly"
    rows[2] = ("place_in_box", "single-global-128", 0.0, 10.0, None, 1)
    write_table(tmp_path, "table1", rows)
    assert verdicts(tmp_path)["128 units per layer give the highest success of the widths 32-256"] == "does not hold"


def test_table3_and_table6_rank_the_views(tmp_path):
    means = {"global": 40.0, "adjacent": 35.0, "top": 20.0, "side": 25.0, "active": 5.0}
    write_table(tmp_path, "table3", [(task, f"single-{v}", 0.0, m, 3.0, 3) for task in TASKS for v, m in means.items()])
    pairs = {"top": 30.0, "side": 38.0, "active": 10.0}
    write_table(tmp_path, "table6", [("place_in_box", f"separated_q-global+{v}", p, m, 3.0, 3)
                                     for v, m in pairs.items() for p in (0.0, 0.5)])
    found = verdicts(tmp_path)
    assert found["global and adjacent are the best single views on every task"] == "holds"
    assert found["the gain from adding a view follows that view's own single-view success"] == "holds"


def test_the_report_and_readme_show_the_claims_with_their_numbers(tmp_path):
    table4(tmp_path / "results", {task: 31.0 for task in TASKS})
    shutil.copy(REPO / "configs/reproduce/table4.yaml", tmp_path / "results/table4/config.yaml")
    report = write_report(tmp_path / "results", tmp_path / "REPORT.md").read_text()
    assert "## Which of the paper's claims hold here" in report
    assert "| Table 4 | separated Q is the best method under masking | **holds** |" in report
    assert "place_in_box: single 2 ± 1, concat 5 ± 2, dropout 30 ± 4, separated Q 31 ± 4 (holds)" in report
    readme = tmp_path / "README.md"
    readme.write_text("# x\n<!-- claims -->\nstale\n<!-- /claims -->\nrest\n")
    assert update_readme(tmp_path / "results", readme) == ["claims"]
    text = readme.read_text()
    assert "stale" not in text and "**holds**" in text and text.endswith("<!-- /claims -->\nrest\n")
    assert "How each verdict is decided" in claims_table(tmp_path / "results")

