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
    if "mesh_size_vs_error" in series:
        rows = series["mesh_size_vs_error"]
        fig, ax = plt.subplots(figsize=(7, 4.8))
        ax.set_xscale("log")
        ax.set_yscale("log")
        for kind, colour, what in (("regular", "tab:orange", "stride"), ("adaptive", "tab:blue", "within")):
            sel = [r for r in rows if r.get("kind") == kind]
            if not sel:
                continue
            size = [r["bytes"] / 1e6 for r in sel]
            ax.plot(size, [r["centre_error_max_m"] for r in sel], "o-", color=colour, label=f"{kind}: max")
            ax.plot(size, [r["centre_error_rms_m"] for r in sel], "s--", color=colour, label=f"{kind}: RMS")
            for r, x in zip(sel, size):
                label = f"{r['setting']:g} m" if kind == "adaptive" else f"x{r['setting']}"
                ax.annotate(label, (x, r["centre_error_max_m"]), fontsize=7, xytext=(3, 4), textcoords="offset points",
                            color=colour)
        ax.set_xlabel("glTF file (MB, geometry only)")
        ax.set_ylabel("|mesh - terrain| at the sampled cells' centres (m)")
        ax.set_title("Terrain meshes: size against error\n(regular: every k-th post; adaptive: RTIN within M m)")
        ax.legend(fontsize=7)
        _save(fig, out_dir / "terrain_mesh_size_vs_error.png", written)
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


def plot_recording(report: dict, out_dir: Path) -> list[Path]:
    """Write the recording suite's plots (seek latency CDFs against the goal, bytes per
    entity second against Tacview's exports); returns the files written."""
    plt = _pyplot()
    out_dir.mkdir(parents=True, exist_ok=True)
    written = []
    series = report.get("series", {})
    curves = [(key, label) for key, label in (("seek_ms", "Recording.frame, decoded-chunk cache cold"),
                                              ("seek_disk_cold_ms", "... and the file's pages out of the OS cache"),
                                              ("replay_seek_ms", "sortie replay: seek call until GetWorld shows it"))
              if series.get(key)]
    sizes = series.get("bytes_per_entity_second", {})
    panels = int(bool(curves)) + int(bool(sizes))
    if not panels:
        return written
    fig, axes = plt.subplots(1, panels, figsize=(6.0 * panels, 5.2), squeeze=False)
    axes = list(axes[0])
    long = report.get("params", {}).get("long", {})
    what = (f"{long.get('world_s', 0) / 60:.0f} min x {long.get('entities', '?')} entities"
            if long else "the long recording")
    if curves:
        ax = axes.pop(0)
        ax.set_xscale("log")
        for key, label in curves:
            xs = sorted(series[key])
            ys = [(k + 1) / len(xs) for k in range(len(xs))]
            ax.step(xs, ys, where="post", label=f"{label} (n={len(xs)})")
        from matplotlib.ticker import FixedLocator, NullFormatter, NullLocator, ScalarFormatter

        lo = min(min(series[key]) for key, _ in curves)
        hi = max(max(series[key]) for key, _ in curves)
        marks = (0.1, 0.2, 0.5, 1, 2, 5, 10, 20, 50, 100, 200, 500, 1000, 2000, 5000)
        first = max([v for v in marks if v <= lo] or [marks[0]])
        ax.set_xlim(first, max(100.0, hi * 1.3))
        ax.xaxis.set_major_locator(FixedLocator([v for v in marks if first <= v <= max(100.0, hi * 1.3)]))
        ax.xaxis.set_major_formatter(ScalarFormatter())
        ax.xaxis.set_minor_locator(NullLocator())
        ax.xaxis.set_minor_formatter(NullFormatter())
        ax.axvline(50.0, color="grey", lw=0.8, ls="--", label="goal: p99 <= 50 ms")
        ax.axhline(0.99, color="grey", lw=0.5, ls=":")
        ax.set_xlabel("seek latency (ms), random times")
        ax.set_ylabel("fraction of seeks at most this long")
        ax.set_title(f"Seeking in a recording of {what}", fontsize=9)
        ax.legend(fontsize=7, loc="upper center", bbox_to_anchor=(0.5, -0.14))
    if sizes:
        ax = axes.pop(0)
        names = {"sortie": "Sortie recording (.sortie)", "acmi_zip": "Tacview .zip.acmi, every tick",
                 "acmi_zip_10hz": "Tacview .zip.acmi, 10 Hz", "acmi_text": "Tacview .acmi text, every tick"}
        keys = [k for k in ("sortie", "acmi_zip", "acmi_zip_10hz", "acmi_text") if k in sizes]
        ax.barh([names[k] for k in keys], [sizes[k] for k in keys],
                color=["tab:blue" if k == "sortie" else "tab:orange" for k in keys])
        for y, k in enumerate(keys):
            ax.annotate(f"{sizes[k]:.0f}", (sizes[k], y), fontsize=7, xytext=(3, 0), textcoords="offset points",
                        va="center")
        ax.invert_yaxis()
        ax.set_xlim(0, max(sizes.values()) * 1.15)
        ax.set_xlabel("bytes per entity second")
        ax.set_title(f"Size: {what}, 30 Hz", fontsize=9)
    _save(fig, out_dir / "recording_seek_and_size.png", written)
    return written


