# blunf — make targets. `make demo` and `make test` are all a newcomer needs.
PY      ?= python3
VENV    ?= .venv
BIN     := $(VENV)/bin
PYTHON  := $(BIN)/python
# glibc malloc: keep large tensors out of fresh mmaps (measured faster on element-wise ops).
export GLIBC_TUNABLES ?= glibc.malloc.mmap_threshold=33554432:glibc.malloc.trim_threshold=4294967296
DEMO    ?= runs/demo

.PHONY: setup constraints sysdeps demo test test-slow check lint typecheck bench bench-quick bench-targets batch clean FORCE

# System libraries the wheels link against, as `library:Debian package`: open3d needs libusb,
# torch and open3d need libgomp. Programs, as `program:Debian package`: the studio's browser
# test drives Debian's chromium (a browser a Python package downloads cannot be fetched here).
# Installed with apt-get when we are root and it exists; otherwise the exact command is
# printed and setup stops.
SYSLIBS := libusb-1.0.so.0:libusb-1.0-0 libgomp.so.1:libgomp1
SYSBINS := chromium:chromium chromedriver:chromium-driver
LDCONFIG := $(shell command -v ldconfig || echo /sbin/ldconfig)

sysdeps:  ## the system libraries the Python packages need (apt-get, when root)
	@missing=""; for e in $(SYSLIBS); do \
	  $(LDCONFIG) -p 2>/dev/null | grep -q "$${e%%:*}" || missing="$$missing $${e##*:}"; done; \
	for e in $(SYSBINS); do \
	  command -v "$${e%%:*}" >/dev/null || missing="$$missing $${e##*:}"; done; \
	if [ -z "$$missing" ]; then exit 0; fi; \
	if [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null; then \
	  echo "blunf: installing system packages:$$missing"; \
	  apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq$$missing >/dev/null; \
	else \
	  echo "blunf: missing system packages:$$missing. Install them, then run make again:"; \
	  echo "  sudo apt-get install -y$$missing"; exit 1; \
	fi

$(BIN)/.installed: pyproject.toml constraints.txt | sysdeps
	test -d $(VENV) || $(PY) -m venv $(VENV)
	$(BIN)/pip install -q --upgrade pip
	# CPU torch first: a later range that 2.13.0 satisfies then pulls nothing more.
	$(BIN)/pip install -q torch==2.13.0
	# within the versions the figures were measured with (constraints.txt)
	$(BIN)/pip install -q -e '.[dev]' -c constraints.txt
	$(PYTHON) -c "import numpy, open3d, pycolmap, torch, kornia, skimage, trimesh" \
	  || (echo "blunf: a dependency failed to import; on Debian run: apt-get install -y libusb-1.0-0 libgomp1" && exit 1)
	touch $@

setup: sysdeps $(BIN)/.installed  ## idempotent: system libraries, .venv and the project

constraints: $(BIN)/.installed  ## pin constraints.txt to the installed versions (then re-measure the figures)
	{ sed -n '/^#/p' constraints.txt; $(BIN)/pip freeze | grep -v '^#\|^-e\|^torch=='; } > constraints.txt.new
	mv constraints.txt.new constraints.txt

demo: setup  ## the default room from photos alone, then edited through its NeRF (~2 min after setup)
	# 1. photos and intrinsics only, as a phone gives: SfM poses, stereo depth (no NeRF trained), geometric classes
	test -d $(DEMO)/phone || $(BIN)/blunf synth $(DEMO)/phone --views 60 --seed 0 --photos-only
	$(BIN)/blunf run $(DEMO)/phone --out $(DEMO)/phone-run --config configs/phone.yaml
	# 2. the full capture (poses, depth, labels): plan, then the example edits rendered (a NeRF
	#    of 200 steps scored on held-out pixels, the edits drawn through the fused mesh refined
	#    round the edited objects: configs/edit-fast.yaml)
	test -d $(DEMO)/capture || $(BIN)/blunf synth $(DEMO)/capture --views 60 --seed 0
	$(BIN)/blunf run $(DEMO)/capture --out $(DEMO)/run --config configs/edit-fast.yaml --edits configs/edits/demo.yaml
	@echo "from photos alone: $(DEMO)/phone-run/blueprint.png  report: $(DEMO)/phone-run/report.json"
	@echo "edited: $(DEMO)/run/edits/  blueprint: $(DEMO)/run/blueprint.png  report: $(DEMO)/run/report.json"

# Both suites run on every core (pytest-xdist), one torch thread a worker; tests that share a
# module's fixture stay on one worker (tests/conftest.py). TESTJOBS=1 runs them in one process.
TESTJOBS ?= logical
XDIST   := $(if $(filter 1,$(TESTJOBS)),,-n $(TESTJOBS) --dist loadgroup)

test: setup  ## the default suite (fast; real-data tests are marked slow)
	OMP_NUM_THREADS=1 $(BIN)/pytest -q $(XDIST)

test-slow: setup  ## real captures and long runs
	OMP_NUM_THREADS=1 $(BIN)/pytest -q -m slow $(XDIST) --durations=15

check: lint typecheck

lint: setup
	$(BIN)/ruff check pipeline stages tests
	$(BIN)/ruff format --check pipeline stages tests

typecheck: setup
	$(BIN)/mypy

# Run time against error over the stage variants (pipeline/bench/grid.py), one thread a run:
# bench.md, bench.csv and the plots in the out folder. Not part of CI.
bench: setup  ## the full grid, 3 repeats (~1 h idle, 89 min measured on a loaded machine): runs/bench/
	$(BIN)/blunf bench --out runs/bench

bench-quick: setup  ## a small grid, 1 repeat (< 10 min): runs/bench-quick/
	$(BIN)/blunf bench --quick --out runs/bench-quick

# Each speed target's figure, the reference measured in the same bench (or its budget), their
# ratio, pass or fail, and the command behind it (pipeline/bench/targets.py); `blunf bench
# --targets --quick` is the ~15-minute cut of it.
bench-targets: setup  ## every speed target against its reference, 3 repeats: runs/targets/targets.md
	$(BIN)/blunf bench --targets --out runs/targets

# make batch CAPTURES="a b c" JOBS=2: `blunf batch` on a local Dask cluster of JOBS workers (one
# thread each): runs/batch/<scene>/, <scene>.log, summary.csv, index.html, batch.json. A failed
# capture does not stop the others. RUNARGS: run options, e.g. RUNARGS="--config configs/fast.yaml".
CAPTURES ?=
JOBS    ?= 2
BATCH   ?= runs/batch

batch: setup
	@test -n "$(CAPTURES)" || (echo 'usage: make batch CAPTURES="capA capB" [JOBS=2]'; exit 2)
	$(BIN)/blunf batch $(CAPTURES) --out $(BATCH) --workers $(JOBS) $(RUNARGS)

FORCE:

clean:
	rm -rf runs
