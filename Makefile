# parammap: `make demo` runs the workflow on the built-in demo capture, `make test` the
# tests. Both create .venv with pinned dependencies on first use.
PYTHON ?= $(shell command -v python3.11 || command -v python3)
VENV := .venv
BIN := $(VENV)/bin
CORES ?= all
# pytest-xdist workers for `make test`: a module's tests stay on one worker (their
# module fixtures are built once)
TEST_WORKERS ?= auto

.PHONY: demo test lint report paper clean-reports setup setup-pbr setup-docs docs browser

setup: $(VENV)/.installed

# The physically based test captures (Mitsuba 3): an optional extra, installed for the
# tests and benchmarks, never needed by the pipeline itself.
setup-pbr: $(VENV)/.installed-pbr

$(VENV)/.installed-pbr: $(VENV)/.installed requirements-pbr.lock
	$(BIN)/python -m pip install --quiet --no-compile -r requirements-pbr.lock
	touch $@

# The documentation site (MkDocs Material, API pages from the docstrings).
setup-docs: $(VENV)/.installed-docs

$(VENV)/.installed-docs: $(VENV)/.installed requirements-docs.lock
	$(BIN)/python -m pip install --quiet --no-compile -r requirements-docs.lock
	touch $@

# Warnings are errors, so that a broken link or docstring cannot land.
docs: setup-docs
	NO_MKDOCS_2_WARNING=1 $(BIN)/mkdocs build --strict --quiet

# --no-compile: pip would byte-compile every module of every package (a third of the
# set-up's time); Python compiles the ones a run imports, once
$(VENV)/.installed: pyproject.toml requirements.lock
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --no-compile --upgrade pip
	$(BIN)/python -m pip install --quiet --no-compile -r requirements.lock
	$(BIN)/python -m pip install --quiet --no-compile --no-deps -e .
	touch $@

demo: setup
	$(BIN)/snakemake --cores $(CORES) --profile profiles/default
	$(BIN)/snakemake --cores 1 --profile profiles/default --report reports/report.html
	@echo "Report: reports/report.html  Viewer: reports/demo/viewer/index.html"

# 004's experiments under the published conditions: tables in reports/paper/.
paper: setup
	$(BIN)/snakemake --cores $(CORES) --profile profiles/default --forcerun paper paper

# Rebuild every report figure and table from the stage outputs (no refitting).
report: setup
	$(BIN)/snakemake --cores $(CORES) --profile profiles/default
	$(BIN)/snakemake --cores 1 --profile profiles/default --report reports/report.html

# The viewer test drives the system Chromium (Debian package). Without it (no root, no
# apt) the viewer tests are skipped and say so, except under CI (CI set), where a
# browser that cannot be installed fails the run instead of skipping the tests.
browser:
	@command -v chromium >/dev/null 2>&1 || { [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null \
	  && (apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq chromium) \
	  >/dev/null 2>&1 || { if [ -n "$$CI" ] && [ "$$CI" != false ]; then \
	  echo "error: CI is set and chromium could not be installed (apt-get install chromium)"; \
	  exit 1; else echo "note: chromium not installed; viewer tests will be skipped"; fi; }; }

test: setup setup-pbr setup-docs browser
	$(BIN)/ruff check src tests workflow/scripts benchmarks
	$(BIN)/snakemake --lint --cores 1 --dry-run >/dev/null
	NO_MKDOCS_2_WARNING=1 $(BIN)/mkdocs build --strict --quiet
	# one BLAS thread a worker: the workers already fill the cores
	OPENBLAS_NUM_THREADS=1 $(BIN)/python -m pytest -q -n $(TEST_WORKERS) --dist loadfile \
	  --no-loadscope-reorder

lint: setup
	$(BIN)/ruff check src tests workflow/scripts benchmarks
	$(BIN)/snakemake --lint

clean-reports:
	rm -rf reports
