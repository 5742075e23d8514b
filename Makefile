# The two commands of the README: `make run` and `make test`. Both install first (once).
VENV := .venv
STAMP := $(VENV)/.installed

.PHONY: install run test test-fast lint bench tables status

$(STAMP): pyproject.toml scripts/install.sh
	bash scripts/install.sh
	touch $@

install: $(STAMP)

run: $(STAMP)
	$(VENV)/bin/murm demo --out outputs/demo
	$(VENV)/bin/murm reproduce --config configs/reproduce/smoke.yaml

# pytest exits 5 when it collects no test: that is not a failure of the suite. Two pytest-xdist
# workers (TEST_WORKERS=0: one process): most tests wait on their subprocesses, so two at a time
# fill 2 cores (23.6 -> 17.1 min on a 2-core Xeon, README "The test suite").
TEST_WORKERS := 2
test: $(STAMP)
	$(VENV)/bin/python -m pytest -q -n $(TEST_WORKERS) --dist worksteal --durations=15; rc=$$?; if [ $$rc -eq 5 ]; then echo "no tests collected"; exit 0; fi; exit $$rc

# What CI checks before the tests: ruff's rules and its formatting (pyproject.toml [tool.ruff]).
LINTED := lerobot_murm lerobot_policy_murm tests benchmarks scripts
lint: $(STAMP)
	$(VENV)/bin/ruff check $(LINTED)
	$(VENV)/bin/ruff format --check $(LINTED)

# The inner loop: everything but the end-to-end tests marked slow (CI runs `make test`).
test-fast: $(STAMP)
	$(VENV)/bin/python -m pytest -q -m "not slow" --durations=10

# Study v2: Tables 3 and 4 first (they carry the claims; the hindsight grid of issue 44 between
# them costs two cells, Table 4 takes its other two), then 6, 7, 1, 2, 5; each later grid
# starting the runs it shares from an earlier one's (Table 4 <- hindsight, Table 2 <- Table 3);
# stop it at any time, it resumes where it was. WORK_DIR holds the datasets, caches and runs
# (tens of GB; a finished run is tested from the policies kept there, so put it on a disk that
# outlives the machine's sessions).
GRIDS := prepare table3 hindsight table4 paper_budget table6 table7 table1 table2 table5
JOBS := 2
WORK_DIR := outputs/murm
tables: $(STAMP)
	for grid in $(GRIDS); do $(VENV)/bin/murm reproduce --config configs/reproduce/$$grid.yaml --jobs $(JOBS) --work_dir=$(WORK_DIR) || exit 1; done
	$(VENV)/bin/murm report --readme README.md

# Where each grid of the study stands and the hours it and the whole study have left, a grid not
# started costed by the earlier grids' runs (reads only; beside a running `make tables`).
status: $(STAMP)
	$(VENV)/bin/murm status $(foreach grid,$(GRIDS),--config configs/reproduce/$(grid).yaml) --work_dir=$(WORK_DIR)

bench: $(STAMP)
	$(VENV)/bin/python benchmarks/bench_env.py
