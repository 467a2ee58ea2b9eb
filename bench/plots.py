"""The benchmark plots, drawn so that each says what it shows without the README.

Every axis is labelled with its unit, log axes carry plain tick labels (``20``, ``50``, ``100``,
``0.001``; never ``6x10^7``), every title names the scene and the machine setting. The sections
call these functions with the numbers they measured; ``python -m bench.plots`` redraws all three
PNGs from the tables in ``bench/results/*.md`` (no benchmark is re-run).
"""

from __future__ import annotations

import math
import os
import re

HERE = os.path.dirname(os.path.abspath(__file__))

#: Storage kinds of a GridSDF: (gradient, dtype) -> (label, colour, marker).
STORAGE = {
    ("stored", "float64"): ("stored gradients, float64 (24 B/node)", "#1f77b4", "o"),
    ("stored", "float32"): ("stored gradients, float32 (12 B/node)", "#2ca02c", "s"),
    ("fd", "float64"): ("finite differences, float64 (8 B/node)", "#ff7f0e", "^"),
    ("fd", "float32"): ("finite differences, float32 (4 B/node)", "#d62728", "v"),
}


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _plain(v: float) -> str:
    """``0.001``, ``0.5``, ``20``, ``300``, ``10k``, ``1M``: no powers of ten, no ``x10^``."""
    if v == 0:
        return "0"
    for scale, suffix in ((1e9, "G"), (1e6, "M"), (1e3, "k")):
        if abs(v) >= scale * (10 if suffix == "k" else 1):
            return f"{v / scale:g}{suffix}"
    if abs(v) >= 1e-4:
        return f"{v:g}".replace("e-04", "e-4") if abs(v) < 1e-3 else f"{v:g}"
    return f"{v:.0e}".replace("e-0", "e-")


def plain_log_ticks(ax, x: bool = True, y: bool = True) -> None:
    """Plain tick labels on log axes: majors always, minors 2 and 5 when a decade or less shows."""
    from matplotlib.ticker import FuncFormatter, LogLocator, NullFormatter

    for use, axis, lim in ((x, ax.xaxis, ax.get_xlim), (y, ax.yaxis, ax.get_ylim)):
        if not use or axis.get_scale() != "log":
            continue
        lo, hi = lim()
        decades = math.log10(max(hi, lo) / max(min(hi, lo), 1e-300))
        axis.set_major_formatter(FuncFormatter(lambda v, _p: _plain(v)))
        if decades <= 1.2:
            axis.set_minor_locator(LogLocator(subs=(2.0, 3.0, 4.0, 5.0, 6.0, 8.0)))
            axis.set_minor_formatter(FuncFormatter(lambda v, _p: _plain(v)))
        elif decades <= 2.5:
            axis.set_minor_locator(LogLocator(subs=(2.0, 5.0)))
            axis.set_minor_formatter(FuncFormatter(lambda v, _p: _plain(v)))
        else:
            axis.set_minor_formatter(NullFormatter())


def pareto_front(points):
    """The points no other point beats on both error (lower) and speed (higher), by error."""
    front, best = [], -math.inf
    for err, speed, *rest in sorted(points, key=lambda p: (p[0], -p[1])):
        if speed > best:
            front.append((err, speed, *rest))
            best = speed
    return front


