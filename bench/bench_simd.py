"""SIMD block kernels and vectorizable exp/log: speed against the kernels they replace, the
C-library variant of the same kernels, and a hand-written Taichi kernel; error of the
approximations; cold compile time.

    python -m bench --only simd
"""

import importlib.util
import json
import math
import os
import shutil
import sys
import tempfile
import time

import numba
import numpy as np
from numba import njit, prange

from fastsdf.backends.kernel.vmath import vexp, vlog, vlog1p
from fastsdf.function import compile_expr
from fastsdf.shapes.scenes import box_world, seed_world

from .common import HERE, fmt_rate, run_fresh_process, stamp, table

COMMAND = "python -m bench --only simd"
BASELINES = os.path.join(HERE, "baseline_kernels")


def _load_baseline(name: str):
    """The frozen kernel module of commit 0a689d2 (before this work) for one scene."""
    path = os.path.join(BASELINES, f"{name}.py")
    key = f"fastsdf_baseline_{name}"
    if key in sys.modules:
        return sys.modules[key]
    spec = importlib.util.spec_from_file_location(key, path)
    mod = importlib.util.module_from_spec(spec)
    sys.modules[key] = mod  # numba's cache re-imports a kernel's module by name
    spec.loader.exec_module(mod)
    return mod


def _load_avg() -> str:
    try:
        with open("/proc/loadavg") as fh:
            return " / ".join(fh.read().split()[:3])
    except OSError:
        return "n/a"


def _interleaved(fns: dict, repeats: int, cpu: bool = False) -> dict:
    """Median seconds of each callable, timed in turn (round-robin) so that changes in the
    machine's load hit every contender alike. With ``cpu``: the process's CPU seconds instead
    of wall-clock seconds (steadier on a loaded machine; for 1-thread runs)."""
    clock = time.process_time if cpu else time.perf_counter
    for fn in fns.values():
        fn()
    times = {k: [] for k in fns}
    for _ in range(repeats):
        for k, fn in fns.items():
            t0 = clock()
            fn()
            times[k].append(clock() - t0)
    return {k: float(np.median(v)) for k, v in times.items()}


def _ulps(a, b):
    """Distance in representable doubles (NaN == NaN)."""
    ia = a.view(np.int64)
    ib = b.view(np.int64)
    ia = np.where(ia < 0, np.int64(-(2**63)) - ia, ia)
    ib = np.where(ib < 0, np.int64(-(2**63)) - ib, ib)
    est = np.abs(ia.astype(np.float64) - ib.astype(np.float64))
    with np.errstate(over="ignore"):
        exact = np.abs(ia - ib).astype(np.float64)
    d = np.where(est < 2.0**60, exact, est)
    d[np.isnan(a) & np.isnan(b)] = 0.0
    return d


# -- elementary functions ---------------------------------------------------------------------


def _apply(fn):
    @njit(parallel=True, error_model="numpy")
    def apply(a, out):
        for i in prange(a.shape[0]):
            out[i] = fn(a[i])

    return apply


@njit
def _m_exp(x):
    return math.exp(x)


@njit
def _m_log(x):
    return math.log(x)


@njit
def _m_log1p(x):
    return math.log1p(x)


