"""Narrow-band grids: memory, build time, query speed and error against dense grids; the particle
simulation's speed against its error for every kind of world.

    python -m bench --only band
    python -m bench --only band --quick       # small sizes, a smoke run

1. **Queries** (seed world, 20-box world): dense GridSDFs 400x400 and 3193x3193 (8x finer),
   NarrowBandGridSDFs at the 8x finer spacing sized to the dense 400x400 grid's memory, and
   tolerance builds. Speed on 1e6 uniform random points in bounds (the dense grid's benchmark)
   and on 1e6 points drawn in the band, side by side with the dense 400x400 grid (the variants
   take turns, repeat after repeat). Errors are measured on the same band points for every grid.
2. **Particles** (the notebook's scenario: gravity, 300 steps of 1/30 s, from the same initial
   state; :data:`PARTICLES` particles per world): the exact SDF, dense grids 50..1600 (float64
   and float32) and narrow-band
   grids; per configuration the particle-steps per second of the whole ``run(300)``, the memory,
   and the error against the run on the exact SDF: the displacement of the final positions of
   the particles at rest in the exact run (speed < 0.05; median and max), and the deepest
   penetration into the exact world at the end. The plot puts speed against the median
   displacement, all configurations.
"""

from __future__ import annotations

import os
import time

import numba
import numpy as np

import fastsdf.particles as phys
from fastsdf import GridSDF, NarrowBandGridSDF
from fastsdf.fields.band import band_points, measure_band_error
from fastsdf.shapes.scenes import box_world, seed_world

from .common import HERE, Progress, fmt_rate, stamp, table

COMMAND = "python -m bench --only band"
BOUNDS = [(-2, 2), (-2, 2)]
FINE = 3193  # 8x finer than 400x400: 3192 = 8 * 399 cells per axis
#: Band of the particle grids: the notebook's largest particle radius is 0.1; particles touch
#: surfaces from outside, so the band reaches 0.12 outside and 0.02 into matter.
PARTICLE_BAND = (-0.02, 0.12)
PLOT = "band_particles_speed_vs_error.png"


def _mb(nbytes):
    return f"{nbytes / 1e6:.3g}"


def _g(x):
    return f"{x:.2g}"


def _query_rates(grids, pts, repeats):
    """Median and best points/s per grid (value + gradient); the grids take turns."""
    times = {k: [] for k in grids}
    for g in grids.values():
        g(pts[0][:5000], pts[1][:5000], compute_gradient=True)
    for _ in range(repeats):
        for k, g in grids.items():
            t0 = time.perf_counter()
            g(pts[0], pts[1], compute_gradient=True)
            times[k].append(time.perf_counter() - t0)
    n = pts[0].size
    return {k: (n / float(np.median(t)), n / float(np.min(t))) for k, t in times.items()}


