"""Pruning per tile: hard unions of many small shapes, the notebook's box worlds (exponential
blends: speed versus error for ``tol``), and the seed world (pruning must switch itself off).

Every pruned figure is measured beside the unpruned kernel (``prune=False``) in the same process,
on the same points; "identical" compares the bits of value and gradient.
"""

from __future__ import annotations

import os
import time

import numpy as np

import fastsdf as sdf
from fastsdf.shapes.scenes import box_world, seed_world

from .common import fmt_rate, run_fresh_process, stamp, table, timeit

BOUNDS = ((-2.0, 2.0), (-2.0, 2.0))
#: Points x operands of one unpruned timing (its rate does not depend on the point count).
WORK = 2e7


_HEXAGON = 0.04 * np.stack([np.cos(np.arange(6) * np.pi / 3), np.sin(np.arange(6) * np.pi / 3)], 1)


def hard_union(n: int, kind: str = "box", seed: int = 0, k: float = 0.0):
    """``n`` small boxes (or hexagons) at random places and angles, hard union (a quadratic
    blend of width ``k`` if ``k > 0``).

    The hexagons are :func:`fastsdf.Polygon` (a compiled loop over a vertex table, so the
    union folds into a loop over a table of placements). ``RegularPolygon`` is built from
    graph operations with loops of its own, which do not fold across instances: 1000 of them
    generate a module of over a million lines.
    """
    rng = np.random.default_rng(seed)
    f = None
    for _ in range(n):
        with sdf.transform(angle=rng.uniform(-3, 3), offset=rng.uniform(-1.9, 1.9, 2)):
            s = sdf.Box([-0.03, -0.02], [0.03, 0.04]) if kind == "box" else sdf.Polygon(_HEXAGON)
        f = s if f is None else f.union(s, k=k, kind="quadratic") if k else f | s
    return f


def _bits(a, b):
    return np.array_equal(np.asarray(a).view(np.int64), np.asarray(b).view(np.int64))


def _cold(n: int, kind: str) -> float:
    """Seconds from nothing to the first pruned answer of 1e6 points, in a fresh process with an
    empty kernel cache (import excluded)."""
    import tempfile

    code = f"""
import time, numpy as np
import fastsdf
from bench.bench_prune import hard_union
t0 = time.perf_counter()
f = hard_union({n}, {kind!r})
x, y = np.random.default_rng(0).uniform(-2, 2, (2, 1_000_000))
d, g = f(x, y, compute_gradient=True)
print(time.perf_counter() - t0)
"""
    with tempfile.TemporaryDirectory() as tmp:
        return float(run_fresh_process(code, env={"FASTSDF_CACHE_DIR": tmp}).split()[-1])


