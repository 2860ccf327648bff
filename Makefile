# Two commands on a fresh machine: `make run` and `make test`. Each creates or reuses the
# virtual environment .venv and installs what it needs. `make docs` builds the docs site.
SHELL := /bin/bash
PYTHON ?= python3
VENV ?= .venv
PY := $(VENV)/bin/python
PIP := $(PY) -m pip
NOISESTOP := $(VENV)/bin/noisestop
# The CPU build of torch; where that exact version is not available, plain torch.
TORCH_SPEC ?= torch==2.13.0
STAMP := $(VENV)/.installed-$(shell cat pyproject.toml | cksum | cut -d' ' -f1)
DATA ?= data/train
LIBRARY ?= data/default
HELDOUT ?= data/heldout
CORPUS ?= data/corpus64
OUT ?= out

.PHONY: setup run test test-fast docs test-portability bench realscenes realscene-refs dataset library heldout corpus estimate fixture model clean

$(STAMP): pyproject.toml
	@test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PIP) install -q --disable-pip-version-check "$(TORCH_SPEC)" || $(PIP) install -q torch
	$(PIP) install -q --disable-pip-version-check -e ".[all,dev]"
	@rm -f $(VENV)/.installed-* && touch $@

setup: $(STAMP)
	@bash scripts/install-llvm.sh

# The main job, showing what the product is for (examples/showcase.py, run from this checkout:
# examples/ is a demo, not installed): the held-out studio_preview rendered adaptively with the
# default criterion, then uniformly for the same wall time; out/equal_time.png puts them side by
# side with the reference shipped in examples/references/, and one line sums up blocks above
# tau, the worst block, the samples and time (docs/guide/rendering.md).
RUN_SCENE ?= studio_preview
run: setup
	$(PY) -m examples.showcase --scene $(RUN_SCENE) --out $(OUT)

test: setup
	$(PY) -m pytest -q

# The CPU-portability check (docs/guide/install.md): how far pixels and decisions move when Dr.Jit's LLVM
# backend compiles for another CPU (AVX2 Haswell code, 8 lanes, on whatever this machine
# is), then the whole suite with every in-process kernel compiled so, in a fresh kernel cache.
PORTABLE_TARGET ?= haswell,8
test-portability: setup
	$(PY) -m tests.support.passloop_golden shift $(PORTABLE_TARGET)
	DRJIT_CACHE_DIR=$$(mktemp -d) NOISESTOP_TEST_LLVM_TARGET=$(PORTABLE_TARGET) $(PY) -m pytest -q

test-fast: setup
	$(PY) -m pytest -q -m "not slow"

# The docs site (mkdocs.yml) into site/: the [docs] extra's tools into .venv (its list read
# from pyproject.toml, so that the project's own install is left as it is), the reference
# pages regenerated from the code (docs/gen_reference.py: the render spec's rows and the
# command line), then a strict build (a broken link or a docstring mkdocstrings cannot read
# fails it). Open site/index.html.
docs: $(STAMP)
	$(PY) -c "import subprocess, sys, tomllib; \
		reqs = tomllib.load(open('pyproject.toml', 'rb'))['project']['optional-dependencies']['docs']; \
		sys.exit(subprocess.call([sys.executable, '-m', 'pip', 'install', '-q', '--disable-pip-version-check', *reqs]))"
	PYTHONPATH=. $(PY) docs/gen_reference.py
	PYTHONPATH=. $(VENV)/bin/mkdocs build --strict

# Every figure and plot of BENCHMARKS.md, from scratch: builds (or finds complete) the
# default dataset first, then runs every section; the timing sections first, alone on the
# machine. The model comparison (paper's albedo quick image, then feature models with
# none) is saved in out/bench, where the trade-off chart finds every model's offset curve.
# Time: BENCHMARKS.md "make bench". The sections live in benchmarks/ (this checkout only: not
# installed, not in the image); `noisestop bench` loads them from here.
bench: dataset heldout
	$(NOISESTOP) bench features crop flip render passes native cost service stability reliability --update BENCHMARKS.md
	$(NOISESTOP) bench dataset inputs models criteria tradeoff ablation step knobs tilestop --data $(DATA) \
		--heldout $(HELDOUT) --input halves,albedo --update BENCHMARKS.md

# The public real-scene suite (benchmarks/realscenes, its sources and licences in SOURCES.md):
# the default render against mi.render at equal wall time, to its quality and under a time
# limit. realscene-refs renders the 8192-spp references once into out/bench/references
# (outside git; each kept as it finishes, so an interrupted build resumes); it runs happily
# in the background (`make realscene-refs &`). Fetches nothing: the scenes are in the repo.
realscene-refs: setup
	$(PY) -m benchmarks.bench_realscenes --refs-only
