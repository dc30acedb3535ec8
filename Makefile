# Two commands on a fresh machine: `make demo` and `make test` (README.md).
VENV := .venv
PY := $(VENV)/bin/python
CLI := $(VENV)/bin/mi-shadowgs
PRESET ?= cpu-small
SCENE ?= mi_shadowgs/scenes/default.xml
DEMO_DIR ?= runs/demo
# Python caches the modules it compiles (__pycache__): the suite starts hundreds of
# processes, each of which would compile ~550 modules again (1.4 s) where the environment
# asks for no bytecode (as container images often do). docs/decisions.md has the figures.
unexport PYTHONDONTWRITEBYTECODE

.PHONY: install install-dev demo test bench validate results docs lint lock clean

$(VENV)/.installed: pyproject.toml $(wildcard constraints.txt) scripts/setup.sh
	bash scripts/setup.sh

# The test tools, JAX (tests/test_lpips.py) and Ray (the cluster extra, tests/test_batch.py):
# only what make test and make lint need.
$(VENV)/.installed-dev: $(VENV)/.installed
	bash scripts/setup.sh --dev

# The libLLVM check runs every time (cached, under a second): a library removed after the
# venv was made is put back before any test imports drjit.
install: $(VENV)/.installed
	@bash scripts/setup.sh --llvm

install-dev: install $(VENV)/.installed-dev

# run writes the report (RUN/report.html) itself.
demo: install
	$(CLI) generate $(SCENE) --out $(DEMO_DIR)/data --preset $(PRESET)
	$(CLI) run $(DEMO_DIR)/data --out $(DEMO_DIR)/run --preset $(PRESET)

# The viewer's browser test needs chromium and chromium-driver (installed here when root),
# the splat tools' tests PlayCanvas's splat-transform (npm, into .venv/node; skipped without).
# The test files run on one process per core, at most TEST_WORKERS (pytest-xdist; a file's
# tests stay on one process, so its fixtures are made once), and each process's Dr.Jit gets
# its share of the cores (tests/conftest.py): on 2 cores, two processes of one thread each.
TEST_WORKERS ?= 4
test: install-dev
	@bash scripts/setup.sh --clients
	$(PY) -m pytest -q -n auto --maxprocesses $(TEST_WORKERS) --dist loadfile tests

# Each suite is kept once it has run (a killed `make bench` resumes); suites run at another
# commit, preset or machine exit 2 naming it: BENCH_ARGS=--overwrite runs them again.
# BENCH_ARGS="--results results" also writes the rasterizer's figures as a result file.
BENCH_ARGS ?=
bench: install
	$(PY) -m benchmarks.run_all --out bench-out $(BENCH_ARGS)

# The whole table (6 scenes x 2 light pairs, hours on 2 cores; resumed after a kill), Table 2,
# the filter drift and the report pages in headless Chromium. A subset:
#   make validate VALIDATE_ARGS="--scene bunny --lights low --only pipeline"
# The studies after the table exit 2 on units made from other inputs or settings:
#   make validate VALIDATE_ARGS=--overwrite
# VALIDATE_ARGS="--results results" also writes the table as a result file.
VALIDATE_ARGS ?=
validate: install
	@bash scripts/setup.sh --chromium
	$(PY) -m validation.run_all --out validation-out $(VALIDATE_ARGS)

# RESULTS.md and docs/results.md from the committed result files in results/ (the same
# bytes every time; tests/test_results.py checks they are current).
results:
	python3 -m scripts.results

# The documentation site from docs/ into site/: the CLI page from the parsers first, then
# mkdocs with --strict (a broken link or a missing page fails).
docs: install-dev
	$(PY) -m scripts.cli_docs
	$(VENV)/bin/mkdocs build --strict

# constraints.txt from the venv's versions (scripts/lock.py): after a version change that
# `make test` from zero passed with.
lock: install-dev
	$(PY) scripts/lock.py

lint: install-dev
	$(VENV)/bin/ruff check .

clean:
	rm -rf $(VENV) runs validation-out bench-out site .pytest_cache
