# Thin wrappers over the `nmjax` command; every option can also be passed through ARGS.
PYTHON ?= python3
VENV := .venv
NMJAX := $(VENV)/bin/nmjax
DATA ?= synth-hand
PRESET ?= default
STEPS ?=
RUN ?=
RESUME ?= 0
ARGS ?=

SKEL_FLAGS := --data $(DATA) --preset $(PRESET) $(if $(STEPS),--steps $(STEPS)) \
	$(if $(RUN),--run $(RUN)) $(if $(filter 1,$(RESUME)),--resume)

.PHONY: install test test-slow lint format train-skel train-dyn prepare-data experiments clean

install:
	$(PYTHON) -m venv $(VENV)
	$(VENV)/bin/pip install --upgrade pip
	$(VENV)/bin/pip install -e '.[dev]'

test:
	$(VENV)/bin/pytest -q -n 2 --dist loadscope

test-slow:
	$(VENV)/bin/pytest -q -m slow

lint:
	$(VENV)/bin/ruff check src tests experiments
	$(VENV)/bin/ruff format --check src tests experiments

format:
	$(VENV)/bin/ruff format src tests experiments
	$(VENV)/bin/ruff check --fix src tests experiments

prepare-data:
	$(NMJAX) prepare-data --data $(DATA) $(ARGS)

train-skel:
	$(NMJAX) train-skel $(SKEL_FLAGS) $(ARGS)

# Phase 2 on a phase-1 run: SKEL_RUN defaults to the latest runs/skel-$(DATA)-*; MODEL=nm|vrnn.
SKEL_RUN ?=
MODEL ?= nm
DYN_FLAGS := --data $(DATA) --model $(MODEL) --preset $(PRESET) \
	$(if $(SKEL_RUN),--skel-run $(SKEL_RUN)) $(if $(STEPS),--steps $(STEPS)) \
	$(if $(RUN),--run $(RUN)) $(if $(filter 1,$(RESUME)),--resume)

train-dyn:
	$(NMJAX) train-dyn $(DYN_FLAGS) $(ARGS)

# Paper tables on the synthetic bodies at CPU scale -> experiments/results/*.md and plots.
# STEPS: phase-1 steps per run (default 2000); DYN_STEPS: phase-2 steps (default 3000);
# EXP_DATA: the bodies, e.g. EXP_DATA="synth-arm synth-hand" (default: each script's own list).
DYN_STEPS ?= 3000
EXP_STEPS = $(or $(STEPS),2000)
EXP_DATA ?=
EXP_FLAGS = $(if $(EXP_DATA),--data $(EXP_DATA))
EXP_PY := JAX_PLATFORMS=cpu $(VENV)/bin/python

experiments:
	$(EXP_PY) experiments/table1_2_9_10_phase1.py --steps $(EXP_STEPS) $(EXP_FLAGS)
	$(EXP_PY) experiments/ltraj_ablation.py --steps $(EXP_STEPS) $(EXP_FLAGS)
	$(EXP_PY) experiments/table11_12_interpolation.py --skel-steps $(EXP_STEPS) \
		--dyn-steps $(DYN_STEPS) $(EXP_FLAGS)

clean:
	rm -rf .pytest_cache .ruff_cache build src/*.egg-info
