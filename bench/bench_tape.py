"""The tape interpreter against the compiled kernels: cost per point, and time to first answer.

    python -m bench.bench_tape          (or: python -m bench --only tape)

1. Points/s, value + gradient, 1e6 points (2 threads): the scene's compiled kernel
   (``backend='kernel'``, pruning off) and the tape (``backend='tape'``), timed in alternating
   rounds in one process, for the seed world, the 20-box world and two 200-primitive scenes.
2. A new scene in a fresh process with an empty kernel cache and a warm installation cache (the
   tape interpreter and the scene-independent kernels compiled once before): seconds from the end
   of ``import fastsdf`` to the first answer of 1e5 points (value + gradient), through the tape,
   through the compiled kernel (cold), and with ``backend='auto'`` (the tape answers while the
   kernel compiles in a background thread): what a caller's 1e5-point call costs while that
   thread compiles, against the same call with no compilation going on, and when the kernel is
   ready. The scenes get fresh random constants per process (never in any cache).
"""

from __future__ import annotations

import json
import os
import shutil
import tempfile

import numpy as np

from fastsdf.scenes import box_world, mixed_scene, seed_world

from .common import HERE, fmt_rate, run_fresh_process, stamp, table, timeit

COMMAND = "python -m bench.bench_tape"


def _scenes(quick: bool = False):
    scenes = [("seed world", seed_world()), ("20-box world", box_world(20))]
    if not quick:  # the 200-primitive scenes compile for a minute and more
        scenes += [("200-primitive world (box_world(197))", box_world(197)),
                   ("mixed ops, 200 primitives", mixed_scene(200))]
    return scenes


def _per_point(quick: bool) -> str:
    n = 200_000 if quick else 1_000_000
    p = np.random.default_rng(0).uniform(-2, 2, (2, n))
    rows = []
    for name, f in _scenes(quick):
        f(p[0][:5000], p[1][:5000], compute_gradient=True, prune=False)  # compile
        f(p[0][:10], p[1][:10], backend="tape")
        tape = f.compiled.tape
        kt, tt, ks, ts = [], [], [], []
        for _ in range(3):  # alternating rounds
            t, s = timeit(lambda: f(p[0], p[1], compute_gradient=True, prune=False), repeats=3)
            kt.append(t)
            ks.append(s)
            t, s = timeit(lambda: f(p[0], p[1], compute_gradient=True, backend="tape"),
                          repeats=3)
            tt.append(t)
            ts.append(s)
        k, t = float(np.median(kt)), float(np.median(tt))
        rows.append([name, f"{len(tape)} / {tape.nreg}", fmt_rate(n / k), fmt_rate(n / t),
                     f"{t / k:.1f}x", f"{k / n * 1e9:.0f} / {t / n * 1e9:.0f}",
                     f"{max(ks):.0%} / {max(ts):.0%}"])
    return table(["scene", "tape: instructions / registers", "kernel points/s",
                  "tape points/s", "tape slower by", "ns per point (kernel / tape)",
                  "spread (kernel / tape)"], rows)


_FIRST = r"""
import json, sys, time
t0 = time.perf_counter()
import numpy as np
import fastsdf as sdf
t_import = time.perf_counter() - t0
from fastsdf.scenes import mixed_scene
SEED = int(sys.argv[1]) if len(sys.argv) > 1 else 0
def scene(kind, seed):
    rng = np.random.default_rng(seed)
    if kind == "seed":  # the seed world with fresh constants
        f = sdf.Halfspace([0, 1], -1.8 + rng.uniform(-1e-3, 1e-3)) | sdf.Halfspace([1, 1], -1.8) \
            | sdf.Halfspace([-1, 1], -1.8)
        with sdf.smoothness(10):
            f |= sdf.Circle([0, rng.uniform(-0.1, 0.1)], 0.5) & sdf.Halfspace([0.1, 1], 0.3)
        return f
    return mixed_scene(200, seed)
KIND, BACKEND, SEED = "KIND_", "BACKEND_", SEED_
p = np.random.default_rng(1).uniform(-2, 2, (2, 100_000))
t0 = time.perf_counter()
f = scene(KIND, SEED)
if BACKEND == "setup":  # the same, split: one point first (numba's one-time setup), then 1e5
    f(p[0][:1], p[1][:1], compute_gradient=True, backend="tape")
    t_setup = time.perf_counter() - t0
    BACKEND = "tape"
d, g = f(p[0], p[1], compute_gradient=True, backend=BACKEND)
t_first = time.perf_counter() - t0
out = dict(import_s=t_import, first_s=t_first)
if "t_setup" in globals():
    out["setup_s"] = t_setup
if BACKEND == "tape":
    calls = []
    for _ in range(8):
        t1 = time.perf_counter()
        f(p[0], p[1], compute_gradient=True, backend="tape")
        calls.append(time.perf_counter() - t1)
    out["call_s"] = float(np.median(calls))
if BACKEND == "auto":
    calls = []
    while not f.compiled.kernel_ready:
        t1 = time.perf_counter()
        f(p[0], p[1], compute_gradient=True, backend="auto")
        calls.append(time.perf_counter() - t1)
    out["ready_s"] = time.perf_counter() - t0
    out["calls_during"] = len(calls)
    out["call_s"] = float(np.median(calls[:-1] or calls)) if calls else float("nan")
    t1 = time.perf_counter()
    f(p[0], p[1], compute_gradient=True, backend="auto")
    out["after_s"] = time.perf_counter() - t1
print(json.dumps(out))
"""