def _queries(world_name, world, quick, out):
    fine = 801 if quick else FINE
    coarse = 101 if quick else 400
    wx, wy = np.random.default_rng(5).uniform(-2, 2, (2, 10_000))
    world(wx, wy)  # compile or load the scene's kernels
    world(wx, wy, compute_gradient=True)
    t0 = time.perf_counter()
    dense = GridSDF(world, bounds=BOUNDS, samples=[coarse, coarse])
    grids = {f"dense {coarse}x{coarse}, float64": dense}
    builds = {f"dense {coarse}x{coarse}, float64": time.perf_counter() - t0}
    if not quick and world_name == "seed world":
        t0 = time.perf_counter()
        grids[f"dense {fine}x{fine}, float64"] = GridSDF(world, bounds=BOUNDS, samples=[fine, fine])
        builds[f"dense {fine}x{fine}, float64"] = time.perf_counter() - t0
    w64, w32 = (0.004, 0.01)
    specs = [
        (
            f"band {fine}x{fine} (8x finer), float64, band 0.004",
            dict(band=w64, samples=[fine, fine]),
        ),
        (
            f"band {fine}x{fine}, float64, band 0.004, tolerance 2e-5",
            dict(band=w64, samples=[fine, fine], tolerance=2e-5),
        ),
        (
            f"band {fine}x{fine}, float32, band 0.01, tolerance 2e-5",
            dict(band=w32, samples=[fine, fine], tolerance=2e-5, dtype=np.float32),
        ),
        ("band, tolerance 1e-4, band 0.01", dict(band=w32, tolerance=1e-4)),
        ("band, tolerance 1e-5, band 0.01", dict(band=w32, tolerance=1e-5)),
    ]
    for name, kw in specs:
        g = NarrowBandGridSDF(world, bounds=BOUNDS, **kw)
        grids[name] = g
        builds[name] = g.build_seconds
    # Common evaluation points: drawn in the fine tiles of the narrowest band grid, kept where
    # |d| < 0.004 (the narrowest band), so every grid is measured on the same points.
    probe = grids[specs[0][0]]
    bx, by = band_points(probe, 400_000 if not quick else 100_000, seed=1)
    errs = {k: measure_band_error(g, points=(bx, by), band=w64) for k, g in grids.items()}
    n = 200_000 if quick else 1_000_000
    rng = np.random.default_rng(0)
    uni = (rng.uniform(-2, 2, n), rng.uniform(-2, 2, n))
    sel = np.random.default_rng(2).integers(0, bx.size, n)
    bandp = (bx[sel].copy(), by[sel].copy())
    reps = 3 if quick else 5
    timed = {k: g for k, g in grids.items() if "dense" not in k or "400" in k or "101" in k}
    r_uni = _query_rates(timed, uni, reps)
    r_band = _query_rates(timed, bandp, reps)
    base = f"dense {coarse}x{coarse}, float64"
    rows = []
    for k, g in grids.items():
        e = errs[k]
        mem = g.nbytes
        exact_cells = getattr(g, "n_exact_cells", "")
        sp = g.spacing[0]
        ru = r_uni.get(k)
        rb = r_band.get(k)
        rows.append(
            [
                k,
                f"{sp:.2g}",
                _mb(mem),
                f"{builds.get(k, 0) * 1e3:.0f}",
                exact_cells,
                _g(e.band_value_max),
                _g(e.band_value_rms),
                _g(e.band_angle_rms_deg),
                f"{errs[base].band_value_max / e.band_value_max:.0f}x" if k != base else "1",
                f"{errs[base].band_value_rms / e.band_value_rms:.0f}x" if k != base else "1",
                f"{fmt_rate(ru[0])} ({fmt_rate(ru[1])})" if ru else "",
                f"{ru[0] / r_uni[base][0]:.2f}" if ru else "",
                f"{fmt_rate(rb[0])} ({fmt_rate(rb[1])})" if rb else "",
                f"{rb[0] / r_band[base][0]:.2f}" if rb else "",
            ]
        )
    out += [
        f"### Queries: {world_name}",
        "",
        table(
            [
                "grid",
                "spacing",
                "memory (MB)",
                "build (ms)",
                "exact cells",
                "band value max",
                "band value RMS",
                "band angle RMS (deg)",
                "max err: dense / this",
                "RMS err: dense / this",
                "uniform points/s",
                "vs dense",
                "band points/s",
                "vs dense",
            ],
            rows,
        ),
        "",
    ]
    return grids, errs, r_uni, r_band, specs, base


# ---------------------------------------------------------------------------------------------
# Particles.


def _run_particles(world, g, n, steps):
    sim = phys.ParticleSimulation(g, n=n, seed=0)
    sim.force_generators += [phys.Gravity()]
    warm = phys.ParticleSimulation(g, n=n, seed=0)  # compile or load the parallel kernel
    warm.force_generators += [phys.Gravity()]
    warm.run(1)
    del warm
    t0 = time.perf_counter()
    sim.run(steps)
    dt = time.perf_counter() - t0
    x = np.asarray(sim.p["x"], dtype=np.float64)
    v = np.asarray(sim.p["v"], dtype=np.float64)
    r = np.asarray(sim.p["r"], dtype=np.float64)
    return n * steps / dt, x, v, r


