# The two commands in the README: `make run` (main job on the built-in phantom) and `make test`.
PYTHON ?= python3.11
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed

.PHONY: run test lint clean-venv

$(STAMP): pyproject.toml constraints.txt
	@command -v $(PYTHON) >/dev/null 2>&1 || { echo "error: $(PYTHON) not found; install Python 3.11 or run 'make PYTHON=python3 ...'"; exit 1; }
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	# torch first, pinned: on CPU machines this resolves to the local CPU wheel, never the CUDA stack.
	$(PY) -m pip install --quiet torch==2.13.0
	$(PY) -m pip install --quiet -c constraints.txt -e ".[j2k,dev]"
	touch $(STAMP)

run: $(STAMP)
	$(VENV)/bin/snakemake --cores 2 --configfile config/config.yaml
	$(VENV)/bin/snakemake --cores 2 --configfile config/config.yaml --report results/report.html

test: $(STAMP)
	$(VENV)/bin/python -m pytest -q

lint: $(STAMP)
	$(VENV)/bin/ruff check ctsplat scripts tests benchmarks
