# The two commands of the README: `make demo` (the main job, end to end) and `make test`.
# Both set everything up first: Debian's renderer/FFmpeg libraries, uv, and the locked Python 3.12 env in .venv/.
# The env is compiled to bytecode once (--compile-bytecode): every lerobot-train/-eval process then imports in
# about half the time, which matters where PYTHONDONTWRITEBYTECODE is set.

SHELL := /bin/bash
.DEFAULT_GOAL := help

PYTHON_VERSION ?= 3.12
UV_VERSION ?= 0.13.9
APT_PACKAGES := libegl1 libegl-mesa0 libgl1-mesa-dri libosmesa6 ffmpeg g++
UV := $(shell command -v uv 2>/dev/null || echo $(HOME)/.local/bin/uv)
VENV := .venv
RUN := MUJOCO_GL=$${MUJOCO_GL:-egl} $(VENV)/bin/python
export UV_PYTHON_DOWNLOADS := never
# pytest workers: each runs torch on one thread (tests/conftest.py), so two keep both cores busy while one
# waits on imports, rendering or a subprocess
TEST_WORKERS ?= 2
PYTEST := $(RUN) -m pytest tests -n $(TEST_WORKERS) --dist loadfile --durations=25

.PHONY: help setup system-deps demo study study-transfer test test-slow test-all lint bench clean

help:
	@echo "make demo   set up, build a tiny Meta-World mixture, train jept with lerobot-train, run the eval suite"
	@echo "make study  set up, run examples/studies/cpu_small.json (resumable; about 2 h on a 2-core CPU)"
	@echo "make study-transfer  set up, run examples/studies/cpu_transfer.json (four scene pairs, both directions; about 8 h on a 2-core CPU)"
	@echo "make test   set up, lint, run the tests (make test-slow: the slow ones; CI runs both)"
	@echo "make bench  set up, print the benchmark figures (name: value)"

system-deps:
	@missing=$$(for p in $(APT_PACKAGES); do dpkg -s $$p >/dev/null 2>&1 || echo $$p; done); \
	if [ -n "$$missing" ]; then \
		echo "Installing Debian packages: $$missing"; \
		SUDO=$$([ "$$(id -u)" = 0 ] || echo sudo); \
		$$SUDO apt-get update -qq && DEBIAN_FRONTEND=noninteractive $$SUDO apt-get install -y -qq $$missing >/dev/null; \
	fi

$(UV):
	python3 -m pip install --user --quiet "uv==$(UV_VERSION)"

$(VENV)/.synced: pyproject.toml uv.lock | $(UV)
	@$(UV) python find $(PYTHON_VERSION) >/dev/null 2>&1 || { \
		echo "Python $(PYTHON_VERSION) not found: install it (e.g. 'pyenv install $(PYTHON_VERSION)') and retry."; exit 1; }
	$(UV) sync --frozen --extra sim --group robosuite --extra dev --extra cluster --extra priors --python $(PYTHON_VERSION) --compile-bytecode
	@touch $@

setup: system-deps $(VENV)/.synced

demo: setup
	$(RUN) -m examples.demo

lint: setup
	$(VENV)/bin/ruff check .
	$(VENV)/bin/ruff format --check .

study: setup
	MUJOCO_GL=$${MUJOCO_GL:-egl} $(VENV)/bin/jept-study --config=examples/studies/cpu_small.json

study-transfer: setup
	MUJOCO_GL=$${MUJOCO_GL:-egl} $(VENV)/bin/jept-study --config=examples/studies/cpu_transfer.json

test: lint
	$(PYTEST) -m "not slow"

test-slow: setup
	$(PYTEST) -m slow

test-all: test test-slow

bench: setup
	@$(RUN) -m benchmarks.bench_plugin
	@$(RUN) -m benchmarks.bench_eval
	@$(RUN) -m benchmarks.bench_builder
	@$(RUN) -m benchmarks.bench_policy
	@$(RUN) -m benchmarks.bench_paper_scale
	@$(RUN) -m benchmarks.bench_paper_scale --figures=speedup --compile_model

clean:
	rm -rf $(VENV) outputs