def grid_speed_vs_error(results, path: str, n_points: int, threads: int, note: str = "") -> str:
    """Speed against error of every GridSDF storage kind, one panel per world and error measure.

    ``results``: dicts with ``world``, ``kind`` (``'grid'``, ``'seed'`` or ``'exact'``), ``res``,
    ``gradient``, ``dtype``, ``best`` (points/s), ``band_value_max``, ``band_angle_rms``.
    Each storage kind's measured points are drawn faint and its Pareto front (the resolutions
    worth picking: no other resolution of that kind is both faster and more accurate) as a line
    labelled with nodes per axis.
    """
    plt = _plt()
    worlds = list(dict.fromkeys(r["world"] for r in results))
    metrics = (
        ("band_value_max", "value error, max over |d| < 0.1 (length units)"),
        ("band_angle_rms", "gradient angle error, RMS over |d| < 0.1 (degrees)"),
    )
    fig, axes = plt.subplots(len(worlds), 2, figsize=(13, 4.6 * len(worlds)), squeeze=False)
    for row, world in enumerate(worlds):
        mine = [r for r in results if r["world"] == world]
        for col, (key, xlabel) in enumerate(metrics):
            ax = axes[row][col]
            errs = [r[key] for r in mine if r["kind"] != "exact" and r.get(key, 0) > 0]
            floor = min(errs) / 4 if errs else 1e-6
            for (gradient, dtype), (label, color, marker) in STORAGE.items():
                pts = [
                    (r[key], r["best"] / 1e6, r["res"])
                    for r in mine
                    if r["kind"] == "grid"
                    and r.get("gradient") == gradient
                    and r.get("dtype") == dtype
                    and r.get(key, 0) > 0
                ]
                if not pts:
                    continue
                ax.plot(
                    [p[0] for p in pts],
                    [p[1] for p in pts],
                    marker=marker,
                    linestyle="none",
                    color=color,
                    alpha=0.25,
                    markersize=5,
                )
                front = pareto_front(pts)
                ax.plot(
                    [p[0] for p in front],
                    [p[1] for p in front],
                    marker=marker,
                    color=color,
                    linewidth=1.6,
                    markersize=6,
                    label=label,
                )
                if (gradient, dtype) == ("stored", "float64"):
                    for err, speed, res in front:
                        ax.annotate(
                            f"{res}",
                            (err, speed),
                            xytext=(-4, 6),
                            textcoords="offset points",
                            ha="right",
                            fontsize=7,
                            color=color,
                            bbox=dict(boxstyle="round,pad=0.1", fc="white", ec="none", alpha=0.8),
                        )
            seed = sorted(
                (r[key], r["best"] / 1e6, r["res"])
                for r in mine
                if r["kind"] == "seed" and r.get(key, 0) > 0
            )
            if seed:
                ax.plot(
                    [p[0] for p in seed],
                    [p[1] for p in seed],
                    marker="x",
                    color="0.35",
                    linestyle=":",
                    label="the notebook's GridSDF (scipy map_coordinates)",
                )
            exact = [r for r in mine if r["kind"] == "exact"]
            if exact:
                speed = exact[0]["best"] / 1e6
                ax.plot(
                    [floor],
                    [speed],
                    marker="*",
                    markersize=13,
                    color="black",
                    linestyle="none",
                    label="exact compiled SDF (no error; drawn at left)",
                )
                ax.annotate(
                    "exact SDF",
                    (floor, speed),
                    xytext=(8, -3),
                    textcoords="offset points",
                    fontsize=7,
                )
            ax.set_xscale("log")
            ax.set_yscale("log")
            ax.set_xlabel(xlabel)
            ax.set_ylabel("value + gradient queries, M points/s")
            ax.set_title(f"{world}: speed vs error (numbers: nodes per axis)", fontsize=10)
            ax.grid(True, which="both", alpha=0.25)
            plain_log_ticks(ax)
    handles, labels = axes[0][0].get_legend_handles_labels()
    fig.legend(handles, labels, fontsize=8, loc="lower center", ncol=3, frameon=False)
    fig.suptitle(
        f"GridSDF: which storage and resolution to pick ({n_points:,} random points "
        f"in [-2, 2]^2, {threads} threads, best of repeats{note})\nlines: the Pareto "
        f"front of each storage kind (no other resolution of it is both faster and more "
        f"accurate); faint: the other resolutions measured",
        fontsize=10,
    )
    fig.tight_layout(rect=(0, 0.07, 1, 0.96))
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path


