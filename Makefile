# The two set-up commands: `make demo` and `make test`. Each creates .venv and installs what it needs.
PY ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed
DEMO := out/demo

.PHONY: demo test test-fast bench clean

$(STAMP): pyproject.toml
	$(PY) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e '.[test]'
	$(BIN)/python -m tracker.compile  # numba's kernels for this machine, once (minutes), not at the first tracker track
	touch $(STAMP)

# The whole workflow on data the project generates itself: simulated mocap (C3D) → per-task synergy
# bundles → synthetic depth recording → tracking in full / reduced / hierarchical space → evaluation.
demo: $(STAMP)
	@echo "== demo outputs go to $(DEMO) (recreated on every run)"; rm -rf $(DEMO); mkdir -p $(DEMO)
	$(BIN)/python -m handmodel.demo --out $(DEMO)/hand --frames 1000
	$(BIN)/synergy simulate -o $(DEMO)/mocap --trials 2 --duration 3
	$(BIN)/synergy angles $(DEMO)/mocap/power_grasp_01.c3d --markers hand16 -o $(DEMO)/angles
	$(BIN)/synergy fit $(DEMO)/mocap/*.c3d --markers hand16 --name demo --per-task -o $(DEMO)/synergies
	$(BIN)/synergy compare demo-grasp demo-general -r $(DEMO)/synergies
	$(BIN)/synergy plot demo-grasp -r $(DEMO)/synergies -o $(DEMO)/figs
	$(BIN)/tracker synth --motion grasp-back --noise none --frames 60 -o $(DEMO)/recording
	$(BIN)/tracker show $(DEMO)/recording -o $(DEMO)/figs/recording.png
	for mode in full reduced hierarchical; do \
	  $(BIN)/tracker track $(DEMO)/recording --synergies demo-grasp -r $(DEMO)/synergies --mode $$mode -o $(DEMO)/track-$$mode.csv \
	    --overlay $(DEMO)/overlay-$$mode --overlay-every 20 || exit 1; \
	  $(BIN)/tracker eval $(DEMO)/recording $(DEMO)/track-$$mode.csv \
	    --plot $(DEMO)/figs/error-$$mode.png || exit 1; \
	done
	@echo "== done: see $(DEMO) (figs/, overlay-*/, track-*.csv, synergies/)"

# two workers, a test file each at a time (module fixtures such as the real frames' fits are made once);
# a crashed worker is not replaced: xdist's loadfile scheduler can hang on its replacement, and a run that
# fails at once beats one that hangs until CI's time runs out. One BLAS thread per worker: two workers
# already fill two cores, and OpenBLAS threads that wait on each other made small batched solves up to 30× slower
XDIST = -n 2 --dist loadfile --max-worker-restart 0
TEST_ENV = OPENBLAS_NUM_THREADS=1 MKL_NUM_THREADS=1
test: $(STAMP)
	$(TEST_ENV) $(BIN)/python -m pytest -q $(XDIST) --durations=20 --doctest-modules src tests

test-fast: $(STAMP)
	$(TEST_ENV) $(BIN)/python -m pytest -q $(XDIST) -m "not slow" --doctest-modules src tests

bench: $(STAMP)
	for b in benchmarks/bench_*.py; do echo "== $$b"; $(BIN)/python $$b || exit 1; done

clean:
	rm -rf $(VENV) out