def _elementary(quick: bool) -> str:
    n = 1_000_000 if quick else 4_000_000
    rng = np.random.default_rng(0)
    cases = [
        (
            "exp",
            vexp,
            _m_exp,
            "[-10, 0] (smooth blends: exp(-k abs(a - b)))",
            rng.uniform(-10, 0, n),
        ),
        ("exp", vexp, _m_exp, "[-745, 710] (whole range)", rng.uniform(-745, 710, n)),
        ("log", vlog, _m_log, "[1, 21] (blend sums)", rng.uniform(1, 21, n)),
        ("log", vlog, _m_log, "exp of [-745, 709]", np.exp(rng.uniform(-745, 709, n))),
        ("log1p", vlog1p, _m_log1p, "[-0.5, 2]", rng.uniform(-0.5, 2, n)),
    ]
    rows = []
    for name, fv, fm, where, a in cases:
        kv, km = _apply(fv), _apply(fm)
        ov, om = np.empty_like(a), np.empty_like(a)
        t = _interleaved({"v": lambda: kv(a, ov), "m": lambda: km(a, om)}, 3 if quick else 9)
        u = _ulps(ov, om)
        rows.append(
            (
                f"`{name}`",
                where,
                f"{fmt_rate(n / t['m'])}/s",
                f"**{fmt_rate(n / t['v'])}/s**",
                f"**{t['m'] / t['v']:.1f}x**",
                f"{u.max():.0f}",
                f"{np.mean(u > 0):.1%}",
            )
        )
    return table(
        [
            "function",
            "arguments",
            "C library (`math.*`)",
            "fastsdf.backends.kernel.vmath",
            "speed-up",
            "max ulp vs C library",
            "results differing by 1 ulp",
        ],
        rows,
    ) + (
        f"\n\n{n:,} arguments, {numba.get_num_threads()} threads, a `prange` loop per function. "
        "Random bit patterns over the whole float64 range and the IEEE edge cases (0, subnormals, "
        "+-inf, NaN, overflow/underflow bounds) are covered by `tests/test_vmath.py` (within "
        "2 ulp required, 1 ulp measured)."
    )


# -- a hand-written Taichi kernel of the seed world (value + analytic gradient) --------------


def _taichi_seed():
    """Taichi kernel ``(xs, ys, out, grad)`` for the seed world, written as a Taichi user would
    (one fused loop, hand gradient, the same tie rules); None if Taichi is not installed."""
    try:
        import taichi as ti
    except ImportError:
        return None
    ti.init(
        arch=ti.cpu,
        default_fp=ti.f64,
        cpu_max_num_threads=numba.get_num_threads(),
        log_level=ti.WARN,
    )
    c = 0.7071067811865475
    nx, ny = 0.09950371902099893, 0.9950371902099893
    k = 10.0

    @ti.kernel
    def seed_vg(
        xs: ti.types.ndarray(dtype=ti.f64, ndim=1),
        ys: ti.types.ndarray(dtype=ti.f64, ndim=1),
        out: ti.types.ndarray(dtype=ti.f64, ndim=1),
        grad: ti.types.ndarray(dtype=ti.f64, ndim=2),
    ):
        for i in xs:
            x, y = xs[i], ys[i]
            d, gx, gy = y + 1.8, 0.0, 1.0
            h = c * x + c * y + 1.8
            if h < d:
                d, gx, gy = h, c, c
            h = -c * x + c * y + 1.8
            if h < d:
                d, gx, gy = h, -c, c
            r = ti.sqrt(x * x + y * y)
            a, ax, ay = r - 0.5, 1.0, 0.0
            if r > 0:
                ax, ay = x / r, y / r
            b = nx * x + ny * y - 0.3
            e = ti.exp(-k * ti.abs(a - b))
            wa = e / (1.0 + e)
            m = b
            if a >= b:
                wa, m = 1.0 / (1.0 + e), a
            v = m + ti.log(1.0 + e) / k
            vx, vy = wa * ax + (1.0 - wa) * nx, wa * ay + (1.0 - wa) * ny
            e = ti.exp(-k * ti.abs(d - v))
            wd = 1.0 / (1.0 + e)
            m = d
            if v < d:
                wd, m = e / (1.0 + e), v
            out[i] = m - ti.log(1.0 + e) / k
            grad[i, 0] = wd * gx + (1.0 - wd) * vx
            grad[i, 1] = wd * gy + (1.0 - wd) * vy

    def call(xs, ys, out, grad):
        seed_vg(xs, ys, out, grad)
        ti.sync()

    return call


# -- whole kernels ------------------------------------------------------------------------------


