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

.PHONY: install test test-slow lint format rig train-skel train-dyn prepare-data experiments clean

install:
	$(PYTHON) -m venv $(VENV)
	$(VENV)/bin/pip install --upgrade pip
	$(VENV)/bin/pip install -e '.[dev]'

test:
	$(VENV)/bin/pytest -q -n auto --dist loadscope

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

# Your capture to a rig in one command: FROM (one folder of mesh or point frames, or one folder
# per sequence), OUT (RIG.glb; RIG.bvh and RIG.png beside it); PRESET, STEPS as for train-skel.
FROM ?=
OUT ?=

rig:
	$(if $(and $(FROM),$(OUT)),,$(error give FROM=RAW and OUT=RIG.glb, e.g. make rig FROM=scans OUT=scan.glb PRESET=cpu))
	$(NMJAX) rig --from $(FROM) --out $(OUT) --preset $(PRESET) $(if $(STEPS),--steps $(STEPS)) $(ARGS)

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

# The paper's results on the synthetic bodies at the cpu preset -> experiments/results/. Phase 1:
# a row per (body, seed, variant), phase 2: a row per body on its seed-0 preset row, each kept
# across sessions (experiments/paper_phase1.py and paper_phase2.py say when). EXP_DATA: the bodies
# (default all four); SEEDS (0 1); STEPS: phase-1 steps instead of the preset's (smoke runs only).
SEEDS ?= 0 1
EXP_DATA ?= synth-arm synth-hand synth-human synth-quadruped
EXP_PY := JAX_PLATFORMS=cpu $(VENV)/bin/python

experiments:
	$(EXP_PY) experiments/paper_phase1.py --data $(EXP_DATA) --seeds $(SEEDS) \
		$(if $(STEPS),--steps $(STEPS))
	$(EXP_PY) experiments/paper_phase2.py --data $(EXP_DATA)

clean:
	rm -rf .pytest_cache .ruff_cache build src/*.egg-info
