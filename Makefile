PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: demo test test-all bench clean

$(BIN)/python:
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install -q --upgrade pip

$(STAMP): $(BIN)/python pyproject.toml
	$(BIN)/pip install -q -e '.[test]'
	touch $(STAMP)

demo: $(STAMP)
	$(BIN)/swarmloc demo

# The fast tier: everything not marked slow, fuzzing at a twentieth of its size (minutes).
test: $(STAMP)
	SWARMLOC_FUZZ_SCALE=0.05 $(BIN)/python -m pytest -q -m "not slow"

# Everything, fuzzing at full size: what CI runs.
test-all: $(STAMP)
	$(BIN)/python -m pytest -q

bench: $(STAMP)
	$(BIN)/python benchmarks/bench_lockstep.py

clean:
	rm -rf $(VENV) runs