def core_scaling(
    sizes, by_points, counts, by_prims, n_prims_points: int, path: str, threads: int | None = None
) -> str:
    """Exact compiled SDFs: throughput against call size (per scene) and against scene size."""
    plt = _plt()
    fig, (a0, a1) = plt.subplots(1, 2, figsize=(11, 4.2))
    for name, rates in by_points.items():
        a0.loglog(sizes, [r / 1e6 for r in rates], "o-", label=name)
    a0.set_xlabel("points per call")
    a0.set_ylabel("value + gradient, M points/s")
    a0.set_title("exact compiled SDF: throughput vs call size")
    a0.legend(title="scene (notebook cells 21, 13)", fontsize=8, title_fontsize=8)
    a1.loglog(counts, [r / 1e6 for r in by_prims], "o-", color="tab:purple")
    for c, r in zip(counts, by_prims):
        a1.annotate(
            f"{r / 1e6:.3g}", (c, r / 1e6), xytext=(4, 4), textcoords="offset points", fontsize=7
        )
    a1.set_xlabel(
        "primitives in the scene (1: a circle; 5: the seed world; n: funnel + n-3 boxes)",
        fontsize=8,
    )
    a1.set_ylabel("value + gradient, M points/s")
    a1.set_title(f"throughput vs scene size ({n_prims_points:,} points per call)")
    for ax in (a0, a1):
        ax.grid(True, which="both", alpha=0.25)
        plain_log_ticks(ax)
    if threads:
        fig.suptitle(f"{threads} threads; calls under 4096 points run serially", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path


def particles_scaling(sizes, curve, path: str, scene: str = "seed world, 400x400 GridSDF") -> str:
    """Fused particle step: particle-steps/s against the particle count, per thread count."""
    plt = _plt()
    fig, ax = plt.subplots(figsize=(6, 4))
    for threads, rates in sorted(curve.items(), reverse=True):
        ax.loglog(
            sizes,
            [r / 1e6 for r in rates],
            "o-",
            label=f"{threads} thread{'s' if threads > 1 else ''}",
        )
    ax.set_xlabel("particles")
    ax.set_ylabel("M particle-steps/s")
    ax.set_title(
        f"fused particle step, {scene},\nsteps 0-100 of the notebook's drop, run(100)", fontsize=10
    )
    ax.grid(True, which="both", alpha=0.25)
    ax.legend(fontsize=8)
    plain_log_ticks(ax)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path


# ---------------------------------------------------------------------------------------------
# Redraw from the committed result tables.


def _rate(text: str) -> float:
    """``'126 M (184 M)'`` -> (126e6, 184e6); ``'627 k pts/s'`` -> 627e3."""
    units = {"": 1.0, "k": 1e3, "M": 1e6, "G": 1e9}
    vals = [float(v) * units[u] for v, u in re.findall(r"([\d.]+)\s*([kMG]?)\b", text)]
    return vals


def _table(md: str, first_header: str):
    """Rows (lists of cells) of the first markdown table whose first header cell matches."""
    lines = md.splitlines()
    for i, line in enumerate(lines):
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if line.startswith("|") and cells[0] == first_header:
            rows = []
            for body in lines[i + 2 :]:
                if not body.startswith("|"):
                    break
                rows.append([c.strip() for c in body.strip().strip("|").split("|")])
            return cells, rows
    return None, []


def _float(text: str) -> float:
    try:
        return float(text)
    except ValueError:
        return float("nan")


def replot() -> list[str]:
    """Redraw the three PNGs beside this file from ``bench/results/*.md``; returns their paths."""
    out = []
    res_dir = os.path.join(HERE, "results")
    with open(os.path.join(res_dir, "grid.md"), encoding="utf-8") as fh:
        header, rows = _table(fh.read(), "world")
    if header:
        col = {name: i for i, name in enumerate(header)}
        results = []
        for r in rows:
            method = r[col["method"]]
            speeds = _rate(r[col["points/s median (best)"]])
            entry = dict(
                world=r[col["world"]],
                best=speeds[-1],
                band_value_max=_float(r[col["band value max"]]),
                band_angle_rms=_float(r[col["band angle RMS (deg)"]]),
            )
            if method.startswith("exact"):
                entry["kind"] = "exact"
            elif method.startswith("seed"):
                entry.update(kind="seed", res=int(r[col["nodes per axis"]]))
            elif method == "GridSDF":
                entry.update(
                    kind="grid",
                    res=int(r[col["nodes per axis"]]),
                    dtype=r[col["storage"]],
                    gradient=r[col["gradient"]],
                )
            else:  # other grid kinds: not in this plot
                continue
            results.append(entry)
        out.append(
            grid_speed_vs_error(
                results, os.path.join(HERE, "grid_speed_vs_error.png"), 1_000_000, 2
            )
        )
    with open(os.path.join(res_dir, "core.md"), encoding="utf-8") as fh:
        md = fh.read()
    header, rows = _table(md, "points per call")
    _, prim_rows = _table(md, "primitives")
    if header and prim_rows:
        sizes = [int(r[0].replace(",", "")) for r in rows]
        by_points = {name: [_rate(r[i])[0] for r in rows] for i, name in enumerate(header) if i > 0}
        counts = [int(r[0]) for r in prim_rows]
        by_prims = [_rate(r[1])[0] for r in prim_rows]
        out.append(
            core_scaling(
                sizes,
                by_points,
                counts,
                by_prims,
                200_000,
                os.path.join(HERE, "core_scaling.png"),
                2,
            )
        )
    with open(os.path.join(res_dir, "particles.md"), encoding="utf-8") as fh:
        header, rows = _table(fh.read(), "particles")
    if header:
        sizes = [int(r[0].replace(",", "")) for r in rows]
        curve = {2: [_rate(r[1])[0] for r in rows], 1: [_rate(r[2])[0] for r in rows]}
        out.append(particles_scaling(sizes, curve, os.path.join(HERE, "particles_scaling.png")))
    return out


if __name__ == "__main__":  # pragma: no cover
    for p in replot():
        print(f"wrote {p}")
