"""Plots of speed against error from a suite's report series (PNG, matplotlib Agg)."""

from __future__ import annotations

from pathlib import Path


def plot_terrain(report: dict, out_dir: Path) -> list[Path]:
    """Write the terrain suite's speed-vs-error plots; returns the files written."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out_dir.mkdir(parents=True, exist_ok=True)
    written = []
    series = report.get("series", {})
    if "heights" in series:
        fig, ax = plt.subplots(figsize=(6, 4))
        for row in series["heights"]:
            for key, marker in (("ours_msps", "o"), ("numpy_msps", "s"), ("scipy_msps", "^")):
                err = row["max_abs_diff_m"] if key == "ours_msps" else 0.0
                ax.scatter(row[key], max(err, 1e-12), marker=marker,
                           label=f"{key.split('_')[0]}" if row is series["heights"][0] else None)
                ax.annotate(row["dem"][:12], (row[key], max(err, 1e-12)), fontsize=6)
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel("million bilinear samples / s (one core)")
        ax.set_ylabel("max |h - scipy| (m); scipy itself plotted at 1e-12")
        ax.set_title("Heights: speed against error")
        ax.legend()
        fig.tight_layout()
        path = out_dir / "terrain_heights_speed_vs_error.png"
        fig.savefig(path, dpi=110)
        plt.close(fig)
        written.append(path)
    if "los_speed_vs_error" in series:
        fig, ax = plt.subplots(figsize=(6, 4))
        for row in series["los_speed_vs_error"]:
            ax.scatter(row["rays_per_s"], max(row["disagreement_rate"], 1e-4))
            ax.annotate(row["method"], (row["rays_per_s"], max(row["disagreement_rate"], 1e-4)), fontsize=7)
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel("10 km rays / s (one core)")
        ax.set_ylabel("fraction of rays answered wrongly (exact plotted at 1e-4)")
        ax.set_title("Line of sight: speed against error")
        fig.tight_layout()
        path = out_dir / "terrain_los_speed_vs_error.png"
        fig.savefig(path, dpi=110)
        plt.close(fig)
        written.append(path)
    return written


PLOTTERS = {"terrain": plot_terrain}