def plot_render(report: dict, out_dir: Path) -> list[Path]:
    """The clipmap's speed against error (issue #5): screen error (median and p99, px) of each
    (L, n, budget) setting of the sweep against its triangles and its frame time, beside the
    full-resolution reference renderer, and each setting's update time (p99) against the 2 ms goal."""
    plt = _pyplot()
    rows = report.get("series", {}).get("sweep", [])
    ref = report.get("series", {}).get("sweep_reference")
    written: list[Path] = []
    if not rows or not ref:
        return written
    from matplotlib.ticker import LogLocator, NullFormatter, ScalarFormatter

    markers = {63: "v", 127: "o", 255: "s"}
    colours = {5: "tab:green", 6: "tab:blue", 7: "tab:purple"}
    floor = 0.01  # medians below this (level 0 draws the reference surface itself) are plotted on it
    fig, axes = plt.subplots(1, 3, figsize=(16.5, 5.0), gridspec_kw={"width_ratios": [1.0, 1.0, 0.8]})
    for ax, x_key, ref_x, xlabel in ((axes[0], "triangles", ref["triangles"], "triangles drawn (median frame)"),
                                     (axes[1], "frame_ms_test", ref["frame_ms_test"],
                                      "frame time, ms (median of measured frames, test mode)")):
        ax.set_xscale("log")
        ax.set_yscale("log")
        for row in rows:
            x, colour = row[x_key], colours.get(row["levels"], "grey")
            small_budget = row["budget"] < 10_000
            face = "none" if small_budget else colour
            ax.scatter(x, row["screen_error_px_p99"], marker=markers.get(row["n"], "D"), s=60 if row["default"] else 36,
                       facecolors=face, edgecolors="black" if row["default"] else colour)
            ax.scatter(x, max(row["screen_error_px_median"], floor), marker=markers.get(row["n"], "D"), s=14,
                       color=colour, alpha=0.45)
            label, offset = ((f"L{row['levels']} n{row['n']} b{row['budget'] // 1000}k", (4, -12)) if small_budget
                             else (f"L{row['levels']} n{row['n']}", (-8, 5 + 8 * (row["levels"] - 5))))
            ax.annotate(label, (x, row["screen_error_px_p99"]), fontsize=6, xytext=offset, textcoords="offset points")
        ax.scatter(ref_x, ref["screen_error_px_p99"], marker="*", s=140, color="tab:red")
        ax.annotate("reference renderer (p99:\nits ring of every 8th post)", (ref_x, ref["screen_error_px_p99"]),
                    fontsize=7, xytext=(0, -22), textcoords="offset points", ha="center", color="tab:red")
        for axis in (ax.xaxis,):
            axis.set_major_locator(LogLocator(subs=(1.0, 2.0, 5.0) if x_key == "triangles" else
                                              (1.0, 1.5, 2.0, 3.0, 5.0, 7.0)))
            axis.set_major_formatter(ScalarFormatter())
            axis.set_minor_formatter(NullFormatter())
        ax.set_ylim(floor * 0.7, 30.0)
        ax.axhline(2.0, color="grey", lw=0.8, ls="--")
        ax.axhline(1.0, color="grey", lw=0.8, ls=":")
        ax.annotate("goal p99 ≤ 2 px", (0.01, 2.1), xycoords=("axes fraction", "data"), fontsize=7, color="grey")
        ax.annotate("goal median ≤ 1 px", (0.01, 1.05), xycoords=("axes fraction", "data"), fontsize=7, color="grey")
        ax.set_xlabel(xlabel, fontsize=8)
        ax.set_ylabel(f"screen error vs the full-resolution mesh, px\n(large: p99; small: median, floor {floor:g})",
                      fontsize=8)
    axes[0].axvline(ref["triangles"] / 10.0, color="tab:red", lw=0.8, ls="--")
    axes[0].annotate("goal: ≤ 1/10 of the\nreference's triangles", (ref["triangles"] / 10.0, 0.03), fontsize=7,
                     color="tab:red", xytext=(4, 0), textcoords="offset points")
    for L, colour in colours.items():
        axes[0].scatter([], [], color=colour, label=f"L = {L}")
    for n, marker in markers.items():
        axes[0].scatter([], [], color="grey", marker=marker, label=f"n = {n}")
    axes[0].scatter([], [], facecolors="none", edgecolors="grey", label="small budget")
    axes[0].legend(fontsize=7, loc="lower left")
    ax = axes[2]
    labels = [f"L{r['levels']} n{r['n']}" + (f" b{r['budget'] // 1000}k" if r["budget"] < 10_000 else "")
              + (" *" if r["default"] else "") for r in rows]
    ax.barh(labels, [r["update_ms_p99"] for r in rows], color=[colours.get(r["levels"], "grey") for r in rows])
    ax.axvline(2.0, color="grey", lw=0.8, ls="--")
    ax.annotate("goal ≤ 2 ms", (2.0, 1.0), xycoords=("data", "axes fraction"), xytext=(3, -10),
                textcoords="offset points", fontsize=7, color="grey")
    ax.invert_yaxis()
    ax.tick_params(axis="y", labelsize=7)
    ax.set_xlabel("update time per 1/60 s frame at 300 m/s, p99 (ms)", fontsize=8)
    params = report.get("params", {})
    fig.suptitle(f"Geometry clipmap against the full-resolution reference: {', '.join(params.get('sweep_paths', []))}"
                 f" paths, {params.get('size', ['?', '?'])[0]}x{params.get('size', ['?', '?'])[1]}, "
                 f"{params.get('gl_renderer', '')} (* the default profile)", fontsize=9)
    out_dir.mkdir(parents=True, exist_ok=True)
    _save(fig, out_dir / "render_clipmap_speed_vs_error.png", written)
    return written


