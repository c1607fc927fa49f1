# Two commands for a newcomer: `make demo` and `make test`. Both create .venv on first use.
PYTHON ?= python3
VENV   := .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.mocaprig-installed
# The CPU build of torch; a bare `torch` requirement would pull a multi-GB CUDA build.
TORCH_SPEC ?= torch==2.13.0
DEMO_OUT ?= demo-out
TEST_WORKERS ?= 2

.PHONY: install demo test lint typecheck unit bench clean firmware

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet "$(TORCH_SPEC)"
	$(PY) -m pip install --quiet -e '.[dev]'
	# The D415 adapter's SDK (the `realsense` extra); optional where no wheel exists.
	$(PY) -m pip install --quiet -e '.[realsense]' || echo "note: pyrealsense2 not installable here; its tests will skip"
	touch $(STAMP)

install: $(STAMP)

demo: $(STAMP)
	$(VENV)/bin/mocaprig demo --out $(DEMO_OUT) --overwrite

lint: $(STAMP)
	$(PY) -m ruff check .
	$(PY) -m ruff format --check .

typecheck: $(STAMP)
	$(PY) -m mypy

# The suite runs on TEST_WORKERS processes (pytest-xdist; a test file stays on one, so its
# module fixtures are built once), each with one BLAS/OpenMP/torch thread so that the workers
# do not spin against each other; files are handed out in the order tests/conftest.py puts them
# (slow ones first), not by their number of tests; the slowest tests are listed at the end.
unit: $(STAMP)
	OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1 MKL_NUM_THREADS=1 \
		$(PY) -m pytest -n $(TEST_WORKERS) --dist loadfile --no-loadscope-reorder --durations=15

test: lint typecheck unit

bench: $(STAMP)
	@for b in benchmarks/*.py; do echo "== $$b"; $(PY) $$b || exit 1; done

# The sync box firmware for the Uno and the Nano (build/firmware/<board>/syncbox.hex) and its
# interrupt latencies; needs gcc-avr binutils-avr avr-libc arduino-core-avr (Debian), not .venv.
firmware:
	$(PYTHON) firmware/syncbox/build.py --out build/firmware --latency

clean:
	rm -rf $(VENV) $(DEMO_OUT) .pytest_cache .mypy_cache .ruff_cache
