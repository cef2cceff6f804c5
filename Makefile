# Two commands do all set-up on a fresh machine:
#   make demo   creates .venv, installs elevmap into it, compiles its kernels once, runs the demo (writes demo.rrd
#               and demo.png)
#   make test   same set-up, then the whole test suite
PYTHON ?= python3
VENV   := .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed
# numba compiles each kernel once into its cache (NUMBA_CACHE_DIR when set, as .ci/run does; else __pycache__
# folders beside the sources) and every later command loads it. `elevmap warmup` fills the cache right after
# installing; it runs again when a source file changes (numba recompiles the kernels of a changed file, and a
# kernel may compile a function written in another file) or for another NUMBA_CACHE_DIR (one stamp per cache).
KERNEL_SOURCES := $(shell find noise_model elevmap -name '*.py' 2>/dev/null)
WARM   := $(VENV)/.warm$(subst /,_,$(NUMBA_CACHE_DIR))

.PHONY: demo test bench install warmup system-deps clean

demo: $(WARM)
	$(BIN)/elevmap demo

test: $(WARM)
	$(BIN)/python -m pytest -q

bench: $(WARM)
	$(BIN)/elevmap bench

install: $(WARM)

warmup: $(WARM)

$(WARM): $(STAMP) $(KERNEL_SOURCES)
	@echo "compiling the numba kernels once (a minute or two; later commands start at once)"
	$(BIN)/elevmap warmup
	@touch $@

# pyrealsense2 links libusb-1.0. Install it with apt when we are root; otherwise say what is missing.
# Only the RealSense sources need it: everything else works without.
system-deps:
	@if ldconfig -p 2>/dev/null | grep -q 'libusb-1.0.so.0'; then :; \
	elif [ "$$(id -u)" = "0" ] && command -v apt-get >/dev/null 2>&1; then \
	  echo "installing libusb-1.0-0 (needed by pyrealsense2)"; \
	  (apt-get install -y -q libusb-1.0-0 >/dev/null 2>&1 || \
	   (apt-get update -q >/dev/null 2>&1 && apt-get install -y -q libusb-1.0-0 >/dev/null 2>&1)) || \
	  echo "warning: could not install libusb-1.0-0; RealSense sources will be unavailable"; \
	else \
	  echo "note: libusb-1.0 is missing; install it (Debian/Ubuntu: sudo apt-get install libusb-1.0-0)"; \
	  echo "      to read RealSense cameras and .bag/.db3 files. Everything else works without it."; \
	fi

$(VENV)/bin/python:
	$(PYTHON) -m venv $(VENV)

$(STAMP): pyproject.toml | $(VENV)/bin/python system-deps
	$(BIN)/python -m pip install -q --upgrade pip
	$(BIN)/python -m pip install -q -e ".[test,foxglove]"
	touch $(STAMP)

clean:
	rm -rf $(VENV) build *.egg-info
