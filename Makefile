# Two commands on a fresh machine: `make demo` and `make test`. Both set up .venv on first use.
PYTHON ?= python3
VENV   := .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.terrainwarp-installed
OUT    ?= out/demo

.PHONY: setup demo test lint docs bench clean
setup: $(STAMP)

# setup: system packages (only when missing), the venv, terrainwarp and its dependencies, then every kernel
# module compiled into Warp's kernel cache (one line per module; a first frame then compiles nothing)
$(STAMP): pyproject.toml scripts/system-deps.sh
	@bash scripts/system-deps.sh
	@test -x $(PY) || { echo "setup: creating $(VENV)"; $(PYTHON) -m venv $(VENV); }
	@echo "setup: installing terrainwarp and its dependencies into $(VENV) (pip; minutes on a fresh machine)"
	$(PY) -m pip install --disable-pip-version-check -e '.[test]'
	@$(VENV)/bin/terrainwarp warmup
	@touch $(STAMP)

demo: $(STAMP)
	$(VENV)/bin/terrainwarp demo --out $(OUT)

lint: $(STAMP)
	$(VENV)/bin/ruff check terrainwarp kernels tests benchmarks examples docs

test: lint
	@$(VENV)/bin/terrainwarp warmup
	$(PY) -m pytest -q

# the API reference, warnings as errors (tests/test_docs.py builds it too, so make test fails on a broken one)
docs: $(STAMP)
	$(PY) -m sphinx -E -a -W --keep-going -q -b html docs out/docs
	@echo "wrote: out/docs/index.html"

bench: $(STAMP)
	$(PY) benchmarks/run_all.py

clean:
	rm -rf out build *.egg-info docs/api
