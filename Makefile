# deckland: two commands do all set-up (README): `make run` and `make test`.
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.deckland-installed
PKGS := $(sort $(wildcard src/*/setup.py))
SCENARIO ?= paper

.PHONY: setup accel run test lint golden bench clean

$(PY):
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip

# Re-installs only when requirements.txt or a package's setup.py/package.xml changed.
$(STAMP): $(PY) requirements.txt $(PKGS) $(wildcard src/*/package.xml)
	$(PY) -m pip install --quiet -r requirements.txt
	$(PY) -m pip install --quiet --no-deps $(foreach p,$(PKGS),-e $(dir $(p)))
	touch $(STAMP)

setup: $(STAMP)

# The compiled cores for batch runs (deckland.accel, mypyc): rebuilt only when a compiled
# source changed. Campaigns run ~3x faster with them; they fall back to the sources without.
accel: setup
	@$(VENV)/bin/deckland accel status >/dev/null 2>&1 || $(VENV)/bin/deckland accel build

run: setup
	$(VENV)/bin/deckland up --scenario $(SCENARIO) --record runs/latest

test: setup accel
	DECKLAND_REQUIRE_ACCEL=1 $(PY) -m pytest test

lint: setup
	$(VENV)/bin/ruff check .

# Deliberate only (never run by tests): fly the reference landing and rewrite the golden bag.
golden: setup
	$(PY) -m deckland.golden record test/fixtures/golden_paper

clean:
	rm -rf $(VENV) runs build install log .pytest_cache
