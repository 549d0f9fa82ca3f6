# kftune — two entry points: `make run` (the main job) and `make test` (the suite).
# Both create .venv on first use. `make run` installs kftune with only what the main job
# needs (numpy, scipy, numba, matplotlib, tqdm, threadpoolctl); `make test` adds the extras
# the suite, the linter, the type checker and the benchmarks use (the references, the peer
# optimisers, Dask, the import readers, the simulator). Each set has its own marker in .venv, so `make test`
# after `make run` installs only the rest, and an edit of pyproject.toml reinstalls both.
# `make venv` prepares the main job's environment only.

PYTHON ?= python3
VENV   := .venv
BIN    := $(VENV)/bin
RUN_STAMP  := $(VENV)/.installed-run
TEST_STAMP := $(VENV)/.installed-test
EXTRAS := test,simulate,peers,dev,dask,import
# Where `make run` writes its report.
REPORT ?= report

.PHONY: venv run test lint typecheck bench clean

venv: $(RUN_STAMP)

$(RUN_STAMP): pyproject.toml
	@test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e .
	@touch $@

$(TEST_STAMP): $(RUN_STAMP)
	$(BIN)/python -m pip install --quiet -e ".[$(EXTRAS)]"
	@touch $@

# --force: a second `make run` starts afresh (the job takes seconds) instead of refusing to
# overwrite the studies of the first; `kftune compare --resume` continues an interrupted one.
run: $(RUN_STAMP)
	$(BIN)/kftune compare --out $(REPORT) --force

test: $(TEST_STAMP)
	$(BIN)/python -m pytest -q

lint: $(TEST_STAMP)
	$(BIN)/ruff check src tests benchmarks examples
	$(BIN)/ruff format --check src tests benchmarks examples

# mypy over src/kftune, configured in pyproject.toml ([tool.mypy]).
typecheck: $(TEST_STAMP)
	$(BIN)/mypy

clean:
	rm -rf $(VENV) build *.egg-info src/*.egg-info .pytest_cache .ruff_cache
