"""How much a simulation slows down when it shares the machine.

    python -m bench.busy_machine                 # 5 runs of each workload in each setting
    python -m bench.busy_machine --quick         # small sizes, 2 runs: checks that it works
    python -m bench.busy_machine --only grains5k --runs 7 --threads 1

Workloads (each in its own process, with numba's default threads unless ``--threads``):

- ``grains5k``: a bed of 5,000 grains of radius 2 mm with history and rolling friction under
  gravity (0, -9.81) (the law's stiffness derived), 100 x 50 on a hexagonal lattice on a
  floor, x periodic (``--quick``: 1,000 grains);
- ``grains1e5``: the same bed with 1e5 grains, 447 x 224 (``--quick``: 5,000);
- ``particles``: ``ParticleSimulation`` on the seed world's 400 x 400 grid under gravity, 1e6
  particles (``--quick``: 1e4).

Settings: ``alone``; ``busy loop``, beside a process that spins one core (``while True:
pass``); ``second run``, beside a second process running the same workload (a sweep of two
runs); and for ``particles``, ``grain run``, beside the ``grains5k`` workload. Each run builds
and warms its simulation (and the companion its own, before the measured run starts), then
steps it for ``--seconds`` (whole blocks) and reports its rate in work per second. The runs of
the settings alternate, so slow phases of the machine fall on all of them. Printed: each
setting's rates, and the slowdown of each run against the median rate alone (a fair share of a
2-core machine beside a second 2-thread run is 2x).
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys

HERE = os.path.dirname(os.path.abspath(__file__))
REPO = os.path.dirname(HERE)

# argv: [json of (workload, size, seconds, loop)]. Prints {"rate", "unit"} after stepping for
# `seconds`; with `loop`, prints "ready" after its warm-up and steps until killed.
WORKER = r"""
import json, math, sys, time
import numpy as np
import fastsdf as fs

workload, size, seconds, loop = json.loads(sys.argv[1])
if workload == "particles":
    import fastsdf.particles as phys
    from fastsdf.shapes.scenes import seed_world

    fs.Function.backend = "kernel"
    g = fs.GridSDF(seed_world(), bounds=[(-2, 2), (-2, 2)], samples=[400j, 400j])
    np.random.seed(0)
    sim = phys.ParticleSimulation(g, n=size, timestep=1 / 30)
    sim.force_generators.append(phys.Gravity())
    sim.run(30)
    steps = 5

    def block():
        sim.run(steps)
        return size * steps

    unit = "M particle-steps/s"
else:
    from fastsdf.granular import ContactLaw, GranularSimulation

    r = 0.002
    cols = round(math.sqrt(2 * size))
    rows = -(-size // cols)
    j, i = np.divmod(np.arange(size), cols)
    pos = np.stack([(i + 0.5 * (j % 2)) * 1.98 * r, r + j * 1.98 * r * math.sqrt(3) / 2], 1)
    sim = GranularSimulation(
        fs.Halfspace((0.0, 1.0), 0.0), positions=pos, radius=r,
        contacts=ContactLaw(history=True, rolling_friction=0.1), gravity=(0.0, -9.81),
        periodic_x=(0.0, cols * 1.98 * r),
    )
    substeps = max(20, 2_000_000 // size)
    sim.advance(substeps)

    def block():
        sim.advance(substeps)
        return size * substeps

    unit = "M grain-substeps/s"
block()
if loop:
    print("ready", flush=True)
    while True:
        block()
work = 0
t0 = time.perf_counter()
while True:
    work += block()
    elapsed = time.perf_counter() - t0
    if elapsed >= seconds:
        break
print(json.dumps({"rate": work / elapsed / 1e6, "unit": unit}))
"""

BUSY = "while True:\n    pass\n"

SIZES = {"grains5k": (5_000, 1_000), "grains1e5": (100_000, 5_000), "particles": (10**6, 10**4)}
SETTINGS = ("alone", "busy loop", "second run")


def _env(threads: int | None) -> dict:
    env = dict(os.environ, PYTHONPATH=REPO, MPLBACKEND="Agg")
    if threads is not None:
        env["NUMBA_NUM_THREADS"] = str(threads)
    return env


def _worker(args: list, env: dict, **kw: object) -> subprocess.Popen:
    return subprocess.Popen(
        [sys.executable, "-c", WORKER, json.dumps(args)], env=env, cwd=REPO, text=True, **kw
    )  # type: ignore[call-overload]


def measure(workload: str, sizes: dict, seconds: float, setting: str, env: dict) -> dict:
    """One run of ``workload`` (of ``sizes[workload]``) in ``setting``: its rate and unit."""
    size = sizes[workload]
    companion = None
    if setting == "busy loop":
        companion = subprocess.Popen([sys.executable, "-c", BUSY])
    elif setting in ("second run", "grain run"):
        other = workload if setting == "second run" else "grains5k"
        companion = _worker([other, sizes[other], seconds, True], env, stdout=subprocess.PIPE)
        assert companion.stdout is not None
        if companion.stdout.readline().strip() != "ready":
            raise RuntimeError(f"the companion run of {other} failed")
    try:
        run = _worker([workload, size, seconds, False], env, stdout=subprocess.PIPE)
        out, _ = run.communicate()
        if run.returncode:
            raise RuntimeError(f"the run of {workload} ({setting}) failed")
        return json.loads(out.strip().splitlines()[-1])
    finally:
        if companion is not None:
            companion.kill()
            companion.wait()


def main(argv: list | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m bench.busy_machine",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--only", nargs="+", choices=list(SIZES), default=list(SIZES))
    parser.add_argument("--runs", type=int, default=None, help="runs per setting (5; quick 2)")
    parser.add_argument("--seconds", type=float, default=None, help="per run (3; quick 0.5)")
    parser.add_argument("--threads", type=int, default=None, help="numba threads of each run")
    parser.add_argument("--quick", action="store_true", help="small sizes: check it works")
    args = parser.parse_args(argv)
    runs = args.runs or (2 if args.quick else 5)
    seconds = args.seconds or (0.5 if args.quick else 3.0)
    env = _env(args.threads)
    load = os.getloadavg()[0]
    threads = args.threads or "numba's default"
    print(f"busy machine: {os.cpu_count()} cores, load {load:.1f}, threads {threads}, {runs} runs")
    sizes = {w: SIZES[w][1 if args.quick else 0] for w in SIZES}
    for workload in args.only:
        settings = SETTINGS + (("grain run",) if workload == "particles" else ())
        rates: dict = {s: [] for s in settings}
        unit = ""
        for _ in range(runs):
            for setting in settings:
                res = measure(workload, sizes, seconds, setting, env)
                rates[setting].append(res["rate"])
                unit = res["unit"]
        alone = statistics.median(rates["alone"])
        print(f"\n{workload} ({sizes[workload]:,}), {unit}; median alone {alone:.3g}")
        for setting in settings:
            slow = ", ".join(f"{alone / r:.2f}x" for r in rates[setting])
            each = ", ".join(f"{r:.3g}" for r in rates[setting])
            print(f"  {setting:>10}: {each}  (slowdown {slow})", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
