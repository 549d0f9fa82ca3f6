# kftune — two entry points: `make run` (the main job) and `make test` (the suite).
# Both create .venv on first use; `make venv` only prepares it.

PYTHON ?= python3
VENV   := .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed
EXTRAS := test,simulate,peers,dev,dask,import
# Where `make run` writes its report.
REPORT ?= report

.PHONY: venv run test lint bench clean

venv: $(STAMP)

$(STAMP): pyproject.toml
	@test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e ".[$(EXTRAS)]"
	@touch $(STAMP)

# --force: a second `make run` starts afresh (the job takes seconds) instead of refusing to
# overwrite the studies of the first; `kftune compare --resume` continues an interrupted one.
run: $(STAMP)
	$(BIN)/kftune compare --out $(REPORT) --force

test: $(STAMP)
	$(BIN)/python -m pytest -q

lint: $(STAMP)
	$(BIN)/ruff check src tests benchmarks examples
	$(BIN)/ruff format --check src tests benchmarks examples

clean:
	rm -rf $(VENV) build *.egg-info src/*.egg-info .pytest_cache .ruff_cache
