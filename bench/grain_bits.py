"""Bit-identity of the granular engine against another revision's.

    python -m bench.grain_bits --rev 9af86bd
    python -m bench.grain_bits --rev 9af86bd --grains 6000 --threads 1 2 --devices cpu cuda

Each bed runs on both sides, each side in its own interpreter with its own fastsdf (the
baseline exported by ``git archive`` into a folder kept under the system's temporary folder,
so that its numba cache stays warm between runs), at each thread count asked for; the
arrays each side saves are compared bit for bit. The beds use only
``GranularSimulation``'s public surface, which both revisions share:

- ``hooke, grid world, periodic x``: ``gran/hooke`` (no history) on a GridSDF of a floor with
  a bump, x periodic;
- ``history + rolling, scene world, periodic x``: ``gran/hooke/history`` with rolling
  friction, between the grains and against the world (an exact scene: a floor and a disc);
- ``history, moving world``: history between the grains, none against the world, in a box
  whose floor rises (a world built with ``fastsdf.t``), x not periodic.

Discs of two kinds (half of radius 0.5, half between 0.35 and 0.5: both branches of the
dashpot's effective mass), started on a loose lattice with random velocities, falling under
gravity: 4 frames of 80 substeps, the velocities halved by ``set_state`` before the
last (a restart), several list rebuilds. Saved and compared: positions, velocities, angular
velocities, the world's force, time, rebuilds, the energies, contact counts, the neighbour
pairs and (with history) the tangential springs. With ``--threads 2`` and at least 4096
grains (the engine's ``PARALLEL_MIN_GRAINS``) the passes run on two threads.

``--devices cuda``: a small bed of each static world on ``device='cuda'`` under numba-cuda's
simulator (slow: ``--cuda-grains``, 200 by default, two frames).

``--compile-time``: instead, the cold compile of the granular kernels on each side (a fresh
``NUMBA_CACHE_DIR``; the world's own kernel compiled first, outside the figure): the CPU
seconds of building a 400-grain simulation on a floor, x periodic, and running two frames and
``energy()``, for ``gran/hooke`` and then ``gran/hooke/history`` with rolling friction (the
second reuses what the first compiled), ``--rounds`` times, alternating sides.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tarfile
import tempfile

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
REPO = os.path.dirname(HERE)

# Run in a fresh interpreter with the side's fastsdf first on the path:
# argv = [json of (case, grains, threads, device), output .npz]
WORKER = r"""
import json, math, sys
import numba
import numpy as np
import fastsdf as fs
from fastsdf.granular import ContactLaw, GranularSimulation

