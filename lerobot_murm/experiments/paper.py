"""The paper's numbers (success rate %, tasks 1-3), to set beside ours in REPORT.md.

Keys are our (cell label, evaluation masking) for the rows we reproduce.
"""

TASKS = ("place_in_box", "place_in_random_box", "pick_up")

TABLE4 = {  # Table 4: after offline RL, 3 seeds
    ("single-global", 0.5): (0.0, 3.17, 0.0),
    ("single-global", 0.1): (11.35, 20.1, 7.85),
    ("concat-global+adjacent", 0.5): (4.22, 11.65, 3.93),
    ("dropout-global+adjacent", 0.5): (36.07, 40.2, 9.67),
    ("separated_q-global+adjacent", 0.5): (38.35, 43.96, 14.88),
}

TABLE3 = {  # Table 3: single-view baselines, no masking
    ("single-global", 0.0): (34.49, 46.63, 15.74),
    ("single-adjacent", 0.0): (33.76, 39.50, 14.65),
    ("single-top", 0.0): (18.84, 38.65, 0.17),
    ("single-side", 0.0): (17.99, 33.86, 12.74),
    ("single-active", 0.0): (12.51, 8.68, 3.63),
}

PAPER_TABLES = {"table3": TABLE3, "table4": TABLE4}
