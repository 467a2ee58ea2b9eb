"""Runtime parameters and moving scenes: what a parameter costs, and a 300-frame animation.

    python -m bench --only params

1. The seed world with its circle's centre as a parameter against the same scene with the centre
   baked in as constants (1e6 points, value + gradient and value only, the two timed in
   alternating rounds in one process).
2. A 300-frame animated scene (a rotating stirrer in a box, ``examples/moving_walls.py``) in a
   fresh process with an empty kernel cache: how many kernels compile over the 300 frames and
   what the compiling costs, particle-steps/s of the moving scene against the same scene held
   still (the stirrer frozen), and what baking each frame's angle as a constant would cost.
"""

from __future__ import annotations

import json
import os
import shutil
import tempfile

import numpy as np

import fastsdf as sdf
from fastsdf.shapes.scenes import funnel

from .common import Progress, fmt_rate, run_fresh_process, stamp, table, timeit

COMMAND = "python -m bench --only params"


def seed_world_with_centre(cx, cy):
    """Notebook cell 21 with the circle's centre given (numbers or parameters)."""
    f = funnel()
    with sdf.smoothness(10):
        f |= sdf.Circle(center=[cx, cy], radius=0.5) & sdf.Halfspace(normal=[0.1, 1], d=0.3)
    return f


def _evaluation(quick: bool) -> str:
    n = 200_000 if quick else 1_000_000
    x, y = np.random.default_rng(0).uniform(-2, 2, (2, n))
    param = seed_world_with_centre(sdf.Param("cx", 0.0), sdf.Param("cy", 0.0))
    baked = seed_world_with_centre(0.0, 0.0)
    rows = []
    rounds = 3 if quick else 9
    with Progress(2 * rounds, "params: evaluation") as bar:
        for label, grad in (("value + gradient", True), ("value", False)):
            param(x, y, compute_gradient=grad, cx=0.1)  # compile, warm
            baked(x, y, compute_gradient=grad)
            tp, tb = [], []
            for r in range(rounds):
                # A new centre every call: the parameter path as an animation uses it.
                tp.append(
                    timeit(lambda: param(x, y, compute_gradient=grad, cx=0.01 * r), repeats=3)[0]
                )
                tb.append(timeit(lambda: baked(x, y, compute_gradient=grad), repeats=3)[0])
                bar.step()
            mp, mb = float(np.median(tp)), float(np.median(tb))
            rows.append([label, fmt_rate(n / mb), fmt_rate(n / mp), f"{mp / mb - 1:+.1%}"])
    out = [
        "### Parameters as kernel data: the seed world's circle centre",
        "",
        stamp(COMMAND),
        "",
        table(
            [
                "path",
                "centre baked in (constants)",
                "centre as parameters, new value every call",
                "parameter overhead",
            ],
            rows,
        ),
        "",
        f"{n} points, medians of {rounds} alternating rounds (3 timed calls each). The "
        "parameter is read once per call from a tuple argument (passed by value, no "
        "reference counting); the target is at most +5%.",
    ]
    return "\n".join(out)


_ANIMATION = r"""
import json, time
t0 = time.perf_counter()
import numpy as np
import fastsdf as sdf
import fastsdf.particles as phys
from fastsdf.backends.kernel import cache as _cache
import importlib.util, sys
spec = importlib.util.spec_from_file_location("mw", "EXAMPLE")
mw = importlib.util.module_from_spec(spec); spec.loader.exec_module(mw)

def overloads():
    n = 0
    for mod in list(_cache._MODULES.values()):
        for name in dir(mod):
            fn = getattr(mod, name)
            n += len(getattr(fn, "overloads", {}))
    return n

def run(world, frames, n):
    sim = mw.make_simulation(world, n=n, seed=0)
    t0 = time.perf_counter()
    sim.run(1)
    first = time.perf_counter() - t0
    kernels = overloads()
    t0 = time.perf_counter()
    for _ in range(frames - 1):
        sim.run(1)
    rest = time.perf_counter() - t0
    return dict(first_s=first, rest_s=rest, kernels_after_first=kernels,
                kernels_after_all=overloads(), modules=len(_cache._MODULES),
                rate=n * (frames - 1) / rest)

world = mw.stirrer_world()
moving = run(world, FRAMES, N)
static = run(world.frozen(t=0.0), FRAMES, N)
# What baking every frame's angle into constants would cost: compile two such scenes.
t0 = time.perf_counter()
for k in range(2):
    w = world.frozen(t=0.123 + k)
    w(np.zeros(8192), np.zeros(8192), compute_gradient=True)
    mw.make_simulation(w, n=64, seed=0).run(1)
baked_each = (time.perf_counter() - t0) / 2
print(json.dumps(dict(moving=moving, static=static, baked_each_s=baked_each)))
"""


def _animation(quick: bool) -> str:
    frames, n = (30, 100_000) if quick else (300, 1_000_000)
    example = os.path.join(
        os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "examples", "moving_walls.py"
    )
    code = (
        _ANIMATION.replace("EXAMPLE", example).replace("FRAMES", str(frames)).replace("N)", f"{n})")
    )
    cache = tempfile.mkdtemp(prefix="fastsdf-bench-cache-")
    try:
        with Progress(1, "params: animation (fresh process)") as bar:
            res = json.loads(
                run_fresh_process(code, {"FASTSDF_CACHE_DIR": cache}, timeout=1800)
                .strip()
                .splitlines()[-1]
            )
            bar.step()
    finally:
        shutil.rmtree(cache, ignore_errors=True)
    mv, st = res["moving"], res["static"]
    rows = [
        [
            "rotating stirrer (the angle is 0.8 t, evaluated at each step's time)",
            f"{mv['first_s']:.2f} s",
            str(mv["kernels_after_all"] - mv["kernels_after_first"]),
            f"{mv['rest_s']:.2f} s",
            fmt_rate(mv["rate"]),
        ],
        [
            "the same scene held still (stirrer frozen at t = 0, its own kernel)",
            f"{st['first_s']:.2f} s",
            str(st["kernels_after_all"] - st["kernels_after_first"]),
            f"{st['rest_s']:.2f} s",
            fmt_rate(st["rate"]),
        ],
    ]
    out = [
        "### A 300-frame animated scene (a stirrer in a box)",
        "",
        stamp(COMMAND),
        "",
        table(
            [
                "scene",
                "first frame (cold cache: code generation and compile)",
                "compiles after the first frame",
                f"frames 2-{frames}",
                "particle-steps/s (frames 2 on)",
            ],
            rows,
        ),
        "",
        f"{n} particles, one step per frame (`sim.run(1)`), fresh process, empty kernel "
        f"cache. Moving / static speed: {mv['rate'] / st['rate']:.2f}. Baking each "
        f"frame's angle into constants instead would compile a new scene and particle "
        f"kernel every frame: {res['baked_each_s']:.2f} s each (measured on two), about "
        f"{frames * res['baked_each_s'] / 60:.0f} minutes for {frames} frames.",
    ]
    return "\n".join(out)


def run(quick: bool = False) -> str:
    before = os.getloadavg()
    parts = [
        "## Runtime parameters and moving scenes",
        "",
        _evaluation(quick),
        "",
        _animation(quick),
        "",
    ]
    after = os.getloadavg()
    parts += [
        f"Machine load (1, 5, 15 min load averages, other work included) at the start: "
        f"{before[0]:.1f} {before[1]:.1f} {before[2]:.1f}; at the end: {after[0]:.1f} "
        f"{after[1]:.1f} {after[2]:.1f}.",
        "",
    ]
    return "\n".join(parts)