def _first_answer(quick: bool) -> str:
    code = _FIRST
    cache = tempfile.mkdtemp(prefix="fastsdf-tape-bench-")
    rows = []
    try:
        env = {"FASTSDF_CACHE_DIR": cache}
        # warm the installation cache: the tape interpreter and the scene-independent kernels
        for backend in ("tape", "kernel"):
            run_fresh_process(code.replace("KIND_", "seed").replace("BACKEND_", backend)
                              .replace("SEED_", "999"), env=env)
        seed = int.from_bytes(os.urandom(3), "little")
        scenes = [("seed", "seed world (new constants)")]
        if not quick:  # a cold 200-primitive kernel alone takes 20 s or more
            scenes.append(("mixed", "mixed ops, 200 primitives (new constants)"))
        for kind, label in scenes:
            res = {}
            for backend in ("tape", "setup", "kernel", "auto"):
                seed += 1
                shutil.rmtree(cache, ignore_errors=True)  # an empty kernel cache
                res[backend] = json.loads(run_fresh_process(
                    code.replace("KIND_", kind).replace("BACKEND_", backend)
                    .replace("SEED_", str(seed)), env={"FASTSDF_CACHE_DIR": cache}))
            a = res["auto"]
            rows.append([label, f"{res['tape']['import_s']:.2f}",
                         f"{res['tape']['first_s']:.2f}",
                         f"{res['setup']['setup_s']:.2f} + "
                         f"{res['setup']['first_s'] - res['setup']['setup_s']:.2f}",
                         f"{res['kernel']['first_s']:.2f}",
                         f"{a['first_s']:.2f}",
                         f"{res['tape']['call_s'] * 1e3:.0f} / {a['call_s'] * 1e3:.0f} "
                         f"({a['calls_during']} calls)",
                         f"{a['ready_s']:.2f}", f"{a['after_s'] * 1e3:.1f}"])
    finally:
        shutil.rmtree(cache, ignore_errors=True)
    return table(["new scene", "import fastsdf (s)", "first answer, tape (s)",
                  "split: scene + numba's setup + 1e5-point tape call (s)",
                  "first answer, kernel, cold (s)", "first answer, auto (s)",
                  "1e5-point call, tape alone / auto while compiling (ms)",
                  "auto: kernel ready after (s)", "auto: call after switch (ms)"], rows)


def run(quick: bool = False) -> str:
    load = os.getloadavg()
    first = _first_answer(quick)
    per = _per_point(quick)
    load2 = os.getloadavg()
    text = "\n".join([
        "## Tape interpreter: no wait for a new scene", "",
        stamp(COMMAND) + f" Load average (1, 5, 15 min) before: {load[0]:.2f}, {load[1]:.2f}, "
        f"{load[2]:.2f}; after: {load2[0]:.2f}, {load2[1]:.2f}, {load2[2]:.2f}.", "",
        "Time from the end of `import fastsdf` to the first answer of 1e5 points (value + "
        "gradient) of a new scene, fresh process, empty kernel cache, warm installation cache "
        "(the tape interpreter and the scene-independent kernels compiled once before). The "
        "first numba call of a process also pays numba's one-time setup (it imports "
        "scipy.linalg when SciPy is installed), whichever backend answers.", "",
        first, "",
        "Cost per point, value + gradient, 1e6 points, 2 threads, kernel (pruning off) and tape "
        "in alternating rounds:", "",
        per, ""])
    path = os.path.join(HERE, "results", "tape.md")
    os.makedirs(os.path.dirname(path), exist_ok=True)
    with open(path, "w") as fh:
        fh.write(text)
    return text


if __name__ == "__main__":
    print(run(quick=bool(os.environ.get("QUICK"))))
