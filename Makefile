# ppe_ros developer entry points. `make demo` and `make test` are the two commands in README.
SHELL := /bin/bash
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed

.PHONY: venv warmup demo test lint bench peers clean

venv: $(STAMP)

$(STAMP): requirements.txt setup.py setup.cfg package.xml
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade "pip>=24"
	$(PY) -m pip install --quiet -r requirements.txt
	$(PY) -m pip install --quiet --no-deps --no-build-isolation --config-settings editable_mode=compat -e .
	# compile the numba kernels into their cache once (minutes with a cold cache; docs/node.md, first start)
	$(VENV)/bin/ppe warmup
	touch $(STAMP)

# fill the numba cache again (e.g. after changing a kernel, or for another NUMBA_CACHE_DIR)
warmup: venv
	$(VENV)/bin/ppe warmup

demo: venv
	$(VENV)/bin/ppe demo --out demo-output

test: venv
	$(VENV)/bin/ruff check ppe_ros test benchmarks
	$(VENV)/bin/ruff format --check ppe_ros test benchmarks launch
	$(PY) -m pytest

# optional peers of `ppe eval` (pinned in requirements.txt on the `# peers:` line)
peers: venv
	$(PY) -m pip install --quiet $$(sed -n 's/^# peers: //p' requirements.txt)

bench: venv
	$(PY) benchmarks/bench_extraction.py
	$(PY) benchmarks/bench_node_overhead.py
	$(PY) benchmarks/bench_bag.py

clean:
	rm -rf $(VENV) build install log demo-output .pytest_cache
