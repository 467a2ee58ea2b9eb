"""Hashes of the evaluators' results: the safety net of changes that must keep every bit.

    python -m bench.results_hash                      # print the table of hashes
    python -m bench.results_hash --out hashes.json    # also write them
    python -m bench.results_hash --compare hashes.json --keep /tmp/sources

Each scene is evaluated at the same points (random ones over the scene, exact zeros, huge and
tiny coordinates, NaN and infinities) on every path that should give the same bits from one
revision to the next: the kernel serial and parallel, value alone and with the gradient, pruned
where the scene has loops over tables, with parameters and time (and dd/dt), the per-point
functions called one point at a time, the NumPy reference, and the CUDA target under
numba-cuda's simulator (``--no-cuda`` leaves it out). ``--compare`` names the entries whose
hash changed and exits 1 if any did; ``--keep`` writes each scene's generated modules into a
folder, for diffing two revisions' code (the sources may change; the hashes may not).
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import sys

import numpy as np

POINTS = 6000  # above the kernels' parallel threshold (4096)
SERIAL = 1000
PER_POINT = 200
CUDA_POINTS = 96


def scenes() -> dict:
    """``{name: (function, call parameters)}``: at least one scene for every form the generated
    code takes (straight lines, loops over tables, folded blocks, combine programs, left folds,
    primitives with their own algorithm, every operation, parameters and time)."""
    import fastsdf as sdf
    from fastsdf.shapes.scenes import box_world, mixed_scene, seed_world

    rng = np.random.default_rng(7)
    hard = sdf.union(
        [
            sdf.Box(-rng.uniform(0.02, 0.08, 2), rng.uniform(0.02, 0.08, 2)).rotate(a).translate(o)
            for a, o in zip(rng.uniform(-3, 3, 1000), rng.uniform(-2.4, 2.4, (1000, 2)))
        ]
    )
    circles = sdf.union(
        [
            sdf.Circle(c, r)
            for c, r in zip(rng.uniform(-2, 2, (200, 2)), rng.uniform(0.05, 0.2, 200))
        ]
    )
    with sdf.smoothness(0.3, kind="quadratic"):
        poly = sdf.Circle([0.0, 0.0], 0.6)
        for c in rng.uniform(-1.5, 1.5, (6, 2)):
            poly |= sdf.Circle(c, 0.25)
    with sdf.smoothness(0.2, kind="cubic"):
        poly &= sdf.Box([-1.8, -1.8], [1.8, 1.8])
    prims = (
        sdf.Ellipse([0.3, -0.2], [0.8, 0.4])
        | sdf.Polygon([[-1.5, -1.0], [-0.5, -1.2], [-0.8, 0.2], [-1.3, 0.1], [-1.0, -0.4]])
        | sdf.Star([1.0, 1.0], 0.5, 5, 0.2)
        | sdf.Arc([-1.0, 1.0], 0.5, 1.0, 0.05)
    )
    ops = (
        sdf.Ring([0.0, 0.0], 1.0, 0.2).round(0.05)
        | sdf.Capsule([-1.0, -1.0], [1.0, -0.5], 0.1).shell(0.02)
        | sdf.Triangle([-2, 1], [-1, 2], [-1.5, 1.0]).mirror("x")
        | sdf.Circle([0.0, 0.0], 0.1).repeat(0.5, (4, 3)).translate([-1.0, -2.0])
        | sdf.RoundedBox([0.5, 0.5], [1.5, 1.2], 0.1).scale(0.8)
    )
    angle = sdf.Param("angle", 0.4)
    lift = sdf.Param("y0", -0.5) + sdf.Param("u", 0.3) * sdf.t
    with sdf.transform(angle=angle, offset=[0.2, lift]):
        bar = sdf.Box([-1.0, -0.05], [1.0, 0.05])
    with sdf.smoothness(sdf.Param("k", 8.0)):
        moving = seed_world() | bar | sdf.Ellipse([0.5, 0.5], [0.3 + 0.1 * sdf.t, 0.2])
    timed = sdf.Circle([0.0, 0.0], 0.5).translate([0.0, 0.2 * sdf.t]) | sdf.Halfspace([0, 1], -1.5)
    out = {
        "seed world": (seed_world(), {}),
        "20 boxes (smooth loops)": (box_world(20), {}),
        "200 boxes (smooth loops)": (box_world(197), {}),
        "1000 boxes (hard union, pruned)": (hard, {}),
        "200 circles (hard union)": (circles, {}),
        "50 mixed primitives (combine program)": (mixed_scene(50), {}),
        "60 mixed primitives, shell (folded blocks)": (mixed_scene(60).shell(0.02), {}),
        "mixed and looped (folded blocks, loops)": (mixed_scene(40) | box_world(20), {}),
        "200 mixed primitives (combine program)": (mixed_scene(200), {}),
        "polynomial blends (left folds)": (poly, {}),
        "primitives with their own algorithm": (prims, {}),
        "modifiers (round, shell, mirror, repeat, scale)": (ops, {}),
        "parameters and time": (moving, {"t": 0.7, "angle": 0.9, "k": 6.0}),
        "time alone": (timed, {"t": 1.3}),
    }
    return out


def points(n: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """``n`` points: random ones over [-2.5, 2.5]^2, then the hard ones (origin, a coordinate on
    the axis, huge and tiny, NaN and infinities) written over the first few."""
    rng = np.random.default_rng(seed)
    x, y = rng.uniform(-2.5, 2.5, (2, n))
    hard = [
        (0.0, 0.0),
        (0.0, -1.8),
        (1e-160, -1e-160),
        (1e150, 2.0),
        (-3e200, 1e200),
        (np.nan, 0.0),
        (0.0, np.inf),
        (-np.inf, np.nan),
        (5e-324, 0.5),
    ]
    for i, (a, b) in enumerate(hard):
        x[i], y[i] = a, b
    return x, y


def _digest(*arrays) -> str:
    h = hashlib.sha256()
    for a in arrays:
        h.update(np.ascontiguousarray(np.asarray(a, dtype=np.float64)).tobytes())
    return h.hexdigest()[:16]


def hash_scene(f, params: dict, cuda: bool) -> dict:
    """``{path: hash}`` of one scene."""
    out: dict[str, str] = {}
    x, y = points(POINTS)
    xs, ys = x[:SERIAL], y[:SERIAL]
    for label, (px, py) in (("serial", (xs, ys)), ("parallel", (x, y))):
        out[f"kernel {label} v"] = _digest(f(px, py, backend="kernel", **params))
        out[f"kernel {label} vg"] = _digest(
            *f(px, py, compute_gradient=True, backend="kernel", **params)
        )
    if params:
        out["kernel dd/dt"] = _digest(
            *f(x, y, compute_gradient=True, time_derivative=True, backend="kernel", **params)
        )
    elif f.compiled.groups:
        out["kernel pruned v"] = _digest(f(x, y, prune=True, backend="kernel"))
        out["kernel pruned vg"] = _digest(
            *f(x, y, compute_gradient=True, prune=True, backend="kernel")
        )
    pv, pvg = f.point_value_fn, f.point_fn
    extra: tuple = ()
    if f.compiled.parametric:
        extra = (float(params.get("t", 0.0)), f.param_tuple(**params))
    px, py = x[:PER_POINT], y[:PER_POINT]
    out["per point v"] = _digest([pv(a, b, *extra) for a, b in zip(px, py)])
    out["per point vg"] = _digest([pvg(a, b, *extra) for a, b in zip(px, py)])
    out["numpy v"] = _digest(f(xs, ys, backend="numpy", **params))
    out["numpy vg"] = _digest(*f(xs, ys, compute_gradient=True, backend="numpy", **params))
    if cuda:
        cx, cy = x[:CUDA_POINTS], y[:CUDA_POINTS]
        res = f(cx, cy, compute_gradient=True, backend="cuda", **params)
        out["cuda vg"] = _digest(*res)
        if params:
            out["cuda dd/dt"] = _digest(
                *f(cx, cy, compute_gradient=True, time_derivative=True, backend="cuda", **params)
            )
    return out


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m bench.results_hash",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--out", help="write the hashes (JSON) to this file")
    parser.add_argument("--compare", help="compare with the hashes (JSON) in this file")
    parser.add_argument("--keep", help="write each scene's generated modules into this folder")
    parser.add_argument("--no-cuda", action="store_true", help="leave out the CUDA target")
    parser.add_argument("--only", nargs="+", help="scenes whose name starts with one of these")
    args = parser.parse_args(argv)
    cuda = not args.no_cuda
    if cuda:
        os.environ.setdefault("NUMBA_ENABLE_CUDASIM", "1")
    import warnings

    warnings.filterwarnings("ignore", category=RuntimeWarning)  # the simulator's NumPy scalars
    hashes: dict[str, dict] = {}
    for name, (f, params) in scenes().items():
        if args.only and not any(name.startswith(o) for o in args.only):
            continue
        hashes[name] = hash_scene(f, params, cuda)
        print(f"{name}: {len(hashes[name])} paths", file=sys.stderr)
        if args.keep:
            os.makedirs(args.keep, exist_ok=True)
            stem = os.path.join(args.keep, "".join(c if c.isalnum() else "_" for c in name))
            with open(stem + ".py", "w") as fh:
                fh.write(f.compiled.module_source)
            if cuda:
                with open(stem + "_cuda.py", "w") as fh:
                    fh.write(f.compiled.cuda.source)
    for name, paths in hashes.items():
        print(name)
        for path, h in paths.items():
            print(f"    {path:22s} {h}")
    if args.out:
        with open(args.out, "w") as fh:
            json.dump(hashes, fh, indent=1)
    if args.compare:
        with open(args.compare) as fh:
            before = json.load(fh)
        changed = [
            f"{name}: {path}"
            for name, paths in hashes.items()
            for path, h in paths.items()
            if before.get(name, {}).get(path) not in (None, h)
        ]
        missing = [
            f"{name}: {path}"
            for name, paths in before.items()
            if name in hashes
            for path in paths
            if path not in hashes[name]
        ]
        for line in changed:
            print(f"CHANGED {line}")
        for line in missing:
            print(f"MISSING {line}")
        print(f"{len(changed)} changed, {len(missing)} missing of {sum(map(len, hashes.values()))}")
        return 1 if changed or missing else 0
    return 0


if __name__ == "__main__":
    sys.exit(main())
