"""Which of the paper's claims hold here: each claim in the paper's words, the rule that
decides it and its verdict from our tables, with the numbers behind it.

The rules read only the reported (test-episode) tables, `results/<grid>/table.csv`, so
`murm report` recomputes the verdicts whenever a grid finishes. The words every rule uses are
DEFINITIONS below. Study v1 judged with "clearly below" alone; study v2's rules (committed
before its first table ran) add "not resolved": a comparison the seeds cannot decide, or one
between two cells that both sit at the floor, is not read as holding or failing.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from lerobot_murm.experiments.paper import TABLE5, TASKS
from lerobot_murm.experiments.results import read_table

HOLDS, PARTLY, FAILS, PENDING = "holds", "partly", "does not hold", "not run yet"
UNRESOLVED = "not resolved"
FLOOR_PERCENT = 5.0

DEFINITIONS = """\
- A cell is *clearly above* (*below*) another when its mean is higher (lower) by more than two
  standard errors of the difference (standard error of a cell: sample std / sqrt(seeds); for
  one seed, the binomial standard error of its episodes). With 3 seeds at a 7-point seed spread
  that is about 11 points. A comparison that is neither, or whose two cells are both below
  5 % (the floor, where every method fails alike), is *not resolved*.
- A claim is judged per task (or masking level): *holds* or *does not hold* where the
  comparisons it rests on are resolved, *not resolved* where they are not. Overall: *holds*
  where every resolved task holds, *does not hold* where every resolved task fails, *partly*
  where they differ, *not resolved* where no task is; "(k of n resolved)" says how many tasks
  decided it. Tasks whose cells have not run yet are left out (*not run yet* when none has).
"""


@dataclass(frozen=True)
class Cell:
    """One row of a grid's table: success (%) over seeds."""

    mean: float
    std: float | None
    seeds: int
    episodes: int
    steps_per_s: float

    @property
    def standard_error(self) -> float:
        if self.seeds > 1 and self.std is not None:
            return self.std / math.sqrt(self.seeds)
        p = min(max(self.mean / 100, 0.0), 1.0)
        return 100 * math.sqrt(max(p * (1 - p), 1e-4) / self.episodes)

    def text(self) -> str:
        return f"{self.mean:.0f} ± {self.std:.0f}" if self.seeds > 1 and self.std is not None else f"{self.mean:.0f}"


class Tables:
    """The committed tables of every grid, by (grid, task, cell, masking)."""

    def __init__(self, results_dir: Path):
        self.cells: dict[tuple[str, str, str, float], Cell] = {}
        for table in sorted(Path(results_dir).glob("*/table.csv")):
            for row in read_table(table):
                std = row["success_std"]
                self.cells[(table.parent.name, row["task"], row["cell"], round(float(row["mask_p"]), 4))] = Cell(
                    float(row["success_mean"]),
                    float(std) if std not in ("", "None") else None,
                    int(row["seeds"]),
                    int(row["episodes_per_seed"]),
                    float(row["train_steps_per_s"]),
                )

    def get(self, grid: str, task: str, cell: str, mask_p: float = 0.0) -> Cell | None:
        return self.cells.get((grid, task, cell, round(mask_p, 4)))

    def row(self, grid: str, task: str, cells: list[str], mask_p: float = 0.0) -> dict[str, Cell] | None:
        """These cells of one task, or None unless every one has run."""
        found = {name: self.get(grid, task, name, mask_p) for name in cells}
        return None if any(c is None for c in found.values()) else found


def clearly_below(cell: Cell, other: Cell, factor: float = 1.0) -> bool:
    """`cell` under `factor` x `other` by more than two standard errors of the difference (the
    learning curves' rule too, `flattening.py`: no floor there)."""
    return factor * other.mean - cell.mean > 2 * math.hypot(cell.standard_error, factor * other.standard_error)