def run(quick: bool = False) -> str:
    load = os.getloadavg()
    rng = np.random.default_rng(2026)
    n_pts = 100_000 if quick else 1_000_000
    n_small = 100_000 if quick else 200_000  # the blends and the worlds (unpruned rates)
    x, y = rng.uniform(-2, 2, (2, n_pts))
    configs = (
        [("box", 200)]
        if quick
        else [
            ("box", 20),
            ("box", 200),
            ("box", 1000),
            ("box", 5000),
            ("polygon", 1000),
            ("quadratic", 1000),
        ]
    )
    rows = []
    for kind, n in configs:
        if True:
            f = hard_union(n, "box", k=0.02) if kind == "quadratic" else hard_union(n, kind)
            t0 = time.perf_counter()
            f(x[:8], y[:8], compute_gradient=True)
            t_compile = time.perf_counter() - t0
            plan = f.compiled.plan(BOUNDS)
            rep = plan.report()
            # The unpruned kernel on fewer points where it is slow (its rate does not depend
            # on the count); the pruned one on all of them.
            m = n_pts if n * n_pts <= WORK else max(4_000, int(WORK // n))
            t_off, _ = timeit(
                lambda: f(x[:m], y[:m], compute_gradient=True, prune=False), repeats=3, warmup=0
            )
            t_on, _ = timeit(lambda: f(x, y, compute_gradient=True, prune=True), repeats=5)
            d1, g1 = f(x[:m], y[:m], compute_gradient=True, prune=True)
            d0, g0 = f(x[:m], y[:m], compute_gradient=True, prune=False)
            r_off, r_on = m / t_off, n_pts / t_on
            g_off = (
                timeit(lambda: _grid(f, False), repeats=1, warmup=0)[0]
                if n <= 1000 and kind != "polygon"
                else float("nan")
            )
            g_on = timeit(lambda: _grid(f, True), repeats=3, warmup=0)[0]
            rows.append(
                [
                    f"{n} {kind}es"
                    if kind == "box"
                    else f"{n} hexagons"
                    if kind == "polygon"
                    else f"{n} boxes, quadratic blend k = 0.02",
                    f"{t_compile:.2f} s",
                    fmt_rate(r_off),
                    fmt_rate(r_on),
                    f"**{r_on / r_off:.0f}x**",
                    "yes" if _bits(d0, d1) and _bits(g0, g1) else "**no**",
                    f"{rep['survivors_mean']:.1f} / {rep['survivors_max']}",
                    f"{rep['build_s']:.2f} s",
                    "" if g_off != g_off else f"{g_off:.2f} s",
                    f"{g_on:.3f} s",
                    "" if g_off != g_off else f"**{g_off / g_on:.0f}x**",
                ]
            )
    out = [
        "## Pruning per tile",
        "",
        stamp("python -m bench --only prune" + (" --quick" if quick else "")),
        "",
        f"Load average before the run: {load[0]:.1f}, {load[1]:.1f}, {load[2]:.1f} "
        "(shared machine: trust the ratios, measured side by side, more than the rates).",
        "",
        f"Hard unions of small shapes at random places in [-2, 2]^2, value + gradient at "
        f"{n_pts:,} random points; plan: 32 x 32 tiles over the points' bounds (its build is "
        "paid once per scene and bounds, then cached). Unpruned = the same compiled kernel "
        "with every operand (`prune=False`); GridSDF 400 x 400 build with and without the "
        "plan. Compile = build to first answer of 8 points, warm installation cache.",
        "",
        table(
            [
                "scene",
                "compile",
                "unpruned",
                "pruned",
                "speed-up",
                "identical bits",
                "survivors / tile (mean / max)",
                "plan build",
                "grid unpruned",
                "grid pruned",
                "grid speed-up",
            ],
            rows,
        ),
        "",
    ]
    if not quick:
        cold = [(n, _cold(n, "box")) for n in (5000,)]
        out += [
            "Cold start (fresh process, empty kernel cache, first answer of 1e6 points "
            "with gradient included): " + "; ".join(f"{n} boxes {t:.1f} s" for n, t in cold) + ".",
            "",
        ]
    # Exponential blends: the notebook's box worlds.
    trows = []
    x, y = x[:n_small], y[:n_small]
    n_pts = n_small
    for nb in [20] if quick else [200]:
        f = box_world(nb)
        f(x[:8], y[:8], compute_gradient=True)
        t_off, _ = timeit(lambda: f(x, y, compute_gradient=True, prune=False), repeats=3)
        d0, _ = f(x, y, compute_gradient=True, prune=False)
        t_auto, _ = timeit(lambda: f(x, y, compute_gradient=True), repeats=3)
        trows.append([f"box world {nb} (k=5)", "off", fmt_rate(n_pts / t_off), "1.0x", "0", ""])
        trows.append(
            [
                f"box world {nb} (k=5)",
                "automatic",
                fmt_rate(n_pts / t_auto),
                f"{t_off / t_auto:.2f}x",
                "",
                "",
            ]
        )
        for tol in (None, 1e-6, 1e-3):
            f.prune_tol = tol
            plan = f.compiled.plan(BOUNDS, tol=tol)
            t_on, _ = timeit(lambda: f(x, y, compute_gradient=True, prune=True), repeats=3)
            d1, _ = f(x, y, compute_gradient=True, prune=True)
            trows.append(
                [
                    f"box world {nb} (k=5)",
                    "default (half an ulp)" if tol is None else f"tol = {tol:g}",
                    fmt_rate(n_pts / t_on),
                    f"{t_off / t_on:.2f}x",
                    f"{np.max(np.abs(d1 - d0)):.2g}",
                    f"{plan.fraction:.2f}",
                ]
            )
        f.prune_tol = None
    out += [
        "Exponential blends (the notebook's box worlds, smoothness 5): every operand "
        "contributes, so pruning is approximate; operands whose total weight changes the "
        "result by at most `tol` are dropped. Error = max |pruned - unpruned| over the "
        "points; fraction = operands evaluated.",
        "",
        table(["scene", "pruning", "value + gradient", "vs off", "max error", "fraction"], trows),
        "",
    ]
    # The seed world and the 20-box world must not pay for pruning.
    srows = []
    for name, f in (("seed world", seed_world()), ("20-box world", box_world(20))):
        f(x[:8], y[:8], compute_gradient=True)
        t_off, s_off = timeit(lambda: f(x, y, compute_gradient=True, prune=False), repeats=5)
        t_auto, s_auto = timeit(lambda: f(x, y, compute_gradient=True), repeats=5)
        srows.append(
            [name, fmt_rate(n_pts / t_off), fmt_rate(n_pts / t_auto), f"{t_off / t_auto:.2f}"]
        )
    if not quick:
        out += _particles()
    out += [
        "Pruning switches itself off where it does not pay (automatic call against "
        "`prune=False`, same run):",
        "",
        table(["scene", "prune=False", "automatic", "ratio"], srows),
        "",
    ]
    return "\n".join(out)


def _particles() -> list:
    """The particle step on the 1000-box union (exact SDF) and on a grid of its middle with
    the exact fallback outside, with and without per-tile row lists, same process."""
    import fastsdf.function as F
    import fastsdf.particles as phys

    f = hard_union(1000)
    n, steps = 100_000, 5
    grid = sdf.GridSDF(f, bounds=[(-1, 1), (-1, 1)], samples=[201j, 201j], mode="exact")
    rows = []
    for name, world in (("exact SDF", f), ("GridSDF of [-1, 1]^2, exact fallback outside", grid)):
        res = {}
        for prune in (False, True):
            old = F.PRUNE_MIN_OPERANDS, F.PRUNE_MIN_POINTS
            if not prune:  # as for a small scene: the scene's own per-point function
                F.PRUNE_MIN_OPERANDS = F.PRUNE_MIN_POINTS = 10**15
            try:
                sim = phys.ParticleSimulation(world, n=n, timestep=1 / 30, seed=3)
                sim.force_generators += [phys.Gravity()]
                for warm in (True, False):
                    sim.p.x[:] = np.random.default_rng(4).uniform(-2, 2, (n, 2))
                    sim.p.v[:] = 0.0
                    t0 = time.perf_counter()
                    sim.run(1 if warm else steps)
                    dt = time.perf_counter() - t0
            finally:
                F.PRUNE_MIN_OPERANDS, F.PRUNE_MIN_POINTS = old
            res[prune] = (dt, sim.p.x.copy(), sim.p.v.copy())
        same = _bits(res[True][1], res[False][1]) and _bits(res[True][2], res[False][2])
        rate = [n * steps / res[k][0] for k in (False, True)]
        rows.append(
            [
                name,
                fmt_rate(rate[0]),
                fmt_rate(rate[1]),
                f"**{rate[1] / rate[0]:.0f}x**",
                "yes" if same else "**no**",
            ]
        )
    return [
        f"The particle step on the 1000-box union ({n:,} particles starting at random in "
        f"[-2, 2]^2, gravity, {steps} steps): each query evaluates its tile's rows (the "
        "plan covers the particles, or those outside the grid), against the scene's own "
        "per-point function with every row. Rates in particle steps per second.",
        "",
        table(["world", "unpruned", "pruned", "speed-up", "identical trajectories"], rows),
        "",
    ]


def _grid(f, prune: bool):
    import fastsdf.function as F

    old = F.PRUNE_MIN_POINTS
    if not prune:
        F.PRUNE_MIN_POINTS = 10**15
    try:
        return sdf.GridSDF(f, bounds=BOUNDS, samples=[400j, 400j])
    finally:
        F.PRUNE_MIN_POINTS = old
