"""Shared helpers for benchmark sections: timing, machine facts, markdown tables, progress.

Every speed figure in fastsdf's docs is a median of repeats after warm-up, measured side by side
with its baseline in the same process (absolute times drift on shared machines; ratios hold).
"""

from __future__ import annotations

import datetime
import os
import platform
import subprocess
import sys
import time

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))


def timeit(fn, *args, repeats: int = 5, warmup: int = 1, min_time: float = 0.0):
    """Run ``fn(*args)`` ``warmup`` times, then ``repeats`` times (more if ``min_time`` seconds
    have not passed). Returns ``(median_seconds, spread)`` where spread is (max-min)/median."""
    for _ in range(warmup):
        fn(*args)
    times = []
    start = time.perf_counter()
    while len(times) < repeats or (time.perf_counter() - start) < min_time:
        t0 = time.perf_counter()
        fn(*args)
        times.append(time.perf_counter() - t0)
        if len(times) > 1000:
            break
    times = np.asarray(times)
    med = float(np.median(times))
    return med, float((times.max() - times.min()) / med) if med > 0 else 0.0


def fmt_rate(per_second: float, unit: str = "") -> str:
    """Human-readable rate, e.g. '41.3 M'."""
    for scale, suffix in ((1e9, "G"), (1e6, "M"), (1e3, "k")):
        if per_second >= scale:
            return f"{per_second / scale:.3g} {suffix}{unit}"
    return f"{per_second:.3g} {unit}"


def table(headers, rows) -> str:
    """A markdown table."""
    out = ["| " + " | ".join(headers) + " |", "|" + "|".join(" --- " for _ in headers) + "|"]
    for row in rows:
        out.append("| " + " | ".join(str(c) for c in row) + " |")
    return "\n".join(out)


def machine_info() -> dict:
    """Facts every results table is stamped with."""
    import numba

    cpu = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo") as fh:
            for line in fh:
                if line.startswith("model name"):
                    cpu = line.split(":", 1)[1].strip()
                    break
    except OSError:
        pass
    return {
        "date": datetime.date.today().isoformat(),
        "cores": os.cpu_count(),
        "cpu": cpu,
        "python": platform.python_version(),
        "numpy": np.__version__,
        "numba": numba.__version__,
        "numba_threads": numba.get_num_threads(),
    }


def stamp(command: str) -> str:
    """A line saying how and where a table was produced."""
    m = machine_info()
    return (
        f"_Command: `{command}`; {m['date']}; {m['cores']} cores ({m['cpu']}); "
        f"Python {m['python']}, numpy {m['numpy']}, numba {m['numba']}._"
    )


def run_fresh_process(code: str, env: dict | None = None, timeout: float = 600) -> str:
    """Run ``code`` in a fresh Python process (for cold compile timings); returns its stdout."""
    full_env = dict(os.environ)
    full_env.update(env or {})
    repo = os.path.dirname(HERE)
    full_env["PYTHONPATH"] = repo + os.pathsep + full_env.get("PYTHONPATH", "")
    res = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, env=full_env, timeout=timeout
    )
    if res.returncode != 0:
        raise RuntimeError(f"fresh process failed:\n{res.stderr[-3000:]}")
    return res.stdout


from fastsdf.viz.progress import Progress  # noqa: E402,F401 - re-exported for sections

# The scenes of the first-answer benchmarks, built with fresh constants in a child process's
# script (bench_instant): KIND_ and SEED_ are filled in by the caller.
FRESH_SCENE = r"""
from fastsdf.shapes.scenes import box_world, mixed_scene
from bench.bench_prune import hard_union
KIND, BACKEND, SEED = "KIND_", "BACKEND_", SEED_
def scene(kind, seed):
    rng = np.random.default_rng(seed)
    if kind == "seed":  # the seed world with fresh constants
        f = sdf.Halfspace([0, 1], -1.8 + rng.uniform(-1e-3, 1e-3)) | sdf.Halfspace([1, 1], -1.8) \
            | sdf.Halfspace([-1, 1], -1.8)
        with sdf.smoothness(10):
            f |= sdf.Circle([0, rng.uniform(-0.1, 0.1)], 0.5) & sdf.Halfspace([0.1, 1], 0.3)
        return f
    if kind == "box20":
        return box_world(20, seed)
    if kind == "circles200":
        f = sdf.Circle(rng.uniform(-2, 2, 2), 0.1)
        for _ in range(199):
            f = f | sdf.Circle(rng.uniform(-2, 2, 2), rng.uniform(0.05, 0.2))
        return f
    if kind == "mixed":
        return mixed_scene(200, seed)
    return hard_union(int(kind[4:]), seed=seed)
"""
