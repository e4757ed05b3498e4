# swarmnav — every user-facing entry point. `make setup` is idempotent; run/test depend on it.
PY      ?= python3
VENV    := .venv
BIN     := $(VENV)/bin
STAMP   := $(VENV)/.setup-stamp
CONFIG  ?= configs/paper.toml
ALGO    ?= atvfg
SEED    ?= 1
LIVE    ?=
MILUV   ?= ../shared/data/miluv/cirObstacles_3_random_0
export OMP_NUM_THREADS=1
export OPENBLAS_NUM_THREADS=1
export MKL_NUM_THREADS=1

.PHONY: setup demo run dropout miluv chaos bench view test test-fast evaluate clean help
help:            ## list targets and variables
	@grep -E '^[a-z-]+:.*##' $(MAKEFILE_LIST) | sed 's/:.*##/ —/'
	@echo "variables: CONFIG=$(CONFIG) ALGO=$(ALGO) SEED=$(SEED) MILUV=$(MILUV) LIVE=$(LIVE) (e.g. make run CONFIG=configs/smoke.toml ALGO=fg SEED=2; make run LIVE=1: follow the run in a Rerun viewer)"

setup: $(STAMP)  ## create/refresh .venv with the pinned dependencies
$(STAMP): requirements.lock pyproject.toml setup.py shared/swarmnav/estimators/_kernels.c shared/swarmnav/wire/_frames.c
	test -x $(BIN)/python || $(PY) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip
	$(BIN)/python -m pip install -q -r requirements.lock
	$(BIN)/python -m pip install -q --no-deps -e .
	touch $(STAMP)

demo: setup      ## 30-second first look: smoke (5 UAVs, 60 s), all five algorithms side by side in one recording (runs/demo)
	rm -rf runs/demo
	$(BIN)/swarmnav evaluate --config configs/smoke.toml --algos atvfg,fg,fkf,ins,central --seeds 1 --out runs/demo
	@if [ -n "$${DISPLAY:-}$${WAYLAND_DISPLAY:-}" ]; then $(BIN)/rerun runs/demo/evaluate.rrd & \
	else echo "recording: runs/demo/evaluate.rrd (no display here: open it with '$(CURDIR)/$(BIN)/rerun runs/demo/evaluate.rrd' on a machine with one, or serve it with --web-viewer)"; fi

run: setup       ## the paper scenario as a real multi-process Zenoh swarm (results in runs/latest)
	$(BIN)/swarmnav launch --config $(CONFIG) --algo $(ALGO) --seed $(SEED) $(if $(LIVE),--live)

dropout: setup   ## configs/dropout.toml: UAV 7 killed at 400 s, restarted at 600 s
	$(BIN)/swarmnav launch --config configs/dropout.toml --algo $(ALGO) --seed $(SEED)

miluv: setup     ## real MILUV flight (MILUV=dir): import, evaluate every algorithm, replay through the Zenoh swarm
	$(BIN)/swarmnav import-miluv $(MILUV) --out runs/miluv-dataset
	$(BIN)/swarmnav evaluate --dataset runs/miluv-dataset --algos atvfg,fg,ins,central,fkf --seeds 0 --out runs/miluv-evaluate
	$(BIN)/swarmnav launch --dataset runs/miluv-dataset --algo $(ALGO) --seed 0

chaos: setup     ## fault campaign on smoke (kills, freeze, monitor/sensor-sim/launcher/router faults) -> runs/chaos-<timestamp>/chaos.md
	$(BIN)/python -m deploy.chaos

bench: setup     ## scale benchmark on configs/scale.toml (<= 15 min): in-process cost per UAV-epoch for N = 18..1000, distributed vs in-process, RSS, profile -> bench/<timestamp>/bench.md, bench.json, cost_vs_n.png
	$(BIN)/python -m deploy.bench

evaluate: setup  ## in-process evaluation of all algorithms on CONFIG
	$(BIN)/swarmnav evaluate --config $(CONFIG) --algos atvfg,fg,fkf,ins,central --seeds $(SEED)

view: setup      ## open the latest recording in the Rerun viewer (prints the command when there is no display)
	@f=$$(ls runs/latest/*.rrd 2>/dev/null | head -1); \
	if [ -z "$$f" ]; then echo "no recording in runs/latest/ yet: run 'make run' first"; exit 1; fi; \
	if [ -n "$${DISPLAY:-}$${WAYLAND_DISPLAY:-}" ]; then $(BIN)/rerun "$$f"; \
	else echo "no display here; open the recording on a machine with one:"; \
	     echo "  $(CURDIR)/$(BIN)/rerun $$(readlink -f $$f)"; \
	     echo "or serve it to a browser: $(CURDIR)/$(BIN)/rerun --web-viewer $$(readlink -f $$f)"; fi

test: setup      ## the whole test suite
	$(BIN)/python -m pytest -q

test-fast: setup ## unit tests only (no multi-process, no slow)
	$(BIN)/python -m pytest -q -m "not slow and not integration"

clean:           ## remove every run directory (runs/) and the test cache
	rm -rf runs .pytest_cache