case, n, threads, device = json.loads(sys.argv[1])
numba.set_num_threads(threads)
rng = np.random.default_rng(7)
cols = max(int(math.sqrt(n) * 1.6), 8)
rows = -(-n // cols)
j, i = np.divmod(np.arange(n), cols)
pos = np.stack([0.6 + i * 1.08 + rng.uniform(-0.03, 0.03, n), 0.55 + j * 1.08], 1)
radius = np.where(rng.uniform(size=n) < 0.5, 0.5, rng.uniform(0.35, 0.5, n))
vel = rng.normal(scale=3.0, size=(n, 2))
width = cols * 1.08 + 0.2
height = rows * 1.08 + 3.0
floor = fs.Halfspace((0.0, 1.0), 0.0)
law = ContactLaw(4e4, 0.5, 0.5)
kw = dict(periodic_x=(0.0, width))
if case == "hooke, grid world, periodic x":
    bump = fs.Circle(center=[0.3 * width, -1.9], radius=2.0)
    world = fs.GridSDF(
        floor | bump, bounds=[(-1.0, width + 1.0), (-1.0, height + 2.0)],
        samples=[int(8 * width) * 1j, int(8 * height) * 1j],
    )
    wall = law
elif case == "history + rolling, scene world, periodic x":
    world = floor | fs.Circle(center=[0.6 * width, -1.4], radius=1.5)
    law = law._replace(history=True, rolling_friction=0.2)
    wall = law._replace(restitution=0.3, rolling_friction=0.1)
else:  # history, moving world
    rise = fs.Param("speed", 5.0) * fs.t
    world = (
        fs.Halfspace((0.0, 1.0), rise)
        | fs.Halfspace((1.0, 0.0), 0.0)
        | fs.Halfspace((-1.0, 0.0), -width)
    )
    law = law._replace(history=True)
    wall = law._replace(history=False, friction=0.3)
    kw = {}
steps = 80
sim = GranularSimulation(
    world, positions=pos, velocities=vel, radius=radius, contacts=law, wall_contacts=wall,
    gravity=(0.0, -40.0), timestep=steps * 2.5e-4, substep=2.5e-4, skin=0.15, device=device, **kw,
)
frames = 4 if device == "cpu" else 2
for k in range(frames):
    if k == frames - 1:
        sim.set_state(velocities=0.5 * sim.velocities)
    sim.run(1)
out = {
    "positions": sim.positions,
    "velocities": sim.velocities,
    "angular_velocities": sim.angular_velocities,
    "wall_force": np.asarray(sim.wall_force),
    "time": np.array([sim.time]),
    "rebuilds": np.array([sim.rebuilds]),
    "energy": np.array(list(sim.energy().values())),
    "contact_counts": np.array(sim.contact_counts()),
    "neighbour_pairs": sim.neighbour_pairs(),
}
if law.history:
    pairs, stretch, against_world = sim.tangential_springs()
    out.update(spring_pairs=pairs, springs=stretch, wall_springs=against_world)
np.savez(sys.argv[2], **out)
"""

# Run in a fresh interpreter with a cold numba cache: prints the CPU seconds of each law's
# first simulation as JSON.
COMPILE = r"""
import json, time
import numpy as np
import fastsdf as fs
from fastsdf.granular import ContactLaw, GranularSimulation

rng = np.random.default_rng(0)
p = np.c_[rng.uniform(0, 10, 400), rng.uniform(0.3, 10, 400)]
world = fs.Halfspace((0.0, 1.0), 0.0)
world(np.zeros(3), np.zeros(3), compute_gradient=True)
out = {}
laws = {"hooke": ContactLaw(1e4), "history+rolling": ContactLaw(1e4, history=True,
                                                                rolling_friction=0.1)}
for name, law in laws.items():
    t0 = time.process_time()
    sim = GranularSimulation(world, positions=p, radius=0.2, contacts=law, timestep=0.01,
                             periodic_x=(0.0, 10.0))
    sim.run(2)
    sim.energy()
    out[name] = time.process_time() - t0
print(json.dumps(out))
"""

CASES = (
    "hooke, grid world, periodic x",
    "history + rolling, scene world, periodic x",
    "history, moving world",
)
STATIC = CASES[:2]


def _git(*args: str) -> str:
    return subprocess.run(
        ["git", "-C", REPO, *args], check=True, capture_output=True, text=True
    ).stdout.strip()


def baseline_tree(rev: str) -> str:
    """``rev``'s tree, exported once into a folder named by its commit and kept (its numba
    cache with it)."""
    sha = _git("rev-parse", "--verify", f"{rev}^{{commit}}")
    root = os.path.join(tempfile.gettempdir(), "fastsdf_grain_bits", sha)
    tree = os.path.join(root, "tree")
    if not os.path.isdir(tree):
        os.makedirs(root, exist_ok=True)
        tar = os.path.join(root, "tree.tar")
        subprocess.run(["git", "-C", REPO, "archive", "--format=tar", "-o", tar, sha], check=True)
        with tarfile.open(tar) as tf:
            tf.extractall(tree + ".part", filter="data")
        os.replace(tree + ".part", tree)
        os.remove(tar)
    return tree


def run_side(tree: str, case: str, grains: int, threads: int, device: str, out: str) -> dict:
    """The arrays one side saves for one bed."""
    env = dict(os.environ, PYTHONPATH=tree, MPLBACKEND="Agg", NUMBA_NUM_THREADS=str(threads))
    env["NUMBA_ENABLE_CUDASIM"] = "1" if device == "cuda" else env.get("NUMBA_ENABLE_CUDASIM", "0")
    arg = json.dumps([case, grains, threads, device])
    res = subprocess.run(
        [sys.executable, "-c", WORKER, arg, out],
        env=env,
        cwd=tree,
        capture_output=True,
        text=True,
    )
    if res.returncode:
        raise RuntimeError(f"the bed {case!r} failed in {tree}:\n{res.stderr[-3000:]}")
    with np.load(out) as z:
        return {k: z[k] for k in z.files}


def compile_times(trees: dict, rounds: int) -> None:
    """Print the cold compile of each side (see ``--compile-time``), ``rounds`` times."""
    for _ in range(rounds):
        for side, tree in trees.items():
            with tempfile.TemporaryDirectory(prefix="fastsdf_grain_numba_") as cache:
                env = dict(os.environ, PYTHONPATH=tree, MPLBACKEND="Agg", NUMBA_CACHE_DIR=cache)
                res = subprocess.run(
                    [sys.executable, "-c", COMPILE], env=env, cwd=tree, capture_output=True,
                    text=True,
                )  # fmt: skip
            if res.returncode:
                raise RuntimeError(f"the compile run failed in {tree}:\n{res.stderr[-3000:]}")
            times = json.loads(res.stdout.strip().splitlines()[-1])
            print(f"{side}: " + ", ".join(f"{k} {v:.1f} s" for k, v in times.items()), flush=True)


def same_bits(a: dict, b: dict) -> list:
    """The names of the arrays that differ (in keys, shape, dtype or any bit)."""
    differ = sorted(set(a) ^ set(b))
    for k in sorted(set(a) & set(b)):
        p, q = a[k], b[k]
        if p.shape != q.shape or p.dtype != q.dtype or p.tobytes() != q.tobytes():
            differ.append(k)
    return differ


def main(argv: list | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m bench.grain_bits",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--rev", required=True, help="git revision of the baseline")
    parser.add_argument("--grains", type=int, default=4500)
    parser.add_argument("--threads", type=int, nargs="+", default=[1, 2])
    parser.add_argument("--cases", nargs="+", choices=CASES, default=list(CASES))
    parser.add_argument("--devices", nargs="+", choices=("cpu", "cuda"), default=["cpu"])
    parser.add_argument("--cuda-grains", type=int, default=200)
    parser.add_argument("--compile-time", action="store_true", help="cold compiles instead")
    parser.add_argument("--rounds", type=int, default=2, help="with --compile-time")
    args = parser.parse_args(argv)
    base = baseline_tree(args.rev)
    if args.compile_time:
        compile_times({"baseline": base, "this": REPO}, args.rounds)
        return 0
    runs = []
    if "cpu" in args.devices:
        runs += [(c, args.grains, t, "cpu") for c in args.cases for t in args.threads]
    if "cuda" in args.devices:
        runs += [(c, args.cuda_grains, 1, "cuda") for c in args.cases if c in STATIC]
    same_all = True
    with tempfile.TemporaryDirectory(prefix="fastsdf_grain_bits_") as tmp:
        for case, n, threads, device in runs:
            a = run_side(base, case, n, threads, device, os.path.join(tmp, "base.npz"))
            b = run_side(REPO, case, n, threads, device, os.path.join(tmp, "this.npz"))
            differ = same_bits(a, b)
            same_all &= not differ
            print(
                f"{case} [{device}, {n} grains, {threads} thread(s), {int(b['rebuilds'][0])} "
                f"rebuilds]: " + ("same bits" if not differ else "DIFFER in " + ", ".join(differ)),
                flush=True,
            )
    print("all bit-identical" if same_all else "DIFFERENCES")
    return 0 if same_all else 1


if __name__ == "__main__":
    sys.exit(main())