def compare(cell: Cell, other: Cell, factor: float = 1.0) -> int | None:
    """+1 if `cell` is clearly above `factor` x `other`, -1 if clearly below, None if not
    resolved (within two standard errors of the difference, or both cells below the floor)."""
    if cell.mean < FLOOR_PERCENT and other.mean < FLOOR_PERCENT:
        return None
    if clearly_below(cell, other, factor):
        return -1
    above = cell.mean - factor * other.mean > 2 * math.hypot(cell.standard_error, factor * other.standard_error)
    return 1 if above else None


def resolved_as(comparison: int | None, holds_when: int) -> str:
    """The verdict of a claim resting on one comparison that should come out `holds_when`."""
    if comparison is None:
        return UNRESOLVED
    return HOLDS if comparison == holds_when else FAILS


def best_verdict(cells: dict[str, Cell], name: str) -> str:
    """holds: `name` is clearly above the best of the others; does not hold: clearly below it;
    else not resolved."""
    rival = max((k for k in cells if k != name), key=lambda k: cells[k].mean)
    return resolved_as(compare(cells[name], cells[rival]), holds_when=1)


def combine(verdicts: list[str]) -> str:
    """The overall verdict of per-task verdicts, from the resolved ones."""
    if not verdicts:
        return PENDING
    resolved = [v for v in verdicts if v != UNRESOLVED]
    if not resolved:
        return UNRESOLVED
    if all(v == HOLDS for v in resolved):
        return HOLDS
    return FAILS if all(v == FAILS for v in resolved) else PARTLY


def _numbers(cells: dict[str, Cell], short: dict[str, str] | None = None) -> str:
    return ", ".join(f"{(short or {}).get(name, name)} {cell.text()}" for name, cell in cells.items())


@dataclass(frozen=True)
class Judged:
    """A claim on each condition (task or masking level) whose cells have run."""

    verdicts: list[str]
    evidence: list[str]
    conditions: int  # how many there are in all


@dataclass(frozen=True)
class Claim:
    source: str  # where in the paper
    text: str  # the claim, in the paper's words where it has them
    rule: str  # how our tables decide it
    judge: Callable[[Tables], Judged]


@dataclass(frozen=True)
class Verdict:
    claim: Claim
    verdict: str
    evidence: str


def judge_cells(
    grid: str,
    cells: list[str],
    decide: Callable[[dict[str, Cell]], str],
    conditions: list[tuple[str, str, float]],
    short: dict[str, str] | None = None,
):
    """A judge that applies `decide` to these cells under each condition (its label, task and
    masking level) where all of them have run."""

    def judge(tables: Tables) -> Judged:
        verdicts, evidence = [], []
        for label, task, mask_p in conditions:
            if (row := tables.row(grid, task, cells, mask_p)) is not None:
                verdict = decide(row)
                verdicts.append(verdict)
                evidence.append(f"{label}: {_numbers(row, short)} ({verdict})")
        return Judged(verdicts, evidence, len(conditions))

    return judge


def per_task(
    grid: str,
    cells: list[str],
    mask_p: float,
    decide: Callable[[dict[str, Cell]], str],
    short: dict[str, str] | None = None,
):
    """A judge of these cells on every task, at one masking level."""
    return judge_cells(grid, cells, decide, [(task, task, mask_p) for task in TASKS], short)


def per_masking(
    grid: str,
    cells: list[str],
    decide: Callable[[dict[str, Cell]], str],
    short: dict[str, str] | None = None,
    levels: tuple[float, ...] = (0.0, 0.5),
):
    """A judge for task-1 grids: these cells at each masking level."""
    return judge_cells(grid, cells, decide, [(f"{m:.0%} masking", "place_in_box", m) for m in levels], short)


SINGLE = "single-global"
CONCAT = "concat-global+adjacent"
DROPOUT = "dropout-global+adjacent"
SEPARATED = "separated_q-global+adjacent"
VIEWS = ["global", "adjacent", "top", "side", "active"]


