# Sortie build: `make demo` and `make test` bootstrap everything on a fresh machine.
# Idempotent: stamps make a second run skip what is already installed.

PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed
SYS_STAMP := $(VENV)/.sysdeps
# Debian packages: Mesa's EGL/GL for headless OpenGL (llvmpipe where no GPU; libgl1 is the
# libGL.so.1 moderngl's EGL backend loads, which nothing else here pulls in for certain);
# tshark (Wireshark's DIS dissector checks our PDUs); docker-compose (CI validates
# docker-compose.yml with `docker-compose config`; there is no Docker engine here).
SYS_PACKAGES := libegl1 libegl-mesa0 libgl1 libgl1-mesa-dri libgles2 libglx-mesa0 tshark docker-compose
# The Khronos glTF validator (npm), an independent check of the glTF files we write
# (tests/test_gltf.py). Where the machine has no npm, Debian's nodejs and npm are installed
# first; where that fails too, its test skips with a note.
TOOLS := .tools
TOOLS_STAMP := $(TOOLS)/.installed
GLTF_VALIDATOR := gltf-validator@2.0.0-dev.3.10
# Two bootstraps at once (two clones on one machine) wait for each other's apt and dpkg
# locks, up to this many seconds, instead of failing (apt >= 1.9.11 reads DPkg::Lock::Timeout).
APT_GET := apt-get -o DPkg::Lock::Timeout=600

.PHONY: all bootstrap sysdeps demo test proto bench clean

all: bootstrap

bootstrap: $(STAMP) $(SYS_STAMP) $(TOOLS_STAMP)

# Debian's python3 comes without venv/ensurepip (the python3-venv package): installed first
# where it is missing, before the environment is made.
$(VENV)/bin/python:
	@if ! $(PYTHON) -c 'import ensurepip, venv' >/dev/null 2>&1; then \
	  echo "installing python3-venv (this python has no venv/ensurepip)"; \
	  SUDO=""; [ "$$(id -u)" -ne 0 ] && SUDO=sudo; \
	  $$SUDO $(APT_GET) update -qq && $$SUDO env DEBIAN_FRONTEND=noninteractive $(APT_GET) install -y -qq python3-venv python3-pip >/dev/null; \
	fi
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip

$(STAMP): pyproject.toml | $(VENV)/bin/python
	$(BIN)/pip install --quiet -e '.[dev]'
	touch $@

$(SYS_STAMP): Makefile | $(VENV)/bin/python
	@missing=""; for p in $(SYS_PACKAGES); do \
	  dpkg-query -W -f='$${Status}' $$p 2>/dev/null | grep -q 'install ok installed' || missing="$$missing $$p"; \
	done; \
	if [ -n "$$missing" ]; then \
	  echo "installing system packages:$$missing"; \
	  SUDO=""; [ "$$(id -u)" -ne 0 ] && SUDO=sudo; \
	  $$SUDO $(APT_GET) update -qq && $$SUDO env DEBIAN_FRONTEND=noninteractive $(APT_GET) install -y -qq $$missing >/dev/null; \
	fi
	touch $@

$(TOOLS_STAMP): Makefile
	@if ! command -v npm >/dev/null 2>&1 && command -v apt-get >/dev/null 2>&1; then \
	  echo "installing nodejs and npm (for the Khronos glTF validator)"; \
	  SUDO=""; [ "$$(id -u)" -ne 0 ] && SUDO=sudo; \
	  ($$SUDO $(APT_GET) update -qq && $$SUDO env DEBIAN_FRONTEND=noninteractive $(APT_GET) install -y -qq nodejs npm \
	    >/dev/null) || echo "note: nodejs and npm could not be installed"; \
	fi; \
	if command -v npm >/dev/null 2>&1; then \
	  (npm install --silent --no-audit --no-fund --prefix $(TOOLS) $(GLTF_VALIDATOR) && touch $@) \
	    || echo "note: the Khronos glTF validator could not be installed (its test skips)"; \
	else \
	  echo "note: no npm here, so the Khronos glTF validator is not installed (its test skips)"; \
	fi

proto: $(STAMP)
	$(BIN)/python -m sortie.protogen

demo: bootstrap
	$(BIN)/sortie demo

test: bootstrap
	$(BIN)/python -m pytest -q

bench: bootstrap
	$(BIN)/sortie bench terrain --json docs/bench/terrain.json

clean:
	rm -rf $(VENV) $(TOOLS) build *.egg-info .pytest_cache out
