# Two commands for a newcomer: `make demo` and `make test`.
# The virtual environment is built from this project's own files only.
PYTHON ?= python3
VENV   := .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed-stamp

.PHONY: demo test test-fast bench clean

$(STAMP): pyproject.toml
	@$(PYTHON) -c 'import sys; sys.exit(sys.version_info < (3, 11))' || \
	  { echo "Python 3.11+ is needed (PYTHON=$(PYTHON) is older)"; exit 1; }
	@test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip
	$(BIN)/python -m pip install -q -e '.[dev]'
	@touch $(STAMP)

# Until the rig's session runner lands (issue 3), the demo generates the standard set
# with the simulator and identifies theta4/theta6/theta16 from a start 15-40 % off.
DEMO_DIR := out/demo
demo: $(STAMP)
	$(BIN)/python -m simulator generate --plan standard --out $(DEMO_DIR) --seed 1 --drop
	$(BIN)/python -m identify fit $(DEMO_DIR) --model 2dof --params examples/start-2dof.json \
	  --estimate theta4,theta6,theta16 --output $(DEMO_DIR)/RESULT.json --figures $(DEMO_DIR)/figures
	@echo "simulator truth: theta4 = 0.005, theta6 = -3.0, theta16 = 0.85 ($(DEMO_DIR)/truth.json)"

test: $(STAMP)
	QT_QPA_PLATFORM=offscreen $(BIN)/python -m pytest -q

test-fast: $(STAMP)
	QT_QPA_PLATFORM=offscreen $(BIN)/python -m pytest -q -m "not slow"

bench: $(STAMP)
	@for b in benchmarks/bench_*.py; do echo "== $$b"; $(BIN)/python $$b || exit 1; done

clean:
	rm -rf $(VENV) .pytest_cache build *.egg-info
