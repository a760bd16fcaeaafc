# Sortie build: `make demo` and `make test` bootstrap everything on a fresh machine.
# Idempotent: stamps make a second run skip what is already installed.

PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed
SYS_STAMP := $(VENV)/.sysdeps
# Debian packages: Mesa's EGL/GL for headless OpenGL (llvmpipe where no GPU);
# tshark (Wireshark's DIS dissector checks our PDUs); docker-compose (CI validates
# docker-compose.yml with `docker-compose config`; there is no Docker engine here).
SYS_PACKAGES := libegl1 libegl-mesa0 libgl1-mesa-dri libgles2 libglx-mesa0 tshark docker-compose

.PHONY: all bootstrap sysdeps demo test proto bench clean

all: bootstrap

bootstrap: $(STAMP) $(SYS_STAMP)

$(VENV)/bin/python:
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
	  $$SUDO apt-get update -qq && DEBIAN_FRONTEND=noninteractive $$SUDO apt-get install -y -qq $$missing >/dev/null; \
	fi
	touch $@

proto: $(STAMP)
	$(BIN)/python -m sortie.protogen

demo: bootstrap
	$(BIN)/sortie demo

test: bootstrap
	$(BIN)/python -m pytest -q

bench: bootstrap
	$(BIN)/sortie bench terrain --json docs/bench/terrain.json

clean:
	rm -rf $(VENV) build *.egg-info .pytest_cache out
