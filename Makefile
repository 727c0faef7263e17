# sb3-soup developer commands. `make demo` and `make test` each install what they need first.
# The interpreter to install into and run: `python3` from PATH (an activated virtual environment's, if any), or
# `make test PYTHON=path/to/python`.
PYTHON ?= python3
PIP = $(PYTHON) -m pip
# The CPU build of torch: install it before anything that depends on torch, or pip pulls a multi-GB CUDA build.
TORCH_CPU ?= torch==2.13.0
PYTEST_WORKERS ?= 2
LINT_PATHS = sb3_soup/ tests/ examples/ $(wildcard benchmarks/) _sb3_soup_zoo_hook.py setup.py docs/conf.py

.PHONY: install install-tests install-docs demo test test-slow test-all bench doc lint type check-codestyle format

install:
	$(PIP) install --quiet $(TORCH_CPU)
	$(PIP) install --quiet -e .

install-tests:
	$(PIP) install --quiet $(TORCH_CPU)
	$(PIP) install --quiet -e ".[tests,zoo]"

install-docs:
	$(PIP) install --quiet $(TORCH_CPU)
	$(PIP) install --quiet -e ".[docs]"

## Train SOUP on a small default (Pendulum-v1), print evaluation returns, save the model and a learning curve.
demo: install
	$(PYTHON) -m sb3_soup.demo --out demo_output

## The default test suite (no `slow` tests), on all cores.
test: install-tests
	$(PYTHON) -m pytest -m "not slow" -n $(PYTEST_WORKERS) --durations=15

## Only the long tests (learning on Pendulum, subprocess CLIs).
test-slow: install-tests
	$(PYTHON) -m pytest -m slow -n $(PYTEST_WORKERS) --durations=15

test-all: test test-slow

## Throughput of SOUP against SB3's DDPG/TD3 on Hopper-v4 (about 20 minutes on 2 cores; see docs/benchmarks.md).
bench: install
	$(PYTHON) benchmarks/throughput.py --out throughput.json

## The documentation (docs/: Markdown pages, autodoc of the API) as HTML in docs/_build/html; every warning is an error.
doc: install-docs
	$(PYTHON) -m sphinx -W --keep-going -b html docs docs/_build/html

lint:
	$(PYTHON) -m ruff check $(LINT_PATHS)

check-codestyle:
	$(PYTHON) -m ruff format --check $(LINT_PATHS)

format:
	$(PYTHON) -m ruff format $(LINT_PATHS)
	$(PYTHON) -m ruff check --fix $(LINT_PATHS)

type:
	$(PYTHON) -m mypy sb3_soup/ _sb3_soup_zoo_hook.py