def _kernels(quick: bool) -> tuple[str, str]:
    threads = numba.get_num_threads()
    repeats = 3 if quick else 11
    scenes = [
        ("seed world (cell 21)", seed_world(), "seed_world", 1_000_000 if not quick else 200_000),
        (
            "20-box world (cell 13)",
            box_world(20),
            "box_world_20",
            1_000_000 if not quick else 100_000,
        ),
    ]
    speed_rows, err_rows = [], []
    taichi = _taichi_seed()
    for name, f, base, n in scenes:
        rng = np.random.default_rng(42)
        xs, ys = rng.uniform(-2, 2, n), rng.uniform(-2, 2, n)
        today = _load_baseline(base).batch_vg_par
        new = compile_expr(f.f, ["x", "y"]).kernel("vg")
        libm = compile_expr(f.f, ["x", "y"], vmath=False).kernel("vg")
        outs = {key: (np.empty(n), np.empty((n, 2))) for key in ("today", "new", "libm", "taichi")}
        chunks = 64 * threads
        fns = {
            "today": lambda: today(xs, ys, *outs["today"], chunks),
            "new": lambda: new(xs, ys, *outs["new"], chunks),
            "libm": lambda: libm(xs, ys, *outs["libm"], chunks),
        }
        if taichi is not None and base == "seed_world":
            fns["taichi"] = lambda: taichi(xs, ys, *outs["taichi"])
        res = {threads: _interleaved(fns, repeats)}
        numba.set_num_threads(1)
        res[1] = _interleaved({k: v for k, v in fns.items() if k != "taichi"}, repeats, cpu=True)
        numba.set_num_threads(threads)
        t = res[threads]
        rate = {k: n / v for k, v in t.items()}
        rate1 = {k: n / v for k, v in res[1].items()}
        speed_rows.append(
            (
                f"{name}, {n:,} points",
                f"{fmt_rate(rate['today'])} pts/s ({fmt_rate(rate1['today'])})",
                f"{fmt_rate(rate['libm'])} pts/s ({fmt_rate(rate1['libm'])})",
                f"**{fmt_rate(rate['new'])} pts/s** ({fmt_rate(rate1['new'])})",
                f"**{rate['new'] / rate['today']:.2f}x** ({rate1['new'] / rate1['today']:.2f}x)",
                f"{rate['new'] / rate['libm']:.2f}x",
                f"{fmt_rate(rate['taichi'])} pts/s; **{rate['new'] / rate['taichi']:.2f}x**"
                if "taichi" in rate
                else "(not written)",
            )
        )
        # errors against the C-library kernel of the same shape, and today's kernel
        d_new, g_new = outs["new"]
        d_libm, g_libm = outs["libm"]
        d_today, _ = outs["today"]
        u = _ulps(d_new, d_libm)
        big = np.abs(d_libm) >= 0.1
        gerr = np.linalg.norm(g_new - g_libm, axis=1) / np.linalg.norm(g_libm, axis=1)
        t_err = ""
        if "taichi" in outs and base == "seed_world" and taichi is not None:
            t_err = f"{np.max(np.abs(outs['taichi'][0] - d_libm)):.1e}"
        err_rows.append(
            (
                name,
                f"{np.max(np.abs(d_new - d_libm)):.1e}",
                f"{u.max():.0f}",
                f"{u[big].max():.0f}",
                f"{np.mean(u <= 4):.4%}",
                f"{gerr.max():.1e}",
                f"{np.max(_ulps(d_libm, d_today)):.0f}",
                t_err or "-",
            )
        )
    numba.set_num_threads(threads)
    speed = table(
        [
            "scene (value + gradient)",
            f"before (commit 0a689d2), {threads} threads (1 thread, per CPU second)",
            "block kernels with `math.*`",
            "block kernels with `_vmath` (default)",
            "speed-up over before",
            "`_vmath` over `math.*`",
            f"Taichi, {threads} threads",
        ],
        speed_rows,
    )
    speed += (
        "\n\nMedians of interleaved repeats in one process. In parentheses: 1 thread, points "
        "per CPU second of the process (robust to other jobs on the machine). "
        "'before' is the kernel module fastsdf generated at commit 0a689d2 (frozen in "
        "`bench/baseline_kernels/`: 4 or 2 interleaved points per call, `math.exp`/"
        "`math.log`). Taichi: one fused kernel with the hand-written gradient, float64, "
        "the same thread count."
    )
    errors = table(
        [
            "scene",
            "max abs value error vs `math.*` kernel",
            "max ulp (all points)",
            "max ulp where abs(d) >= 0.1",
            "points within 4 ulp",
            "max gradient error / gradient length",
            "`math.*` block kernel vs before (ulp)",
            "Taichi vs `math.*` kernel (abs)",
        ],
        err_rows,
    )
    errors += (
        "\n\nThe kernels differ only in `exp`/`log` (each within 1 ulp of the C library). "
        "The value of a smooth blend is `m - log(s)/k`: near the surface (d -> 0) the two "
        "terms cancel, so a 1-ulp difference of `log(s)/k` (about 1e-17) is many ulps "
        "of a tiny `d`; in absolute terms the difference stays at a few 1e-17 and where "
        "abs(d) >= 0.1 it is within a few ulp. The C-library kernel has the same absolute "
        "rounding against exact arithmetic; the targets are 4 ulp in value and 1e-13 "
        "relative in gradients."
    )
    return speed, errors


