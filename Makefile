# The two commands in the README: `make run` (main job on the built-in phantom) and `make test`.
# Python 3.11+ (python3.11 if present, else python3).
PYTHON ?= $(shell command -v python3.11 2>/dev/null || command -v python3)
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed
# Triton (~300 MB wheel): only the tests need it here, to run the GPU kernels in its CPU interpreter.
GPU_STAMP := $(VENV)/.installed-gpu
# Idle OpenMP threads sleep instead of spinning: with several jobs per machine, spinning makes torch ~5x slower.
export OMP_WAIT_POLICY ?= PASSIVE

.PHONY: run test lint

$(STAMP): pyproject.toml constraints.txt
	@$(PYTHON) -c "import sys; assert sys.version_info >= (3, 11)" 2>/dev/null || { echo "error: need Python >= 3.11 (found '$(PYTHON)'); run make PYTHON=/path/to/python3.11"; exit 1; }
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	# torch first, pinned, so the project's install never picks another build. Whether a plain install is the CPU
	# wheel depends on the index: this machine's serves it; PyPI on Linux serves the CUDA build, hence TORCH_INDEX.
	$(PY) -m pip install --quiet torch==2.13.0 $(if $(TORCH_INDEX),--index-url $(TORCH_INDEX))
	$(PY) -m pip install --quiet -c constraints.txt -e ".[j2k,dev]"
	touch $(STAMP)

$(GPU_STAMP): $(STAMP)
	$(PY) -m pip install --quiet -c constraints.txt -e ".[j2k,dev,gpu]"
	touch $(GPU_STAMP)

run: $(STAMP)
	$(VENV)/bin/snakemake --cores 2 --configfile config/config.yaml
	$(VENV)/bin/snakemake --cores 2 --configfile config/config.yaml --report results/report.html

test: $(GPU_STAMP)
	$(VENV)/bin/python -m pytest -q

lint: $(STAMP)
	$(VENV)/bin/ruff check ctsplat scripts tests benchmarks
