# plantscan: `make demo` and `make test` do all the set-up on a fresh Debian/Ubuntu machine.
PY ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed-stamp

.PHONY: setup sysdeps demo test test-fast bench lint clean

# A new plugin package needs a new editable install (its finder maps packages at install time).
$(STAMP): pyproject.toml $(wildcard plugins/*/__init__.py)
	@bash scripts/install-system-deps.sh
	@test -x $(BIN)/python || $(PY) -m venv $(VENV) || { \
	  echo "make: cannot create $(VENV): install python3-venv (apt-get install python3-venv)"; exit 1; }
	$(BIN)/python -m pip install -q --upgrade pip
	$(BIN)/python -m pip install -q -e '.[dev,all]'
	@# numba kernels compiled into their cache now, not during the first scan or run (~1 min)
	$(BIN)/plantscan warm-up
	@touch $(STAMP)

setup: $(STAMP)

sysdeps:
	@bash scripts/install-system-deps.sh

demo: setup
	$(BIN)/plantscan demo --out demo-out

# pytest exits 5 when it collected no test: reported, and a failure.
test: setup
	@$(BIN)/python -m pytest; rc=$$?; \
	  if [ $$rc -eq 5 ]; then echo "make test: pytest collected no tests"; fi; exit $$rc

test-fast: setup
	$(BIN)/python -m pytest -m "not slow"

bench: setup
	$(BIN)/python benchmarks/run_all.py

lint: setup
	$(BIN)/ruff check plantscan_core plugins tests benchmarks

clean:
	rm -rf $(VENV) demo-out *.egg-info .pytest_cache