# -- compile time -------------------------------------------------------------------------------

_PROBE = r"""
import json, os, sys, time
t0 = time.perf_counter(); c0 = time.process_time()
import numpy as np
WHAT
p = np.random.default_rng(0).uniform(-2, 2, (2, 8192))
out = np.empty(8192); grad = np.empty((8192, 2))
kernel(p[0], p[1], out, grad, 128)
print(json.dumps(dict(wall=time.perf_counter() - t0, cpu=time.process_time() - c0)))
"""

_NEW = """
from fastsdf.shapes.scenes import box_world
from fastsdf.function import compile_expr
kernel = compile_expr(box_world(20).f, ["x", "y"]).kernel("vg")
"""

_OLD = """
import importlib.util
spec = importlib.util.spec_from_file_location("box_world_20", os.path.join(os.environ["BASEDIR"], "box_world_20.py"))
mod = importlib.util.module_from_spec(spec); spec.loader.exec_module(mod)
kernel = mod.batch_vg_par
"""  # noqa: E501 - a script for a fresh process


def _compile(quick: bool) -> str:
    rows = []
    for label, what in (("before (commit 0a689d2)", _OLD), ("block kernels, `_vmath`", _NEW)):
        res = []
        for _ in range(1 if quick else 3):
            cache = tempfile.mkdtemp(prefix="fastsdf-simd-cache-")
            try:
                shutil.copy(os.path.join(BASELINES, "box_world_20.py"), cache)
                env = {"FASTSDF_CACHE_DIR": cache, "BASEDIR": cache}
                out = run_fresh_process(_PROBE.replace("WHAT", what), env)
                res.append(json.loads(out.strip().splitlines()[-1]))
            finally:
                shutil.rmtree(cache, ignore_errors=True)
        wall = float(np.median([r["wall"] for r in res]))
        cpu = float(np.median([r["cpu"] for r in res]))
        rows.append((label, f"**{wall:.2f} s**", f"{cpu:.2f} s"))
    return table(
        [
            "20-box world, cold (empty cache, fresh process)",
            "wall: import to first parallel value+gradient call",
            "CPU time of the process",
        ],
        rows,
    ) + (
        "\n\nImport of numpy, numba and fastsdf included; median of 3 fresh processes. CPU time "
        "is the steadier figure on a loaded machine. Target: cold 20-box world <= 3 s."
    )


def run(quick: bool = False) -> str:
    load0 = _load_avg()
    speed, errors = _kernels(quick)
    elem = _elementary(quick)
    comp = _compile(quick)
    parts = [
        "## SIMD block kernels and vectorizable exp/log",
        stamp(COMMAND + (" --quick" if quick else "")),
        f"Load average (1/5/15 min) at start: {load0}; at end: {_load_avg()} "
        f"(2-core machine shared with other jobs: trust the ratios more than the rates).",
        "",
        "### Exact evaluation, value + gradient",
        speed,
        "",
        "### Error of the approximations",
        errors,
        "",
        "### Elementary functions alone",
        elem,
        "",
        "### Compile time",
        comp,
    ]
    return "\n".join(parts) + "\n"
