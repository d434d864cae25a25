# Two commands on a fresh machine:  `make demo` (the main job) and `make test` (the test suite).
PYTHON ?= python3
VENV   ?= .venv
PY     := $(VENV)/bin/python
OUT    ?= out

.PHONY: demo test test-fast install bench drive drive-screenshot clean

$(VENV)/.installed: pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet torch==2.13.0
	$(PY) -m pip install --quiet -e '.[test,ray]'
	touch $@

install: $(VENV)/.installed

demo: install
	$(VENV)/bin/trafficweaving demo --out $(OUT)

test: install
	$(PY) -m pytest

# the fast tier while editing: every module, under a minute on 2 cores (no slow or browser tests)
test-fast: install
	$(PY) -m pytest -q -m "not slow and not browser"

bench: install
	$(PY) benchmarks/bench_generate.py
	$(PY) benchmarks/bench_train.py
	$(PY) benchmarks/bench_plan.py
	$(PY) benchmarks/bench_chunks.py
	$(PY) benchmarks/bench_drive.py

drive: install
	$(VENV)/bin/trafficweaving drive

# docs/figures/drive.png: the browser test's screenshot (needs /usr/bin/chromium)
drive-screenshot: install
	TRAFFICWEAVING_DRIVE_SCREENSHOT=docs/figures/drive.png $(PY) -m pytest -q tests/web/test_web_browser.py

clean:
	rm -rf $(VENV) $(OUT)
