# Two commands for a newcomer: `make demo` and `make test`.
# The virtual environment is built from this project's own files only.
PYTHON ?= python3
VENV   := .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed-stamp

.PHONY: demo gui lint test test-fast bench clean qc-screenshots screenshots

$(STAMP): pyproject.toml
	@$(PYTHON) -c 'import sys; sys.exit(sys.version_info < (3, 11))' || \
	  { echo "Python 3.11+ is needed (PYTHON=$(PYTHON) is older)"; exit 1; }
	@test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip
	$(BIN)/python -m pip install -q -e '.[dev]'
	@touch $(STAMP)

# The whole product: the simulator at 50x, the standard plan over Modbus + serial,
# identification, parameters beside the simulator's truth (examples/demo.py).
demo: $(STAMP)
	$(BIN)/python examples/demo.py --out out/demo-session

# The operator's console on the virtual rig at 1x (python -m rig gui --help for a real rig).
gui: $(STAMP)
	$(BIN)/python -m rig gui --simulate --speed 1

# PNGs of the console's main views from a session on the virtual rig (offscreen).
screenshots: $(STAMP)
	QT_QPA_PLATFORM=offscreen $(BIN)/python -m rig.gui.screenshots --out out/screenshots

# Static checks (configured in pyproject.toml), run before the tests: a finding fails
# `make test` as a failing test would.
lint: $(STAMP)
	$(BIN)/ruff check .
	$(BIN)/mypy identify rig simulator tests benchmarks examples

# Two workers: much of the suite waits on simulated rigs and child processes, so two
# keep a 2-core machine busy (7.5 min against 13 serially, measured here).
test: $(STAMP) lint
	QT_QPA_PLATFORM=offscreen $(BIN)/python -m pytest -q -n 2 --dist worksteal --durations=15

test-fast: $(STAMP)
	QT_QPA_PLATFORM=offscreen $(BIN)/python -m pytest -q -n 2 --dist worksteal -m "not slow"

bench: $(STAMP)
	@for b in benchmarks/bench_*.py; do echo "== $$b"; $(BIN)/python $$b || exit 1; done

# A PASS and a FAIL QC report (and a control chart) as headless Chromium shows them, into
# out/screenshots/.  Debian's chromium is installed when missing (as root, or with sudo).
qc-screenshots: $(STAMP)
	@command -v chromium >/dev/null || { \
	  if [ "$$(id -u)" -eq 0 ]; then sudo=; else sudo="sudo -n"; fi; \
	  $$sudo env DEBIAN_FRONTEND=noninteractive apt-get install -y --no-install-recommends chromium; }
	$(BIN)/python examples/qc_screenshots.py --out out/screenshots

# Every screenshot of the product; each part adds its own target as a prerequisite.
screenshots: qc-screenshots

clean:
	rm -rf $(VENV) .pytest_cache .ruff_cache .mypy_cache build *.egg-info
