# The README's two commands: `make run` and `make test`. Each installs what is
# missing (Debian packages, a venv, the native build) and then acts.
PYTHON ?= python3
VENV   := .venv
BIN    := $(VENV)/bin
NATIVE := $(wildcard native/*.cpp native/*.hpp native/CMakeLists.txt)
HOST   ?= 127.0.0.1
PORT   ?= 8000
DATA   ?= data

.PHONY: run test build stub system-deps bench clean

system-deps:
	bash scripts/install-system-deps.sh

$(BIN)/.deps: pyproject.toml scripts/install-system-deps.sh
	bash scripts/install-system-deps.sh
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip
	$(BIN)/python -m pip install -q "scikit-build-core>=0.10" "nanobind>=2.0"
	touch $@

$(BIN)/.built: $(BIN)/.deps $(NATIVE) pyproject.toml
	$(BIN)/python -m pip install -q --no-build-isolation -e ".[test]"
	touch $@

build: $(BIN)/.built

# The type stub of the extension, generated from the built module and checked
# in; tests/test_native.py fails when it differs from a fresh one.
stub: build
	$(BIN)/python -m nanobind.stubgen -q -m flatserve._core -p native/stubgen_patterns.txt -o flatserve/_core.pyi

# Debian's chromium + chromedriver, for the viewer test only.
$(BIN)/.browser: scripts/install-system-deps.sh
	bash scripts/install-system-deps.sh --browser
	touch $@

run: build
	$(BIN)/flatserve serve --demo --host $(HOST) --port $(PORT) --data-dir $(DATA)

# FLATSERVE_STRICT=1: a skipped test counts as failed (see tests/conftest.py).
test: build $(BIN)/.browser
	FLATSERVE_STRICT=1 $(BIN)/python -m pytest -q tests

bench: build
	for b in benchmarks/bench_*.py; do $(BIN)/python $$b || exit 1; done

clean:
	rm -rf build $(VENV)
