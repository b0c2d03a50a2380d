# Quick start: `make demo` runs the pipeline on the built-in phantom, `make test` runs the tests.
# Each target creates the virtual environment (.venv) and installs what it needs.
PY ?= python3
VENV ?= .venv
BIN := $(VENV)/bin

.PHONY: venv demo test lint bench clean

$(BIN)/activate:
	$(PY) -m venv $(VENV)
	$(BIN)/pip install -q --upgrade pip

$(VENV)/.installed: $(BIN)/activate pyproject.toml
	bash scripts/install-system-deps.sh
	$(BIN)/pip install -q torch==2.13.0
	$(BIN)/pip install -q -e ".[test]"
	touch $@

venv: $(VENV)/.installed

demo: venv
	$(BIN)/tissuecast demo

test: venv
	$(BIN)/python -m pytest -q

lint: venv
	$(BIN)/ruff check src tests benchmarks examples scripts

# The benchmarks that run on their own; the others measure a data set or a model you give them
# (`python benchmarks/NAME.py --help`).
STANDALONE_BENCHMARKS := anatomies batching brain_label_map dataset_throughput igtl_latency label_map_fidelity \
	organ_speed pin_identifiability predict_latency preset_run scaling scenarios_vs_calculix solver_speed \
	solver_vs_calculix

bench: venv
	for b in $(STANDALONE_BENCHMARKS); do $(BIN)/python benchmarks/$$b.py || exit 1; done

clean:
	rm -rf $(VENV) build dist src/*.egg-info