def _particle_configs(world, quick):
    dense_sizes = (50, 100, 200, 400) if quick else (50, 100, 200, 400, 1600)
    fine = 801 if quick else FINE
    configs = [("exact SDF", "exact", lambda: world)]
    for s in dense_sizes:
        configs.append(
            (
                f"dense {s}x{s}",
                "dense float64",
                lambda s=s: GridSDF(world, bounds=BOUNDS, samples=[s, s]),
            )
        )
    for s in (400,):
        configs.append(
            (
                f"dense {s}x{s} float32",
                "dense float32",
                lambda s=s: GridSDF(world, bounds=BOUNDS, samples=[s, s], dtype=np.float32),
            )
        )
    configs += [
        (
            f"band {fine}x{fine} float32",
            "narrow band",
            lambda: NarrowBandGridSDF(
                world, bounds=BOUNDS, band=PARTICLE_BAND, samples=[fine, fine], dtype=np.float32
            ),
        ),
        (
            "band 400x400",
            "narrow band",
            lambda: NarrowBandGridSDF(world, bounds=BOUNDS, band=PARTICLE_BAND, samples=[400, 400]),
        ),
        (
            "band tolerance 1e-4",
            "narrow band",
            lambda: NarrowBandGridSDF(world, bounds=BOUNDS, band=PARTICLE_BAND, tolerance=1e-4),
        ),
        (
            "band tolerance 1e-5",
            "narrow band",
            lambda: NarrowBandGridSDF(world, bounds=BOUNDS, band=PARTICLE_BAND, tolerance=1e-5),
        ),
    ]
    return configs


#: Particles per run (full mode).
PARTICLES = {"seed world": 1_000_000, "20-box world": 1_000_000}


def _particles(world_name, world, quick, bar):
    n = 50_000 if quick else PARTICLES[world_name]
    steps = 60 if quick else 300
    results = []
    ref = None
    for name, kind, make in _particle_configs(world, quick):
        g = make()
        rate, x, v, r = _run_particles(world, g, n, steps)
        if ref is None:
            ref = (x, v)
            rest = np.linalg.norm(v, axis=1) < 0.05
        disp = np.linalg.norm(x - ref[0], axis=1)[rest]
        pen = float(np.max(np.maximum(r - world(x[:, 0], x[:, 1]), 0.0)))
        mem = getattr(g, "nbytes", 0)
        results.append(
            dict(
                name=name,
                kind=kind,
                rate=rate,
                mem=mem,
                med=float(np.median(disp)),
                max=float(np.max(disp)),
                q99=float(np.quantile(disp, 0.99)),
                pen=pen,
            )
        )
        bar.step(f"{world_name}: {name}")
    return results, float(rest.mean()), n, steps


def _side_by_side(world, quick):
    """Settled-phase step rate of the dense 400x400 grid against narrow-band grids, side by
    side (run(20) from the same state after 200 steps, the variants taking turns)."""
    n = 100_000 if quick else 1_000_000
    dense = GridSDF(world, bounds=BOUNDS, samples=[400, 400])
    fine = 801 if quick else FINE
    grids = {
        "dense 400x400 float64": dense,
        "band 400x400 float64": NarrowBandGridSDF(
            world, bounds=BOUNDS, band=PARTICLE_BAND, samples=[400, 400]
        ),
        f"band {fine}x{fine} float32": NarrowBandGridSDF(
            world, bounds=BOUNDS, band=PARTICLE_BAND, samples=[fine, fine], dtype=np.float32
        ),
        "band tolerance 1e-4": NarrowBandGridSDF(
            world, bounds=BOUNDS, band=PARTICLE_BAND, tolerance=1e-4
        ),
    }
    sim = phys.ParticleSimulation(dense, n=n, seed=0)
    sim.force_generators += [phys.Gravity()]
    sim.run(200)
    state = sim.p.copy()
    sims = {}
    for k, g in grids.items():
        s = phys.ParticleSimulation(g, n=n, seed=0)
        s.force_generators += [phys.Gravity()]
        s.p = state.copy()
        s.run(1)
        sims[k] = s
    times = {k: [] for k in grids}
    for _ in range(3):
        for k, s in sims.items():
            s.p = state.copy()
            t0 = time.perf_counter()
            s.run(20)
            times[k].append(time.perf_counter() - t0)
    return {
        k: (n * 20 / float(np.median(t)), n * 20 / float(np.min(t)), grids[k].nbytes)
        for k, t in times.items()
    }