def _top_two(row: dict[str, Cell]) -> str:
    """Global and adjacent each against the best of the other three views: holds if both are
    clearly above it, does not hold if one is clearly below it and neither clearly above,
    partly if one is above and one below, else not resolved."""
    others = [k for k in row if k not in ("single-global", "single-adjacent")]
    rival = row[max(others, key=lambda k: row[k].mean)]
    found = {compare(row[view], rival) for view in ("single-global", "single-adjacent")}
    if found == {1}:
        return HOLDS
    if -1 in found:
        return PARTLY if 1 in found else FAILS
    return UNRESOLVED


def fails_under_masking(row: dict[str, Cell]) -> str:
    """holds: under 50 % masking clearly below a third of the unmasked single view's success."""
    return resolved_as(compare(row["masked"], row["single"], factor=1 / 3), holds_when=-1)


def stays_successful(row: dict[str, Cell]) -> str:
    """holds: under 50 % masking clearly above half the unmasked single view's success."""
    return resolved_as(compare(row["masked"], row["single"], factor=1 / 2), holds_when=1)


def masked_vs_single(masked: str, decide: Callable[[dict[str, Cell]], str]):
    """A judge of a Table 4 cell under 50 % masking against the unmasked single view, per task."""

    def judge(tables: Tables) -> Judged:
        verdicts, evidence = [], []
        for task in TASKS:
            single, cell = tables.get("table4", task, SINGLE, 0.0), tables.get("table4", task, masked, 0.5)
            if single is None or cell is None:
                continue
            verdict = decide({"single": single, "masked": cell})
            verdicts.append(verdict)
            evidence.append(f"{task}: {cell.text()} at 50 % vs single view unmasked {single.text()} ({verdict})")
        return Judged(verdicts, evidence, len(TASKS))

    return judge


def _time_costs(tables: Tables) -> Judged:
    """Table 5: time per update relative to the single view, within 0.25 of the paper's."""
    names = list(TABLE5)
    cells = [tables.get("table5", "place_in_box", name) for name in names]
    if any(c is None for c in cells):
        return Judged([], [], 1)
    ratio = {name: cells[0].steps_per_s / c.steps_per_s for name, c in zip(names, cells, strict=True)}
    close = all(abs(ratio[n] - TABLE5[n]) <= 0.25 for n in names)
    ordered = (
        ratio["dropout-global+adjacent"] < ratio["separated_q-global+adjacent"]
        and ratio["dropout-global+adjacent+top"] > ratio["dropout-global+adjacent"]
        and ratio["separated_q-global+adjacent+top"] > ratio["separated_q-global+adjacent"]
    )
    verdict = HOLDS if close else PARTLY if ordered else FAILS
    text = ", ".join(f"{n} {ratio[n]:.2f} (paper {TABLE5[n]:.2f})" for n in names[1:])
    return Judged([verdict], [f"place_in_box: {text} ({verdict})"], 1)


def _gain_follows_the_added_view(tables: Tables) -> Judged:
    """Table 6 against Table 3 (task 1): the added views ranked as their own single views."""
    views = ["top", "side", "active"]
    singles = tables.row("table3", "place_in_box", [f"single-{v}" for v in views])
    verdicts, evidence = [], []
    for mask_p in (0.0, 0.5):
        pairs = tables.row("table6", "place_in_box", [f"separated_q-global+{v}" for v in views], mask_p)
        if singles is None or pairs is None:
            continue
        # each two added views: ordered alike with global as alone, where both orders are resolved
        agree = []
        for a, b in itertools.combinations(views, 2):
            alone = compare(singles[f"single-{a}"], singles[f"single-{b}"])
            added = compare(pairs[f"separated_q-global+{a}"], pairs[f"separated_q-global+{b}"])
            if alone is not None and added is not None:
                agree.append(alone == added)
        verdict = UNRESOLVED if not agree else HOLDS if all(agree) else FAILS if not any(agree) else PARTLY
        verdicts.append(verdict)
        with_global = ", ".join(f"{v} {pairs[f'separated_q-global+{v}'].text()}" for v in views)
        alone_text = ", ".join(f"{v} {singles[f'single-{v}'].text()}" for v in views)
        evidence.append(f"{mask_p:.0%} masking: global + {with_global}; alone {alone_text} ({verdict})")
    return Judged(verdicts, evidence, 2)


