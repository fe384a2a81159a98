# Two commands on a fresh machine: `make demo` and `make test`. Both set up .venv on first use.
PYTHON ?= python3
VENV   := .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.terrainwarp-installed
OUT    ?= out/demo

.PHONY: setup demo test lint docs bench clean
setup: $(STAMP)

$(STAMP): pyproject.toml scripts/system-deps.sh
	@bash scripts/system-deps.sh
	@test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --disable-pip-version-check -e '.[test]'
	@touch $(STAMP)

demo: $(STAMP)
	$(VENV)/bin/terrainwarp demo --out $(OUT)

lint: $(STAMP)
	$(VENV)/bin/ruff check terrainwarp kernels tests benchmarks examples docs

test: lint
	$(PY) -m pytest -q

# the API reference, warnings as errors (tests/test_docs.py builds it too, so make test fails on a broken one)
docs: $(STAMP)
	$(PY) -m sphinx -E -a -W --keep-going -q -b html docs out/docs
	@echo "wrote: out/docs/index.html"

bench: $(STAMP)
	$(PY) benchmarks/run_all.py

clean:
	rm -rf out build *.egg-info docs/api