def _plot(all_results, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    styles = {
        "exact": ("k", "*"),
        "dense float64": ("tab:blue", "o"),
        "dense float32": ("tab:cyan", "s"),
        "narrow band": ("tab:red", "D"),
    }
    fig, axes = plt.subplots(
        1, len(all_results), figsize=(6.5 * len(all_results), 5.2), squeeze=False
    )
    for ax, (world_name, results, n, steps) in zip(axes[0], all_results):
        errs = [r["med"] for r in results if r["med"] > 0]
        floor = min(errs) / 4 if errs else 1e-9
        seen = set()
        for r in results:
            colour, marker = styles[r["kind"]]
            x = r["med"] if r["med"] > 0 else floor
            label = r["kind"] if r["kind"] not in seen else None
            seen.add(r["kind"])
            ax.scatter([x], [r["rate"]], c=colour, marker=marker, s=70, label=label, zorder=3)
            text = r["name"].replace(" float32", " f32").replace("tolerance ", "tol ")
            if r["kind"] == "exact":
                text += " (error 0)"
            ax.annotate(text, (x, r["rate"]), textcoords="offset points", xytext=(5, 4), fontsize=7)
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel("median displacement of resting particles vs the exact-SDF run")
        ax.set_ylabel("particle-steps / s (whole run)")
        ax.set_title(f"{world_name}: {n:,} particles x {steps} steps")
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=8, loc="best")  # the corner with the fewest points
    fig.suptitle("Particles: speed against error (up and left is better)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def run(quick: bool = False) -> str:
    threads = numba.get_num_threads()
    load_before = os.getloadavg()
    out = [
        "## Narrow-band grids: memory, error and speed; particles' speed against error",
        "",
        stamp(COMMAND + (" --quick" if quick else "")),
        "",
        f"{threads} numba threads. See the module docstring of `bench/bench_band.py` for the "
        "method. Query speeds: value + gradient, median of side-by-side repeats (best in "
        "parentheses); 'vs dense' is the ratio of medians to the dense 400x400 grid in the "
        "same run. Errors: on the same random points in the band |d| < 0.004 for every grid "
        "(value error in coordinate units, gradient angle in degrees). 'exact cells' are "
        "cells where a tolerance build answers with the exact SDF (kinks).",
        "",
    ]
    worlds = [("seed world", seed_world()), ("20-box world", box_world(20))]
    n_configs = len(_particle_configs(worlds[0][1], quick))
    all_results = []
    target_lines = []
    with Progress(2 * (n_configs + 2), "band") as bar:
        for world_name, world in worlds:
            grids, errs, r_uni, r_band, specs, base = _queries(world_name, world, quick, out)
            bar.step(f"{world_name}: queries")
            if world_name == "seed world":
                at = specs[2][0] if not quick else specs[2][0]
                g = grids[at]
                target_lines.append(
                    f"- memory: `{at}` takes {_mb(g.nbytes)} MB against the dense 400x400 "
                    f"grid's {_mb(grids[base].nbytes)} MB; its band error is "
                    f"{errs[base].band_value_max / errs[at].band_value_max:.0f}x smaller (max) "
                    f"and {errs[base].band_value_rms / errs[at].band_value_rms:.0f}x (RMS) "
                    f"(target: >= 50x at 8x finer spacing). Without exact cells (`{specs[0][0]}`,"
                    f" {_mb(grids[specs[0][0]].nbytes)} MB): "
                    f"{errs[base].band_value_max / errs[specs[0][0]].band_value_max:.0f}x (max),"
                    f" {errs[base].band_value_rms / errs[specs[0][0]].band_value_rms:.0f}x "
                    f"(RMS): bilinear interpolation is first order at the SDF's kinks."
                )
                target_lines.append(
                    f"- random-point queries: {r_uni[at][0] / r_uni[base][0]:.2f}x the dense "
                    f"400x400 grid on uniform points, {r_band[at][0] / r_band[base][0]:.2f}x on "
                    f"points in the band (target >= 0.6x)."
                )
                tol5 = grids[specs[4][0]]
                target_lines.append(
                    f"- build of the 1e-5-tolerance grid: {tol5.build_seconds:.2f} s (target "
                    f"< 1 s), spacing {tol5.spacing[0]:.2g}, {_mb(tol5.nbytes)} MB, measured "
                    f"band error max {_g(errs[specs[4][0]].band_value_max)} on |d| < 0.004 and "
                    f"{_g(measure_band_error(tol5).band_value_max)} on its own band |d| < 0.01."
                )
            side = _side_by_side(world, quick)
            bar.step(f"{world_name}: side by side")
            dense_rate = side["dense 400x400 float64"][0]
            out += [
                f"Settled particles ({world_name}), `run(20)` from the state after 200 "
                f"steps, side by side (particle-steps/s, median and best):",
                "",
                table(
                    ["world", "memory (MB)", "particle-steps/s", "vs dense 400x400"],
                    [
                        [k, _mb(m), f"{fmt_rate(a)} ({fmt_rate(b)})", f"{a / dense_rate:.2f}"]
                        for k, (a, b, m) in side.items()
                    ],
                ),
                "",
            ]
            if world_name == "seed world":
                ratios = ", ".join(
                    f"{k}: {a / dense_rate:.2f}x"
                    for k, (a, b, m) in side.items()
                    if k.startswith("band")
                )
                target_lines.append(
                    f"- settled particle step against the dense 400x400 grid "
                    f"(target >= 0.8x): {ratios}."
                )
            results, rest_frac, n, steps = _particles(world_name, world, quick, bar)
            all_results.append((world_name, results, n, steps))
            out += [
                f"### Particles: {world_name}, {n:,} particles x {steps} steps",
                "",
                f"{rest_frac:.0%} of the particles are at rest at the end of the exact run; "
                f"displacements are over those. Penetration: max over all particles of "
                f"r - d_exact(x) at the end (0 = none).",
                "",
                table(
                    [
                        "world",
                        "memory (MB)",
                        "particle-steps/s",
                        "median displacement",
                        "99% displacement",
                        "max displacement",
                        "max penetration",
                    ],
                    [
                        [
                            r["name"],
                            _mb(r["mem"]) if r["mem"] else "",
                            fmt_rate(r["rate"]),
                            _g(r["med"]),
                            _g(r["q99"]),
                            _g(r["max"]),
                            _g(r["pen"]),
                        ]
                        for r in results
                    ],
                ),
                "",
            ]
    if not quick:
        _plot(all_results, os.path.join(HERE, PLOT))
        out += [f"![particles: speed against error]({PLOT})", ""]
    load_after = os.getloadavg()
    out += (
        ["Targets:", ""]
        + target_lines
        + [
            "",
            f"Machine load (1-minute load average) at the start and end of this section: "
            f"{load_before[0]:.2f} and {load_after[0]:.2f} on {os.cpu_count()} cores; absolute "
            f"rates drift with it, ratios measured side by side hold better.",
            "",
        ]
    )
    return "\n".join(out)
