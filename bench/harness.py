"""What every benchmark suite shares: its data files, timing, the report, its table and JSON."""

from __future__ import annotations

import json
import os
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]  # the checkout; site-packages in an installed copy
DATA_DIR_ENV = "SORTIE_DATA_DIR"  # a folder laid out as data/ (dem/, scenarios/, ...), searched first
IMAGE_DATA_DIR = Path("/opt/sortie/data")  # where the Dockerfile copies data/


def data_dirs() -> list[Path]:
    """The folders the benchmarks' data files are looked for in, in order: $SORTIE_DATA_DIR,
    ../shared/data beside the checkout (the larger shared set), the checkout's data/, and the
    Docker image's /opt/sortie/data (an installed copy has no checkout around it)."""
    env = os.environ.get(DATA_DIR_ENV)
    return ([Path(env)] if env else []) + [REPO.parent / "shared" / "data", REPO / "data", IMAGE_DATA_DIR]


def data_file(folder: str, name: str) -> Path:
    """``folder/name`` (e.g. "dem", "N47E009.hgt") from the first of :func:`data_dirs` holding
    it; a NotFound naming the file and every folder searched when none does."""
    return data_files(folder, [name])[0]


def data_files(folder: str, names) -> list[Path]:
    """Those of ``names`` found in ``folder`` of any of :func:`data_dirs` (each from the first
    holding it), in the order of ``names``; a NotFound naming the folders searched when none is."""
    from sortie.errors import NotFound

    dirs = [d / folder for d in data_dirs()]
    found = [next((d / n for d in dirs if (d / n).is_file()), None) for n in names]
    found = [p for p in found if p is not None]
    if not found:
        raise NotFound(f"benchmark data {', '.join(names)}: in none of {', '.join(map(str, dirs))} "
                       f"(set {DATA_DIR_ENV} to a folder holding {folder}/)")
    return found


@dataclass
class Report:
    """One suite's run: metrics (name -> number) and the parameters that shaped it."""

    suite: str
    quick: bool
    metrics: dict[str, float] = field(default_factory=dict)
    params: dict = field(default_factory=dict)
    # Free-form series for plots (e.g. speed against error); not part of the contract keys.
    series: dict = field(default_factory=dict)

    def to_json(self) -> dict:
        return {"suite": self.suite, "quick": self.quick, "metrics": self.metrics,
                "params": self.params, "series": self.series}

    def write(self, path: str | Path) -> None:
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(json.dumps(self.to_json(), indent=2, sort_keys=True) + "\n")

    def print_table(self) -> None:
        from rich.console import Console
        from rich.table import Table

        table = Table(title=f"sortie bench {self.suite}{' (quick)' if self.quick else ''}")
        table.add_column("metric")
        table.add_column("value", justify="right")
        for name, value in self.metrics.items():
            table.add_row(name, f"{value:.6g}" if isinstance(value, float) else str(value))
        Console().print(table)


def best_time(fn, repeat: int, number: int = 1) -> float:
    """Best wall time (s) of ``number`` calls, over ``repeat`` rounds: the least
    disturbed run is the best estimate of the code's own cost on a shared machine."""
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        for _ in range(number):
            fn()
        times.append((time.perf_counter() - t0) / number)
    return min(times)


def percentile(samples, q: float) -> float:
    """q-th percentile (0..100) of samples by linear interpolation between closest ranks:
    numpy.percentile's default ("linear", Hyndman & Fan 1996 definition 7), which
    statistics.quantiles(method="inclusive") also is."""
    from sortie.errors import InvalidArgument

    a = np.asarray(samples, dtype=np.float64).reshape(-1)
    if a.size == 0:
        raise InvalidArgument("samples", "is empty: no percentile of nothing", value=[])
    if not 0.0 <= q <= 100.0:
        raise InvalidArgument("q", "must be a percentile in [0, 100]", value=q)
    return float(np.percentile(a, q))
