"""What a new scene costs before its first evaluation: building it, and the per-node passes.

    python -m bench.bench_build          (or: python -m bench --only build)

For each scene, in this process after a warm-up (pure Python: no numba compilation is timed),
the median over repeats of: building the scene with the modelling DSL (``fastsdf.shapes``),
per primitive; the code generator (``f.compiled.module_source``); and the pruning plan
(``f.compiled.plan`` over ``[-3, 3]^2``, 32 x 32 tiles; only scenes with loops over tables
have one). Every repeat builds the scene from other
random constants (``seed``), so no cache keyed by the expression helps.

Box unions are written two ways: ``f = f | Box(...)`` in a loop, and the n-ary
``fastsdf.union`` of a list comprehension of boxes; polygons (stars and triangles, the compiled
polygon primitive) are united at once; the mixed scenes are
:func:`fastsdf.shapes.scenes.mixed_scene`.
"""

from __future__ import annotations

import argparse
import os
import sys
import time

import numpy as np

from .common import stamp, table

COMMAND = "python -m bench.bench_build"


def boxes_loop(n: int, seed: int = 0):
    """A hard union of ``n`` small boxes, written ``f = f | Box(...)`` in a loop."""
    import fastsdf as sdf

    c = np.random.default_rng(seed).uniform(-2, 2, (n, 2))
    f = sdf.Box(c[0] - 0.05, c[0] + 0.05)
    for p in c[1:]:
        f = f | sdf.Box(p - 0.05, p + 0.05)
    return f


def boxes_list(n: int, seed: int = 0):
    """The same union from a list comprehension, united at once (``fastsdf.union``)."""
    import fastsdf as sdf

    c = np.random.default_rng(seed).uniform(-2, 2, (n, 2))
    shapes = [sdf.Box(p - 0.05, p + 0.05) for p in c]
    if not hasattr(sdf, "union"):  # an older fastsdf (to compare): a left fold
        import functools

        return functools.reduce(lambda a, b: a | b, shapes)
    return sdf.union(shapes)


def polygons_list(n: int, seed: int = 0):
    """A union of ``n`` small rotated stars and triangles (compiled polygon primitives)."""
    import fastsdf as sdf

    rng = np.random.default_rng(seed)
    shapes = []
    for i, p in enumerate(rng.uniform(-2, 2, (n, 2))):
        with sdf.transform(angle=float(rng.uniform(-3, 3)), offset=p):
            shapes.append(
                sdf.Star([0, 0], 0.08, 5)
                if i % 2
                else sdf.Polygon([[0, 0], [0.1, 0], [0.05, 0.07]])
            )
    return sdf.union(shapes)


def _scenes(quick: bool):
    from fastsdf.shapes import scenes

    out = [("seed world", 1, lambda seed: scenes.seed_world())]
    sizes = (200, 1000) if quick else (200, 1000, 5000)
    for n in sizes:
        out.append((f"{n} boxes, `f = f \\| Box` loop", n, lambda seed, n=n: boxes_loop(n, seed)))
        out.append((f"{n} boxes, `union([...])`", n, lambda seed, n=n: boxes_list(n, seed)))
    out.append(
        (
            "1000 polygons (stars, triangles), `union([...])`",
            1000,
            lambda seed: polygons_list(1000, seed),
        )
    )
    for n in (200, 1000):
        out.append((f"mixed_scene({n})", n, lambda seed, n=n: scenes.mixed_scene(n, seed + 1)))
    return out


def measure(build, repeats: int = 3) -> dict:
    """Median CPU seconds of each step over ``repeats`` scenes built with seeds 1, 2, ...

    CPU time of this process (``time.process_time``): the steps are single-threaded Python
    and NumPy, so on an idle machine it is the wall time, and on a loaded one (other processes
    sharing the cores) it is far steadier than the wall time."""
    clock = time.process_time
    steps = {"build": [], "codegen": [], "plan": []}
    for seed in range(1, repeats + 1):
        t0 = clock()
        f = build(seed)
        steps["build"].append(clock() - t0)
        t0 = clock()
        f.compiled.module_source  # noqa: B018 - generates
        steps["codegen"].append(clock() - t0)
        if f.compiled.groups:
            t0 = clock()
            f.compiled.plan(((-3.0, 3.0), (-3.0, 3.0)))
            steps["plan"].append(clock() - t0)
        del f
    return {k: (float(np.median(v)) if v else None) for k, v in steps.items()}


def _ms(s):
    return "-" if s is None else f"{s * 1e3:.1f}"


def run(quick: bool = False) -> str:
    import fastsdf  # noqa: F401 - import cost is not part of the table
    from fastsdf.shapes import scenes

    scenes.mixed_scene(20)  # warm-up: first-call costs of the modelling layer
    boxes_list(20)
    load = os.getloadavg()[0]
    rows = []
    for name, n, build in _scenes(quick):
        r = measure(build, repeats=2 if quick else 3)
        total = sum(v for v in r.values() if v is not None)
        rows.append(
            [
                name,
                n,
                _ms(r["build"]),
                f"{r['build'] / n * 1e6:.0f}",
                _ms(r["codegen"]),
                _ms(r["plan"]),
                _ms(total),
            ]
        )
    head = [
        "scene",
        "primitives",
        "build (ms)",
        "build per primitive (us)",
        "codegen (ms)",
        "plan 32x32 (ms)",
        "total (ms)",
    ]
    return "\n".join(
        [
            "## Building scenes: the modelling DSL and the passes before the first evaluation",
            "",
            stamp(COMMAND) + f" Load average at start: {load:.1f}.",
            "",
            "CPU time of this process (single-threaded steps: the wall time on an idle machine), "
            "median over 3 scenes of each kind (other random constants each time), in one process "
            "after a warm-up; pure Python and NumPy, no numba compilation. "
            "'codegen': the generated "
            "module's source (`f.compiled.module_source`); "
            "'plan': the pruning plan over [-3, 3]^2 in 32 x 32 tiles (scenes with loops over "
            "tables only).",
            "",
            table(head, rows),
            "",
        ]
    )


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(
        prog=COMMAND, description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--quick", action="store_true", help="smaller scenes")
    args = parser.parse_args(argv)
    print(run(quick=args.quick))
    return 0


if __name__ == "__main__":
    sys.exit(main())