def _more_help_up_to_1000(row: dict[str, Cell]) -> str:
    return resolved_as(compare(row["demos1000"], row["demos250"]), holds_when=1)


def _no_gain_beyond_1000(row: dict[str, Cell]) -> str:
    """does not hold: 2000 or 3000 clearly above 1000; holds: both clearly below; else not resolved."""
    found = {compare(row[k], row["demos1000"]) for k in ("demos2000", "demos3000")}
    return FAILS if 1 in found else HOLDS if found == {-1} else UNRESOLVED


def masking_claim(cell: str, what: str, paper: str, fails: bool) -> Claim:
    """A Table 4 claim about one method under 50 % masking, judged against the unmasked single view."""
    if fails:
        return Claim(
            "Table 4",
            f"{what} fails under 50 % masking (paper {paper} %)",
            "per task, below a third of the unmasked single view's success",
            masked_vs_single(cell, fails_under_masking),
        )
    return Claim(
        "Table 4",
        f"{what} stays successful under 50 % masking (paper {paper} %)",
        "per task, at least half the unmasked single view's success",
        masked_vs_single(cell, stays_successful),
    )


CLAIMS = [
    Claim(
        "Table 1",
        "128 units per layer give the highest success of the widths 32-256",
        "the 128-unit cell is clearly above the best other width",
        per_masking(
            "table1",
            [f"single-global-{w}" for w in (32, 64, 128, 256)],
            lambda row: best_verdict(row, "single-global-128"),
            levels=(0.0,),
        ),
    ),
    Claim(
        "Table 2",
        "epsilon 2.0 gives the highest success of the five thresholds",
        "the paper-epsilon-2 cell (mapped to our scale) is clearly above the best other threshold",
        per_masking(
            "table2",
            [f"single-global-paper-eps{e}" for e in ("0.1", "1", "2", "3", "5")],
            lambda row: best_verdict(row, "single-global-paper-eps2"),
            levels=(0.0,),
        ),
    ),
    Claim(
        "Table 3",
        "global and adjacent are the best single views on every task",
        "per task, global and adjacent are each clearly above the best of top, side and active "
        "(partly: one above, one below)",
        per_task("table3", [f"single-{v}" for v in VIEWS], 0.0, _top_two, {f"single-{v}": v for v in VIEWS}),
    ),
    masking_claim(SINGLE, "a single view", "0 / 3 / 0", fails=True),
    masking_claim(CONCAT, "concatenation", "4 / 12 / 4", fails=True),
    masking_claim(DROPOUT, "MURM dropout", "36 / 40 / 10", fails=False),
    masking_claim(SEPARATED, "MURM separated Q", "38 / 44 / 15", fails=False),
    Claim(
        "Table 4",
        "separated Q is the best method under masking",
        "per task at 50 % masking, separated Q is clearly above the best of single, concat and dropout",
        per_task(
            "table4",
            [SINGLE, CONCAT, DROPOUT, SEPARATED],
            0.5,
            lambda row: best_verdict(row, SEPARATED),
            {SINGLE: "single", CONCAT: "concat", DROPOUT: "dropout", SEPARATED: "separated Q"},
        ),
    ),
    Claim(
        "Table 5",
        "dropout trains in about the single view's time (1.05x), separated Q in about 1.5x, "
        "and each added view costs about 0.5x more",
        "every ratio within 0.25 of the paper's (partly: the same order: dropout < separated Q, three cameras > two)",
        _time_costs,
    ),
    Claim(
        "Table 6",
        "the gain from adding a view follows that view's own single-view success",
        "each two of top / side / active whose order is resolved both alone (Table 3) and added to "
        "global (separated Q) are in the same order (partly: some pairs are), at 0 and 50 % masking",
        _gain_follows_the_added_view,
    ),
    Claim(
        "Table 7",
        "more demonstrations help up to about 1000",
        "1000 demonstrations clearly above 250, at 0 and 50 % masking",
        per_masking("table7", ["demos250", "demos1000"], _more_help_up_to_1000),
    ),
    Claim(
        "Table 7",
        "more than about 1000 demonstrations bring no further gain",
        "neither 2000 nor 3000 clearly above 1000 and both clearly below it (does not hold: one clearly above), "
        "at 0 and 50 % masking",
        per_masking("table7", ["demos1000", "demos2000", "demos3000"], _no_gain_beyond_1000),
    ),
    Claim(
        "Table 7",
        "a fully noisy dataset is best",
        "the 100 %-noisy cell (1000 demonstrations) clearly above the best of 0 / 25 / 50 % noisy, "
        "at 0 and 50 % masking",
        per_masking(
            "table7",
            ["noisy0", "noisy25", "noisy50", "demos1000"],
            lambda row: best_verdict(row, "demos1000"),
            {"demos1000": "noisy100"},
        ),
    ),
]