def plot_store(report: dict, out_dir: Path) -> list[Path]:
    """Rate-distortion curves of the store's codec per DEM: bits per post against the
    maximum and RMS error, with the PNG-like baseline at the same steps."""
    plt = _pyplot()
    out_dir.mkdir(parents=True, exist_ok=True)
    written = []
    rd = report.get("series", {}).get("rate_distortion", {})
    if not rd:
        return written
    fig, axes = plt.subplots(1, 2, figsize=(12, 5))
    for (name, steps), colour in zip(sorted(rd.items()), ("tab:blue", "tab:orange", "tab:green", "tab:red")):
        keys = sorted(steps, key=float)
        bits = [steps[k]["bits_per_post"] for k in keys]
        base = [8.0 * steps[k]["delta_zstd_bytes"] / (steps[k]["bytes"] * 8.0 / steps[k]["bits_per_post"])
                for k in keys]
        axes[0].plot([steps[k]["max_error_m"] for k in keys], bits, "o-", color=colour, label=f"{name} (pyramid)")
        axes[0].plot([steps[k]["max_error_m"] for k in keys], base, "x--", color=colour,
                     label=f"{name} (row delta + zstd)")
        axes[1].plot([steps[k]["rms_error_m"] for k in keys], bits, "o-", color=colour, label=name)
    axes[0].set_xlabel("maximum error (m), every post of level 0")
    axes[1].set_xlabel("RMS error (m)")
    for ax in axes:
        ax.set_ylabel("bits per post")
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=6)
    axes[1].legend(fontsize=7)
    fig.suptitle("sortie bench store: size against error (steps 1..16 m; 1 m is lossless on integer-metre DEMs)",
                 fontsize=9)
    _save(fig, out_dir / "store_rate_distortion.png", written)
    return written


PLOTTERS = {"store": plot_store, "terrain": plot_terrain, "fdm": plot_fdm, "server": plot_server, "recording": plot_recording,
            "render": plot_render}
