"""A/B of whole workloads: the fastsdf of another git revision against this checkout, each in
its own fresh processes, alternating, in one run.

    python -m bench.ab --rev 06cb1ff                       # every workload, 3 rounds
    python -m bench.ab --rev HEAD~5 --only seed box20 --rounds 5

The baseline revision is exported (``git archive``) into a temporary folder; each round runs
every workload once on the baseline and once on this checkout, each in a new interpreter with
its own warm kernel cache (a first, unmeasured round warms both caches), so both sides see the
same machine load. Reported: the median rate of each side and their ratio (this / baseline);
the workloads use only the public API both versions share.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tarfile
import tempfile

HERE = os.path.dirname(os.path.abspath(__file__))
REPO = os.path.dirname(HERE)

# Each workload prints one JSON object {"rate": ..., "unit": ...}; PREAMBLE finds the scenes
# module under either layout.
PREAMBLE = """
import json, time
import numpy as np
import fastsdf as sdf
try:
    from fastsdf.shapes.scenes import box_world, seed_world
except ImportError:
    from fastsdf.scenes import box_world, seed_world

def steady():
    # steady-state workloads run the compiled kernel (the default call may answer through
    # an interpreter while the kernel compiles)
    sdf.Function.backend = "kernel"


def best(fn, repeats=5):
    fn()
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter(); fn(); times.append(time.perf_counter() - t0)
    return min(times)
"""

# The dense bed of bench.bench_granular through the particle family's front door (the
# engine's own constructor changed its argument order between revisions; the family's did not).
GRAINS = """
import math
from fastsdf.particles import ContactLaw, ParticleSimulation
from fastsdf.granular import restitution_from_damping
cols = rows = 316
j, i = np.divmod(np.arange(rows * cols), cols)
pos = np.stack([(i + 0.5 * (j % 2)) * 0.99, 0.5 + j * 0.99 * math.sqrt(3) / 2], 1)
m = math.pi / 4
law = ContactLaw(2e5, restitution_from_damping(300.0, 2e5, m / 2), 0.5, 0.5, history={history})
wall = law._replace(restitution=restitution_from_damping(300.0, 2e5, m))
sim = ParticleSimulation(
    sdf.Halfspace((0.0, 1.0), 0.0), positions=pos, radius=0.5, contacts=law,
    wall_contacts=wall, timestep=1e-4, substep=1e-4, skin=0.2, periodic_x=(0.0, cols * 0.99),
)
sim.force_generators.append(__import__("fastsdf.particles", fromlist=["Gravity"]).Gravity())
sim.run(100)
t0 = time.perf_counter(); sim.run(200); dt = time.perf_counter() - t0
print(json.dumps({{"rate": len(pos) * 200 / dt / 1e6}}))
"""

# A bed of 5,000 grains of radius 2 mm with history and rolling friction under gravity 9.81,
# the law's stiffness derived (the user's defaults): 100 x 50 on a hexagonal lattice, pressing
# on its neighbours, x periodic; settles for one frame (1,927 substeps), then two are timed.
BED_5K = """
import math
from fastsdf.particles import ContactLaw, Gravity, ParticleSimulation
r, cols, rows = 0.002, 100, 50
j, i = np.divmod(np.arange(rows * cols), cols)
pos = np.stack([(i + 0.5 * (j % 2)) * 1.98 * r, r + j * 1.98 * r * math.sqrt(3) / 2], 1)
sim = ParticleSimulation(
    sdf.Halfspace((0.0, 1.0), 0.0), positions=pos, radius=r,
    contacts=ContactLaw(history=True, rolling_friction=0.1), periodic_x=(0.0, cols * 1.98 * r),
)
sim.force_generators.append(Gravity((0.0, -9.81)))
sim.run(1)
t0 = time.perf_counter(); sim.run(2); dt = time.perf_counter() - t0
print(json.dumps({"rate": len(pos) * sim.substeps_per_frame * 2 / dt / 1e6}))
"""

WORKLOADS = {
    "seed": (
        "exact seed world, value + gradient, 1e6 points",
        "M points/s",
        """
steady()
f = seed_world(); x, y = np.random.default_rng(0).uniform(-2, 2, (2, 1_000_000))
print(json.dumps({"rate": 1.0 / best(lambda: f(x, y, compute_gradient=True))}))
""",
    ),
    "box20": (
        "exact 20-box world, value + gradient, 1e6 points",
        "M points/s",
        """
steady()
f = box_world(20); x, y = np.random.default_rng(0).uniform(-2, 2, (2, 1_000_000))
print(json.dumps({"rate": 1.0 / best(lambda: f(x, y, compute_gradient=True))}))
""",
    ),
    "grid": (
        "GridSDF 400x400 of the seed world, value + gradient, 1e6 points",
        "M points/s",
        """
