# hdrmerge-cli: `make demo` and `make test` set everything up on a fresh machine
# (python3 with venv/pip is all they need).
PYTHON ?= python3
VENV ?= .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed-stamp
DEMO ?= demo

.PHONY: install warm demo test man bench clean

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e '.[test]'
	$(MAKE) --no-print-directory warm
	touch $(STAMP)

install: $(STAMP)

## Compile and cache the numba kernels (merge of a tiny RAW, JPEG (its response measured) and 16-bit TIFF bracket, the first two
## with deghosting; the weights of a resampled RAW frame, which a static bracket does not reach), so
## that a user's first merge does not pay for compilation; run again after editing a kernel.
warm:
	@tmp=$$(mktemp -d) && trap 'rm -rf "$$tmp"' EXIT && export HDRMERGE_CLI_CACHE_DIR="$$tmp/cache" && \
	$(BIN)/hdrmerge-cli simulate -o "$$tmp/raw" --size 96x64 --frames 3 -q && \
	$(BIN)/hdrmerge-cli merge "$$tmp"/raw/frame_*.dng -o "$$tmp/raw.exr" --deghost on -q && \
	$(BIN)/hdrmerge-cli simulate -o "$$tmp/jpg" --format jpg --size 96x64 --frames 3 -q && \
	$(BIN)/hdrmerge-cli merge "$$tmp"/jpg/frame_*.jpg -o "$$tmp/jpg.exr" --deghost on -q && \
	$(BIN)/hdrmerge-cli simulate -o "$$tmp/tif" --format tif --out-bits 16 --size 96x64 --frames 3 -q && \
	$(BIN)/hdrmerge-cli merge "$$tmp"/tif/frame_*.tif -o "$$tmp/tif.exr" --crf srgb -q && \
	$(BIN)/python -c "import numpy as np; from hdrmerge_cli.core.resample import resampled_weight_mosaic as f; \
	z = np.zeros((4, 4), np.uint16); z.flags.writeable = False; w = np.ones((4, 4), np.float32); \
	f(w, z, np.zeros((2, 2), np.intp), w.ravel(), w.ravel(), 16, w, np.eye(2, 3), out=w)" && \
	echo "numba kernels compiled and cached"

## Render a bracket with the built-in scene and merge it.
demo: $(STAMP)
	$(BIN)/hdrmerge-cli simulate -o $(DEMO)/bracket --overwrite
	$(BIN)/hdrmerge-cli merge $(DEMO)/bracket/frame_*.dng -o $(DEMO)/merged.exr --extra-channels clipped --overwrite

## The whole test suite.
test: $(STAMP)
	$(BIN)/python -m pytest -q

## Benchmarks: accuracy and speed against OpenCV/colour-hdri, CRF estimation, noise calibration
## (need ../shared/data); tables and plots in benchmarks/results/, then docs/benchmarks.md and
## the README's headline table generated from them.
bench: $(STAMP)
	$(BIN)/python -W ignore -m benchmarks
	$(BIN)/python -m benchmarks.report

## Regenerate the man pages from the click definitions.
man: $(STAMP)
	$(BIN)/python -m hdrmerge_cli.manpages man
	$(BIN)/python -m hdrmerge_cli.manpages --usage docs/usage.md

clean:
	rm -rf $(VENV) $(DEMO) .pytest_cache
