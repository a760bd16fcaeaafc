"""Plots of speed against error from a suite's report series (PNG, matplotlib Agg)."""

from __future__ import annotations

from pathlib import Path


def _pyplot():
    """matplotlib's pyplot on the Agg backend (no display needed)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _save(fig, path: Path, written: list[Path]) -> None:
    """Lay out, write as PNG, close, and record the file."""
    import matplotlib.pyplot as plt

    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    written.append(path)


def plot_terrain(report: dict, out_dir: Path) -> list[Path]:
    """Write the terrain suite's speed-vs-error plots; returns the files written."""
    plt = _pyplot()
    out_dir.mkdir(parents=True, exist_ok=True)
    written = []
    series = report.get("series", {})
    if "heights" in series:
        rows = series["heights"]
        # Differences below this are rounding: plotted on the floor, labelled so.
        floor = 1e-12
        markers = "ovD^sPX*"
        fig, ax = plt.subplots(figsize=(7, 4.5))
        ax.set_xscale("log")
        ax.set_yscale("log")
        for method, speed_key, err_key, colour in (("ours", "ours_msps", "max_abs_diff_m", "tab:blue"),
                                                   ("plain numpy", "numpy_msps", "numpy_max_abs_diff_m", "tab:orange"),
                                                   ("scipy (reference)", "scipy_msps", None, "tab:green")):
            for k, row in enumerate(rows):
                err = row.get(err_key, 0.0) if err_key else 0.0
                ax.scatter(row[speed_key], max(err, floor), color=colour, marker=markers[k % len(markers)],
                           label=method if k == 0 else None)
        for k, row in enumerate(rows):  # marker legend: which DEM
            ax.scatter([], [], color="grey", marker=markers[k % len(markers)], label=row["dem"][:24])
        ax.axhline(1e-6, color="grey", lw=0.8, ls="--")
        ax.annotate("goal: 1e-6 m", (0.01, 1.3e-6), xycoords=("axes fraction", "data"), fontsize=7, color="grey")
        ax.set_xlabel("million bilinear samples / s (one core, uniform random points)")
        ax.set_ylabel(f"max |h - scipy| (m), floor {floor:g}")
        ax.set_title("Heights: speed against error")
        ax.legend(fontsize=7, loc="center left", bbox_to_anchor=(1.0, 0.5))
        _save(fig, out_dir / "terrain_heights_speed_vs_error.png", written)
    if "los_speed_vs_error" in series:
        curve = series["los_speed_vs_error"]
        n_rays = max(row.get("rays", 1) for row in curve)
        floor = 0.5 / n_rays  # "none wrong of n_rays"
        fig, ax = plt.subplots(figsize=(6.5, 4.5))
        ax.set_xscale("log")
        ax.set_yscale("log")
        for row in curve:
            y = max(row["disagreement_rate"], floor)
            ours = row["method"].startswith("exact")
            ax.scatter(row["rays_per_s"], y, color="tab:blue" if ours else "tab:orange", marker="o" if ours else "s")
            ax.annotate(row["method"], (row["rays_per_s"], y), fontsize=7, xytext=(4, 4), textcoords="offset points")
        ax.axhline(floor, color="grey", lw=0.8, ls="--")
        ax.annotate(f"floor: 0 of {n_rays} rays wrong", (0.01, floor * 1.08), xycoords=("axes fraction", "data"),
                    fontsize=7, color="grey", va="bottom")
        ax.set_ylim(floor * 0.5, 1.0)
        ax.set_xlabel("10 km rays / s (one core)")
        ax.set_ylabel("fraction of rays whose answer differs from the exact one")
        ax.set_title("Line of sight: speed against error")
        _save(fig, out_dir / "terrain_los_speed_vs_error.png", written)
    return written


def plot_fdm(report: dict, out_dir: Path) -> list[Path]:
    """Write the fdm suite's speed-vs-error plots (dt sweeps); returns the files written."""
    plt = _pyplot()
    out_dir.mkdir(parents=True, exist_ok=True)
    written = []
    series = report.get("series", {})
    panels = []
    if "dt_convergence" in series:
        rows = series["dt_convergence"]
        panels.append(("c172x (JSBSim): 60 s of manoeuvring vs dt = 1/1000 s",
                       [r["cost_s_per_sim_s"] * 1e3 for r in rows], [r["position_error_m"] for r in rows],
                       [f"1/{r['rate_hz']:g} s" for r in rows], "ms of wall time per simulated second",
                       "position error (m)"))
    if "ground_dt_sweep" in series:
        rows = series["ground_dt_sweep"]
        panels.append(("ground vehicles: median error vs dt = 0.01 s",
                       [r["wall_s_per_sim_s_per_1000"] * 1e3 for r in rows],
                       [max(r["median_pos_err_m"], 1e-6) for r in rows],
                       [f"{r['dt_s']:g} s" for r in rows], "ms of wall time per simulated second per 1000 vehicles",
                       "median position error (m)"))
    if not panels:
        return written
    fig, axes = plt.subplots(1, len(panels), figsize=(6.0 * len(panels), 4.5), squeeze=False)
    for ax, (title, x, y, labels, xlabel, ylabel) in zip(axes[0], panels):
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.plot(x, y, "o-", color="tab:blue")
        for xi, yi, label in zip(x, y, labels):
            ax.annotate(f"dt {label}", (xi, yi), fontsize=7, xytext=(4, 4), textcoords="offset points")
        ax.set_title(title, fontsize=9)
        ax.set_xlabel(xlabel, fontsize=8)
        ax.set_ylabel(ylabel, fontsize=8)
    fig.suptitle("Step size: speed against error")
    _save(fig, out_dir / "fdm_dt_speed_vs_error.png", written)
    return written


def plot_server(report: dict, out_dir: Path) -> list[Path]:
    from bench.dr import plot_dr

    return plot_dr(report, out_dir)


PLOTTERS = {"terrain": plot_terrain, "fdm": plot_fdm, "server": plot_server}