steady()
g = sdf.GridSDF(seed_world(), bounds=[(-2, 2), (-2, 2)], samples=[400j, 400j])
x, y = np.random.default_rng(0).uniform(-2, 2, (2, 1_000_000))
print(json.dumps({"rate": 1.0 / best(lambda: g(x, y, compute_gradient=True))}))
""",
    ),
    "union1000": (
        "hard union of 1000 small boxes (pruned per tile), value + gradient, 1e6 points",
        "M points/s",
        """
steady()
r = np.random.default_rng(5)
f = sdf.Halfspace([0, 1], -2.5)
for c, h in zip(r.uniform(-1.9, 1.9, (1000, 2)), r.uniform(0.01, 0.05, (1000, 2))):
    f = f | sdf.Box(c - h, c + h)
x, y = np.random.default_rng(0).uniform(-2, 2, (2, 1_000_000))
print(json.dumps({"rate": 1.0 / best(lambda: f(x, y, compute_gradient=True))}))
""",
    ),
    "particles": (
        "1e6 particles on the seed world's 400x400 grid, gravity, 60 steps after 240",
        "M particle-steps/s",
        """
steady()
import fastsdf.particles as phys
g = sdf.GridSDF(seed_world(), bounds=[(-2, 2), (-2, 2)], samples=[400j, 400j])
np.random.seed(0)
sim = phys.ParticleSimulation(g, n=1_000_000, timestep=1 / 30)
sim.force_generators.append(phys.Gravity())
sim.run(240)
t0 = time.perf_counter(); sim.run(60); dt = time.perf_counter() - t0
print(json.dumps({"rate": 60 / dt}))
""",
    ),
    "grains": (
        "dense bed of 1e5 discs (gran/hooke), 200 substeps after 100",
        "M grain-steps/s",
        GRAINS.format(history=False),
    ),
    "grains_history": (
        "the same bed with contact history (gran/hooke/history)",
        "M grain-steps/s",
        GRAINS.format(history=True),
    ),
    "grains5k": (
        "bed of 5,000 grains r = 2 mm, history + rolling friction, gravity 9.81, 2 frames",
        "M grain-steps/s",
        BED_5K,
    ),
    "first": (
        "first answer of a new 20-box world (fresh process, warm cache), 1e5 points",
        "s (lower is better)",
        """
t0 = time.perf_counter()
f = box_world(20); x, y = np.random.default_rng(1).uniform(-2, 2, (2, 100_000))
f(x, y, compute_gradient=True)
print(json.dumps({"rate": time.perf_counter() - t0}))
""",
    ),
}


def _export(rev: str, dest: str) -> str:
    """The package and bench of ``rev``, written under ``dest``."""
    tar = os.path.join(dest, "tree.tar")
    subprocess.run(["git", "-C", REPO, "archive", "--format=tar", "-o", tar, rev], check=True)
    with tarfile.open(tar) as tf:
        tf.extractall(os.path.join(dest, "tree"), filter="data")
    return os.path.join(dest, "tree")


def _run(tree: str, cache: str, code: str) -> float:
    env = dict(os.environ, PYTHONPATH=tree, FASTSDF_CACHE_DIR=cache, MPLBACKEND="Agg")
    res = subprocess.run(
        [sys.executable, "-c", PREAMBLE + code],
        env=env,
        cwd=tree,
        capture_output=True,
        text=True,
        timeout=1800,
    )
    if res.returncode:
        raise RuntimeError(f"workload failed in {tree}:\n{res.stderr[-2000:]}")
    return float(json.loads(res.stdout.strip().splitlines()[-1])["rate"])


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m bench.ab",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--rev", required=True, help="git revision of the baseline")
    parser.add_argument("--only", nargs="+", choices=list(WORKLOADS), default=list(WORKLOADS))
    parser.add_argument("--rounds", type=int, default=3)
    args = parser.parse_args(argv)
    if args.rounds < 1:
        parser.error(f"--rounds must be at least 1, got {args.rounds}")
    with tempfile.TemporaryDirectory(prefix="fastsdf_ab_") as tmp:
        base = _export(args.rev, tmp)
        sides = {
            "baseline": (base, os.path.join(tmp, "cache_base")),
            "this": (REPO, os.path.join(tmp, "cache_this")),
        }
        rates: dict = {(w, s): [] for w in args.only for s in sides}
        for rnd in range(args.rounds + 1):
            for w in args.only:
                for s, (tree, cache) in sides.items():
                    r = _run(tree, cache, WORKLOADS[w][2])
                    if rnd:  # round 0 warms the caches
                        rates[w, s].append(r)
        load = os.getloadavg()[0]
    print(f"A/B: this checkout against {args.rev}, {args.rounds} rounds, load {load:.1f}\n")
    print("| workload | unit | baseline | this | speed of this / baseline |")
    print("| --- | --- | --- | --- | --- |")
    for w in args.only:
        desc, unit, _ = WORKLOADS[w]
        med = {s: sorted(rates[w, s])[len(rates[w, s]) // 2] for s in sides}
        speed = med["baseline"] / med["this"] if "lower" in unit else med["this"] / med["baseline"]
        print(f"| {desc} | {unit} | {med['baseline']:.3g} | {med['this']:.3g} | {speed:.3f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
