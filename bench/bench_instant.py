"""The first answer of a new scene through each instant path, and through the default call.

    python -m bench.bench_instant       (QUICK=1: the seed and 20-box worlds only)

Fresh process per scene and path, empty kernel cache, warm installation cache (the
scene-independent kernels of ``fastsdf.backends.kernel.drive``, combine
programs included, compiled once before), fresh random constants per process. Seconds for
``import fastsdf``, for building the scene, and from the built scene to the first answer of 1e5
points (value + gradient) through:

* ``numpy``: the NumPy path (the op table's reference formulas, no numba);
* ``kernel``: the scene's compiled kernel, cold (for scenes of more than a few hundred nodes its
  block code is a fold function plus a combine program run by the interpreter of
  ``fastsdf.backends.kernel.drive``: the column says which);
* ``default``: ``f(x, y, compute_gradient=True)`` with no backend named (``Function.backend``).

The combine-program interpreter is not an instant path on its own: it runs a program over the
values of the scene's fold function, which numba compiles per scene, so its first answer is the
kernel column of the scenes marked *program*.
"""

from __future__ import annotations

import json
import os
import shutil
import tempfile

from .common import FRESH_SCENE, HERE, run_fresh_process, stamp, table

COMMAND = "python -m bench.bench_instant"

_SCRIPT = (
    r"""
import json, sys, time
t0 = time.perf_counter()
import numpy as np
import fastsdf as sdf
t_import = time.perf_counter() - t0
"""
    + FRESH_SCENE
    + r"""p = np.random.default_rng(1).uniform(-2, 2, (2, 100_000))
t0 = time.perf_counter()
f = scene(KIND, SEED)
t_build = time.perf_counter() - t0
t0 = time.perf_counter()
if BACKEND == "default":
    d, g = f(p[0], p[1], compute_gradient=True)
else:
    d, g = f(p[0], p[1], compute_gradient=True, backend=BACKEND)
t_first = time.perf_counter() - t0
out = dict(import_s=t_import, build_s=t_build, first_s=t_first,
           default=type(f).backend if hasattr(type(f), "backend") else "kernel")
if BACKEND == "kernel":
    out["program"] = "_PROG_VG" in f.compiled.module_source
print(json.dumps(out))
"""
)

#: (kind, label) of the scenes; the first two are the quick set.
SCENES = [
    ("seed", "seed world"),
    ("box20", "20-box world"),
    ("circles200", "hard union of 200 circles"),
    ("mixed", "mixed ops, 200 primitives"),
    ("hard1000", "hard union of 1000 boxes"),
    ("hard5000", "hard union of 5000 boxes"),
]
PATHS = ("numpy", "kernel", "default")


def _fresh(kind: str, backend: str, seed: int, cache: str) -> dict:
    shutil.rmtree(cache, ignore_errors=True)  # an empty kernel cache
    code = _SCRIPT.replace("KIND_", kind).replace("BACKEND_", backend).replace("SEED_", str(seed))
    return json.loads(run_fresh_process(code, env={"FASTSDF_CACHE_DIR": cache}).split("\n")[-2])


def run(quick: bool = False) -> str:
    load = os.getloadavg()
    scenes = SCENES[:2] if quick else SCENES
    cache = tempfile.mkdtemp(prefix="fastsdf-instant-bench-")
    rows = []
    try:
        # warm the installation cache: the scene-independent kernels
        for kind, _ in scenes:
            _fresh(kind, "kernel", 999, cache)
        seed = int.from_bytes(os.urandom(3), "little")
        for kind, label in scenes:
            res = {}
            for backend in PATHS:
                seed += 1
                res[backend] = _fresh(kind, backend, seed, cache)
            d = res["default"]
            kernel = f"{res['kernel']['first_s']:.2f}" + (
                " (program)" if res["kernel"].get("program") else ""
            )
            rows.append(
                [
                    label,
                    f"{d['import_s']:.2f}",
                    f"{d['build_s']:.3f}",
                    f"{res['numpy']['first_s']:.3f}",
                    kernel,
                    f"**{d['first_s']:.3f}** ({d['default']})",
                    f"{d['build_s'] + d['first_s']:.2f}",
                ]
            )
    finally:
        shutil.rmtree(cache, ignore_errors=True)
    load2 = os.getloadavg()
    text = "\n".join(
        [
            "## The instant paths: a new scene's first answer",
            "",
            stamp(COMMAND) + f" Load average (1, 5, 15 min) before: {load[0]:.2f}, {load[1]:.2f}, "
            f"{load[2]:.2f}; after: {load2[0]:.2f}, {load2[1]:.2f}, {load2[2]:.2f}.",
            "",
            "One fresh process per scene and path, empty kernel cache, warm installation cache, "
            "fresh random constants; seconds from the built scene to the answer of 1e5 random "
            "points in [-2, 2]^2, value + gradient. *Default*: no backend named "
            "(`Function.backend` in brackets); *from import*: construction + default answer.",
            "",
            table(
                [
                    "new scene",
                    "import fastsdf (s)",
                    "construction (s)",
                    "NumPy (s)",
                    "kernel, cold (s)",
                    "default call (s)",
                    "from import (s)",
                ],
                rows,
            ),
            "",
        ]
    )
    path = os.path.join(HERE, "results", "instant.md")
    os.makedirs(os.path.dirname(path), exist_ok=True)
    with open(path, "w") as fh:
        fh.write(text)
    return text


if __name__ == "__main__":
    print(run(quick=bool(os.environ.get("QUICK"))))
