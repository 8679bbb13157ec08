# hdrmerge-cli: `make demo` and `make test` set everything up on a fresh machine
# (python3 with venv/pip is all they need).
PYTHON ?= python3
VENV ?= .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed-stamp
DEMO ?= demo

.PHONY: install demo test man bench clean

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e '.[test]'
	touch $(STAMP)

install: $(STAMP)

## Render a bracket with the built-in scene and merge it.
demo: $(STAMP)
	$(BIN)/hdrmerge-cli simulate -o $(DEMO)/bracket --overwrite
	$(BIN)/hdrmerge-cli merge $(DEMO)/bracket/frame_*.dng -o $(DEMO)/merged.exr --extra-channels clipped --overwrite

## The whole test suite.
test: $(STAMP)
	$(BIN)/python -m pytest -q

## Benchmarks: accuracy and speed against OpenCV/colour-hdri, CRF estimation, noise calibration
## (need ../shared/data); tables and plots in benchmarks/results/.
bench: $(STAMP)
	$(BIN)/python -W ignore -m benchmarks

## Regenerate the man pages from the click definitions.
man: $(STAMP)
	$(BIN)/python -m hdrmerge_cli.manpages man

clean:
	rm -rf $(VENV) $(DEMO) .pytest_cache