realscenes: realscene-refs
	$(NOISESTOP) bench realscenes --update BENCHMARKS.md

# The training dataset (docs/guide/training.md): PROCEDURAL seeded procedural scenes
# (renderer/scenes/procedural.py) plus the 14 built-in training scenes, each a 64x64 frame of one
# 64x64 block, a level every 32 spp up to 4096 spp and an 8192-spp reference, so that most
# blocks converge inside their stacks under the tile observer. Resumes if interrupted; on a
# complete dataset it relabels stacks of an older observer (no rendering). Time: BENCHMARKS.md.
PROCEDURAL ?= 72
TRAIN_ARGS ?= --resolution 64 --block 64 --step 32 --levels 128 --reference-spp 8192
dataset: setup
	$(NOISESTOP) dataset build --out $(DATA) --scenes procedural:$(PROCEDURAL),training $(TRAIN_ARGS)
	$(NOISESTOP) dataset check $(DATA)

# The learned stop's training corpus (docs/guide/training.md): CORPUS_SCENES seeded
# procedural scenes plus the 14 training scenes, each a 64x64 frame of one 64x64 block (16
# tiles), a level every 32 spp to 2048 and a 4096-spp reference; the tile truth written beside
# the block truth. Nothing held out goes in. About 10 s a scene here: run it in the background
# (`make corpus &`), it resumes where it stopped; --scheduler (see `noisestop dataset build
# --help`) spreads it over a Dask farm.
CORPUS_SCENES ?= procedural:366,training
CORPUS_ARGS ?= --resolution 64 --block 64 --step 32 --levels 64 --reference-spp 4096 --no-contact-sheets
corpus: setup
	$(NOISESTOP) dataset build --out $(CORPUS) --scenes $(CORPUS_SCENES) $(CORPUS_ARGS)
	$(NOISESTOP) dataset relabel $(CORPUS)
	$(NOISESTOP) dataset check $(CORPUS)

# The scene library at the paper's layout (14 scenes x 16 blocks of 64x64, 16..640 spp,
# reference 4096): the reference `make run` compares its render with. Resumes if interrupted.
LIBRARY_ARGS ?= --resolution 256 --step 16 --levels 40 --reference-spp 4096
library: setup
	$(NOISESTOP) dataset build --out $(LIBRARY) $(LIBRARY_ARGS)
	$(NOISESTOP) dataset check $(LIBRARY)

# The held-out scenes every figure is measured on (renderer/scenes/heldout.py): 8 scenes x 16
# blocks x 64 levels (32..2048 spp), reference 8192 spp, so that most blocks converge
# inside the stack. Never trained or calibrated on. Resumes if interrupted.
HELDOUT_ARGS ?= --resolution 256 --step 32 --levels 64 --reference-spp 8192
heldout: setup
	$(NOISESTOP) dataset build --out $(HELDOUT) --scenes heldout $(HELDOUT_ARGS)
	$(NOISESTOP) dataset check $(HELDOUT)

# What ships to decide stops: the bundled model (learning/bundled: DSVM_AS on every scene of
# the training dataset, input 'halves' in its measured composition, decision offset
# calibrated on out-of-fold scores for <= 5 % early stops) and flip's c (learning/flip.json:
# calibrated on the same training scenes to the same target). Held-out figures: `make bench`.
# --update-package: the maintainer's flag that rewrites the shipped files (without it, both
# commands write the user's own: the given --out, or the user data directory).
model: setup
	$(NOISESTOP) train --data $(DATA) --model dsvm_as --input halves --update-package \
		$(if $(wildcard $(HELDOUT)/*/meta.json),--heldout $(HELDOUT),--test-scenes '')
	$(NOISESTOP) calibrate --criterion flip --data $(DATA) --update-package

# The learned stop's bundle (learning/bundled_estimate): the per-tile error estimate
# trained on the corpus and its c(tau) chosen out of fold there (docs/guide/training.md).
ESTIMATE_ARGS ?= --kind gbm
estimate: setup
	$(NOISESTOP) calibrate --criterion estimate --data $(CORPUS) $(ESTIMATE_ARGS) --update-package

# The small dataset committed for tests (tests/fixtures/dataset, about 2 MB): 4 scenes x
# 16 blocks x 16 levels of 64x64 frames.
fixture: setup
	rm -rf tests/fixtures/dataset
	$(NOISESTOP) dataset build --out tests/fixtures/dataset --scenes cornell,cornell_dark,checker,sky \
		--resolution 64 --step 48 --levels 16 --reference-spp 4096 --no-contact-sheets
	$(NOISESTOP) dataset check tests/fixtures/dataset

clean:
	rm -rf $(VENV) build site *.egg-info .pytest_cache .hypothesis
