# crosspath: every target sets itself up on a fresh clone.
VENV    ?= .venv
PYTHON  ?= python3
BIN      = $(VENV)/bin
STAMP    = $(VENV)/.installed-stamp
OUT     ?= results

.PHONY: install sysdeps lint test test-fast bench demo clean

$(STAMP): pyproject.toml setup.py protocol/_speedups.c services/rsu/_scan.c services/model/_geometry.c
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install -q --upgrade pip
	$(BIN)/pip install -q -e '.[dev]'
	touch $(STAMP)

install: $(STAMP)

# Debian packages the network lab needs, and a C compiler for the codec's C speed-ups
# (root only; no-op when present). `make test` runs it before the install.
sysdeps:
	@bash deploy/lab/install-sysdeps.sh

lint: install
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .
	$(BIN)/mypy
	$(BIN)/lint-imports

# `make test` is what CI runs (.ci/run sets CI): everything, the wheel installed in a fresh
# venv included (tests/test_packaging.py). Tests marked `slow` run on CI, or with SLOW=1.
# Two passes at once (tests/passes.sh): the `serial` tests (real time, daemons, the network
# lab; tests/conftest.py marks them) one at a time at normal priority, and beside them the
# pure tests (virtual clock, no sockets) on every core (pytest-xdist) at idle priority
# (SCHED_IDLE), so that no timing-sensitive test shares the CPU with another test.
NOT_SLOW = $(if $(CI)$(SLOW),,and not slow)

test: sysdeps install lint
	@bash tests/passes.sh $(BIN) "$(NOT_SLOW)"

test-fast: install
	$(BIN)/pytest -q -n auto -m "not serial and not slow"

bench: install
	@mkdir -p $(OUT)/bench
	$(BIN)/crosspath bench codec --json $(OUT)/bench/codec.json
	$(BIN)/crosspath bench rsu --json $(OUT)/bench/rsu.json
	$(BIN)/crosspath bench sim --json $(OUT)/bench/sim.json
	$(BIN)/crosspath bench latency --json $(OUT)/bench/latency.json
	$(BIN)/crosspath bench security --json $(OUT)/bench/security.json --flood-duration 60

demo: install
	$(BIN)/crosspath demo

clean:
	rm -rf $(VENV) .mypy_cache .ruff_cache .pytest_cache .hypothesis build dist *.egg-info