def judge_claims(results_dir: Path) -> list[Verdict]:
    tables = Tables(results_dir)
    verdicts = []
    for claim in CLAIMS:
        judged = claim.judge(tables)
        verdict = combine(judged.verdicts)
        resolved = sum(v != UNRESOLVED for v in judged.verdicts)
        if judged.conditions > 1 and resolved:  # "not resolved" alone says none was
            verdict += f" ({resolved} of {len(judged.verdicts)} resolved)"
        if 0 < len(judged.verdicts) < judged.conditions:
            verdict += f" ({len(judged.verdicts)} of {judged.conditions} run)"
        verdicts.append(Verdict(claim, verdict, "; ".join(judged.evidence) or "-"))
    return verdicts


def claims_table(results_dir: Path, rules: bool = True) -> str:
    """Markdown: one row per claim with its verdict and our numbers (test episodes, success %
    mean ± sample std over seeds), then the rules."""
    verdicts = judge_claims(results_dir)
    lines = ["| | the paper's claim | verdict here | our numbers |", "|---|---|---|---|"]
    for v in verdicts:
        lines.append(f"| {v.claim.source} | {v.claim.text} | **{v.verdict}** | {v.evidence} |")
    text = "\n".join(lines) + "\n"
    if rules:
        text += (
            "\nHow each verdict is decided (fixed before the v2 tables ran; "
            "`lerobot_murm/experiments/claims.py`):\n\n"
            + "\n".join(f"- {v.claim.source}, {v.claim.text}: {v.claim.rule}." for v in verdicts)
            + "\n"
            + DEFINITIONS
        )
    return text


HINDSIGHT = "-hindsight"  # the label suffix of a cell trained on hindsight goals (configs/reproduce/hindsight.yaml)


def goal_source_table(results_dir: Path, grid: str) -> str:
    """Markdown: each cell of `grid` trained on hindsight goals beside the same cell trained on
    the rendered goal images, per task and masking level, judged by `compare` (issue 44's
    rule, fixed in REPORT.md's protocol before its runs); "" when the grid has no such pair."""
    tables = Tables(results_dir)
    lines = []
    for (name, task, cell, mask_p), hindsight in tables.cells.items():
        rendered = tables.get(grid, task, cell.replace(HINDSIGHT, ""), mask_p)
        if name != grid or HINDSIGHT not in cell or rendered is None:
            continue
        if hindsight.mean < FLOOR_PERCENT and rendered.mean < FLOOR_PERCENT:
            verdict = "not resolved (both under 5 %)"
        else:
            verdict = {1: "clearly better", -1: "clearly worse", None: "no clear difference"}[
                compare(hindsight, rendered)
            ]
        lines.append(
            f"| {task} | {cell.replace(HINDSIGHT, '')} | {100 * mask_p:.0f} % | {rendered.text()} | "
            f"{hindsight.text()} | {hindsight.mean - rendered.mean:+.0f} | {verdict} |"
        )
    if not lines:
        return ""
    header = (
        "| task | cell | masking | rendered goals | hindsight goals | difference | hindsight against rendered |\n"
        "|---|---|---:|---:|---:|---:|---|\n"
    )
    return header + "\n".join(lines) + "\n"
