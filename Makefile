# The README's two commands: `make run` and `make test`. Each installs what is
# missing (Debian packages, a venv, the native build) and then acts.
PYTHON ?= python3
# bash with pipefail: a filtered pip (the native build below) still fails the recipe
SHELL := /bin/bash
.SHELLFLAGS := -o pipefail -c
VENV   := .venv
BIN    := $(VENV)/bin
NATIVE := $(wildcard native/*.cpp native/*.hpp native/CMakeLists.txt)
# The editable install maps each module of the package to its file when it is made:
# a module added, moved or removed makes it anew (a stamp named by the list's hash).
MODULES := $(BIN)/.modules-$(shell find flatserve -name '*.py' -not -path '*/__pycache__/*' | LC_ALL=C sort | md5sum | cut -c1-12)
HOST   ?= 127.0.0.1
PORT   ?= 8000
DATA   ?= data

.PHONY: run test test-fast build stub system-deps bench clean constraints

# Every pip install of a dependency is pinned by constraints.txt (what CI tests is
# what the image ships); `make constraints` refreshes it (pip-tools, in .venv-tools).
PIN := -c constraints.txt

system-deps:
	bash scripts/install-system-deps.sh

# Not -q: each step says what it is doing (the native build is minutes of compiling).
$(BIN)/.deps: pyproject.toml constraints.txt scripts/install-system-deps.sh
	@echo "==> Debian packages (scripts/install-system-deps.sh)"
	bash scripts/install-system-deps.sh
	@echo "==> the venv $(VENV) and the build tools"
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --progress-bar off --upgrade pip
	$(BIN)/python -m pip install --progress-bar off $(PIN) "scikit-build-core>=0.10" "nanobind==3.1.0"
	touch $@

# The package with the extras `make run` needs (pyproject.toml: the library
# itself needs NumPy only).
# -v: CMake's and ninja's lines ([3/12] Building CXX ...) while the extension compiles.
$(BIN)/.built: $(BIN)/.deps $(NATIVE) pyproject.toml constraints.txt $(MODULES)
	@echo "==> flatserve, its C++ extension (CGAL: about 4 minutes on 2 cores) and the extras service, lightfield"
	$(BIN)/python -m pip install -v --progress-bar off $(PIN) --no-build-isolation -e ".[service,lightfield]" \
	    | grep --line-buffered -E '^\s*(\[[0-9]+/[0-9]+\]|-- (Build files|Configuring done)|Successfully|Collecting|Installing|ERROR|\*\*\*)'
	touch $@

build: $(BIN)/.built

$(BIN)/.modules-%:
	@mkdir -p $(BIN) && rm -f $(BIN)/.modules-* && touch $@

# The type stub of the extension, generated from the built module and checked
# in; tests/test_native.py fails when it differs from a fresh one (nanobind is
# pinned: another version's stub generator writes other text).
stub: build
	$(BIN)/python -m nanobind.stubgen -q -m flatserve._core -p native/stubgen_patterns.txt -o flatserve/_core.pyi

# The test extra, the PostgreSQL driver and Ray (the cluster extra), installed beside the package (no rebuild of the extension).
$(BIN)/.test-deps: $(BIN)/.built pyproject.toml constraints.txt scripts/requirements.py
	$(BIN)/python scripts/requirements.py --no-core test postgres cluster docs > $(BIN)/test-requirements.txt
	@echo "==> the test extra, the PostgreSQL driver, Ray (cluster mode) and the docs extra (MkDocs)"
	$(BIN)/python -m pip install --progress-bar off $(PIN) -r $(BIN)/test-requirements.txt
	touch $@

# Debian's chromium + chromedriver, for the viewer test only.
$(BIN)/.browser: scripts/install-system-deps.sh
	bash scripts/install-system-deps.sh --browser
	touch $@

# Debian's Docker engine + debootstrap, for the container image test.
$(BIN)/.docker: scripts/install-system-deps.sh
	bash scripts/install-system-deps.sh --docker
	touch $@

# Debian's PostgreSQL server, for the tests of the PostgreSQL backend (they run
# their own throwaway clusters: tests/harness/pgcluster.py).
$(BIN)/.postgres: scripts/install-system-deps.sh
	bash scripts/install-system-deps.sh --postgres
	touch $@

run: build
	$(BIN)/flatserve serve --demo --host $(HOST) --port $(PORT) --data-dir $(DATA)

# FLATSERVE_STRICT=1: a skipped test counts as failed (see tests/conftest.py).
test: build $(BIN)/.test-deps $(BIN)/.browser $(BIN)/.docker $(BIN)/.postgres
	FLATSERVE_STRICT=1 $(BIN)/python -m pytest -q tests

# The fast lane: the library's and the service's in-process tests, none that needs
# more than this interpreter (the lanes are pytest markers: pyproject.toml lists them,
# tests/conftest.py gives them). It needs the build and the test extras only, none of
# the Debian installs of the browser, Docker or PostgreSQL; `make test` runs every test.
FAST := not (slow or server or postgres or ray or docker or browser)
test-fast: build $(BIN)/.test-deps
	FLATSERVE_STRICT=1 $(BIN)/python -m pytest -q -m "$(FAST)" tests

# wrk: the load generator of benchmarks/bench_service.py and bench_replicas.py.
$(BIN)/.bench-tools: scripts/install-system-deps.sh
	bash scripts/install-system-deps.sh --bench
	touch $@

bench: build $(BIN)/.test-deps $(BIN)/.postgres $(BIN)/.bench-tools
	for b in benchmarks/bench_*.py; do $(BIN)/python $$b || exit 1; done

# The pins of constraints.txt, re-resolved to the newest versions pyproject.toml allows.
TOOLS := .venv-tools
constraints:
	test -x $(TOOLS)/bin/pip-compile || { $(PYTHON) -m venv $(TOOLS) && $(TOOLS)/bin/pip install pip-tools; }
	{ $(PYTHON) scripts/requirements.py client gradient service lightfield postgres cluster test docs; \
	  echo "scikit-build-core>=0.10"; echo "nanobind==3.1.0"; } > $(TOOLS)/requirements.in
	$(TOOLS)/bin/pip-compile --upgrade --quiet --strip-extras --allow-unsafe --no-header \
	    --no-emit-index-url --no-emit-find-links -o $(TOOLS)/constraints.txt $(TOOLS)/requirements.in
	{ echo "# The versions every install of flatserve's dependencies uses (pip install -c):"; \
	  echo "# make build, make test (so CI tests this set) and docker/Dockerfile (so the image"; \
	  echo "# ships it). Generated by pip-tools' pip-compile from pyproject.toml's requirements"; \
	  echo "# (every extra and the build requirements); refresh with \`make constraints\`, then"; \
	  echo "# \`make test\`, and commit the result."; cat $(TOOLS)/constraints.txt; } > constraints.txt

clean:
	rm -rf build $(VENV) $(TOOLS)
