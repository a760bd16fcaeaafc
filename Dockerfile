# Sortie service image: every `sortie` command (terrain serve, server, bot, replay, dis,
# tacview, health, ...), run as ENTRYPOINT ["sortie"] by a non-root user.
#
#   docker build -t sortie:latest .
#   docker run --rm --init sortie:latest terrain info --dem /opt/sortie/data/dem/N47E009.hgt
#
# Two stages: the builder installs the project and its dependencies into a virtual
# environment (/opt/venv) from this build context and PyPI; the runtime stage is
# python:3.11-slim-bookworm with that venv, Debian's Mesa EGL/GL for headless OpenGL
# (the same packages as the Makefile's SYS_PACKAGES, without the test tools) and the
# embedded data/ (DEMs with their licences, the example scenario). Larger DEM sets are
# mounted read-only at run time (docker-compose.yml mounts one at /dem).
# Not built in this repository's CI (there is no Docker engine there): see docs/DEPLOYMENT.md.

ARG PYTHON_IMAGE=python:3.11-slim-bookworm

# --- builder ---------------------------------------------------------------------------------------
FROM ${PYTHON_IMAGE} AS builder

# A C toolchain for any dependency pip has to build from source (wheels exist for
# amd64 and arm64 today, so normally none is).
RUN apt-get update \
    && apt-get install -y --no-install-recommends build-essential \
    && rm -rf /var/lib/apt/lists/*

ENV PIP_NO_CACHE_DIR=1 \
    PIP_DISABLE_PIP_VERSION_CHECK=1 \
    PATH=/opt/venv/bin:$PATH
RUN python -m venv /opt/venv \
    && pip install --upgrade pip setuptools wheel

# The dependencies first, from pyproject.toml alone, so this slow layer is reused
# while only the sources change.
WORKDIR /src
COPY pyproject.toml ./
RUN python -c "import tomllib; print('\n'.join(tomllib.load(open('pyproject.toml', 'rb'))['project']['dependencies']))" \
        > /tmp/requirements.txt \
    && pip install -r /tmp/requirements.txt

# Then the project itself (a regular, non-editable install into the venv).
COPY sortie ./sortie
COPY terrain ./terrain
COPY server ./server
COPY client ./client
COPY fdm ./fdm
COPY bench ./bench
RUN pip install --no-deps .

# --- runtime ---------------------------------------------------------------------------------------
FROM ${PYTHON_IMAGE} AS runtime

# Mesa's EGL and GL drivers: headless OpenGL (llvmpipe where there is no GPU).
RUN apt-get update \
    && apt-get install -y --no-install-recommends \
        libegl1 libegl-mesa0 libgl1 libgl1-mesa-dri libgles2 libglx-mesa0 \
    && rm -rf /var/lib/apt/lists/*

RUN groupadd --system sortie \
    && useradd --system --gid sortie --create-home --home-dir /home/sortie --shell /usr/sbin/nologin sortie \
    && mkdir -p /recordings /frames /opt/sortie \
    && chown sortie:sortie /recordings /frames

COPY --from=builder /opt/venv /opt/venv
COPY data/ /opt/sortie/data/
# Every command module imports in this image (the parser loads them all).
RUN /opt/venv/bin/sortie --version

ENV PATH=/opt/venv/bin:$PATH \
    PYTHONUNBUFFERED=1 \
    PYTHONDONTWRITEBYTECODE=1 \
    NUMBA_CACHE_DIR=/home/sortie/.cache/numba \
    SORTIE_SERVER_RECORD_DIR=/recordings \
    SORTIE_HEALTHCHECK_ADDRESS=127.0.0.1:50051

USER sortie
WORKDIR /home/sortie
# Recordings and rendered frames outlive the container (named volumes in docker-compose.yml). Declared after
# the chown above, so a new volume starts owned by the sortie user.
VOLUME ["/recordings", "/frames"]
# Conventional ports: simulation server, terrain service, replay, Tacview, DIS (UDP),
# Prometheus metrics of the server and of the terrain service.
EXPOSE 50051 50061 50071 42674 3000/udp 9100 9101

# The health of whatever service this container runs: set SORTIE_HEALTHCHECK_ADDRESS to its
# address (docker-compose.yml gives each service its own check instead).
HEALTHCHECK --interval=10s --timeout=10s --start-period=90s --retries=3 \
    CMD sortie health "$SORTIE_HEALTHCHECK_ADDRESS"

ENTRYPOINT ["sortie"]
CMD ["--help"]
