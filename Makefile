# make demo: set everything up (system packages, .venv, Python packages) and run a simulated scan.
# make test: the whole test suite (what .ci/run calls). make serve: the service (README, "Service").
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed
# the project runs on Python 3.11 (pyproject.toml): python3.11 where there is one, else python3
PYTHON ?= $(shell command -v python3.11 || command -v python3)

.PHONY: demo test lint bench setup clean serve dist

demo: $(STAMP)
	$(VENV)/bin/cell scan

setup: $(STAMP)

# the service of the embedded default cell on http://127.0.0.1:8080 (data dir: data/)
serve: $(STAMP)
	$(VENV)/bin/cell serve

# setup.py and the .pyx: the compiled kernels are rebuilt when their source changes.
$(STAMP): pyproject.toml setup.py cell/perception/_kernels.pyx cell/planning/vs/_objective.pyx \
		cell/planning/lrnbv/_raygains.pyx \
		deploy/system-deps.sh
	bash deploy/system-deps.sh
	@$(PYTHON) -c 'import sys; sys.exit(sys.version_info[:2] != (3, 11))' || \
		{ echo "cell needs Python 3.11 and $(PYTHON) is $$($(PYTHON) -V): make PYTHON=/path/to/python3.11"; exit 1; }
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -e '.[dev]'
	touch $(STAMP)

# pytest exits 5 when it collects no test: that is reported, not a failure. The suite runs in
# TEST_WORKERS processes (pytest-xdist), each test file in one of them (its module fixtures built once),
# handed out in collection order, the longest files first (tests/conftest.py): two, the CI machine's cores.
TEST_WORKERS ?= 2
test: $(STAMP)
	@$(VENV)/bin/pytest -q -n $(TEST_WORKERS) --dist loadfile --no-loadscope-reorder; rc=$$?; \
	if [ $$rc -eq 5 ]; then echo "pytest collected no tests"; exit 0; fi; exit $$rc

# mypy checks the packages listed in pyproject.toml's [tool.mypy] files (cell, drivers, benchmarks).
lint: $(STAMP)
	$(VENV)/bin/ruff check cell drivers tests benchmarks
	$(VENV)/bin/mypy

# the sdist and the wheel (the kernels compiled from the sdist) in dist/: what `pip install` takes on a cell's PC
dist: $(STAMP)
	$(PY) -m build --outdir dist .

# The quick benchmarks that need nothing but the .venv (about 1.5 min on 2 cores), one after another; each
# prints its figures and, last, one line of JSON. The others start services, an RTDE peer on the UR's fixed
# ports or long scan grids, and are run by hand (README, "Benchmarks").
BENCH_QUICK := sim_render perception_cycle map_vs_octomap servo_rate guard_tick ik_solve lrnbv_iteration \
	vl53l8cx_link
bench: $(STAMP)
	@set -e; for b in $(BENCH_QUICK); do echo "== benchmarks/$$b.py"; $(PY) benchmarks/$$b.py; done

clean:
	rm -rf $(VENV) dist *.egg-info .pytest_cache .ruff_cache .mypy_cache build cell/perception/_kernels.c \
		cell/planning/vs/_objective.c cell/planning/lrnbv/_raygains.c cell/perception/*.so cell/planning/*/*.so
