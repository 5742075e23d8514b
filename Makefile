# The two commands of the README: `make run` and `make test`. Both install first (once).
VENV := .venv
STAMP := $(VENV)/.installed

.PHONY: install run test bench

$(STAMP): pyproject.toml scripts/install.sh
	bash scripts/install.sh
	touch $@

install: $(STAMP)

run: $(STAMP)
	$(VENV)/bin/murm demo --out outputs/demo
	$(VENV)/bin/murm reproduce --config configs/reproduce/smoke.yaml

# pytest exits 5 when it collects no test: that is not a failure of the suite.
test: $(STAMP)
	$(VENV)/bin/python -m pytest -q; rc=$$?; if [ $$rc -eq 5 ]; then echo "no tests collected"; exit 0; fi; exit $$rc

bench: $(STAMP)
	$(VENV)/bin/python benchmarks/bench_env.py
