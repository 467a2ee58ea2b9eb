"""Bit-identity of the particle-by-particle step against another revision's particle engine.

    python -m bench.step_bits --rev f8cd325 --particles 3000

``bench.step_ab`` times and compares the block kernel of a grid world; this compares the
results of the general kernel (``run_*``) where the block kernel does not apply: a thin bar
rising through a box and a piston (moving worlds: the space-time march and sweep), and the
seed world as an exact SDF (the static sweep), with gravity, the tunnelling check and query
skipping, 60 steps in 4 calls from the same random state. The baseline is loaded beside the
current engine as in ``bench.step_ab``. Prints, per world, whether positions and velocities
have the same bits.
"""

from __future__ import annotations

import argparse
import sys

import numpy as np


def worlds() -> dict:
    """The worlds compared, with the values of their runtime parameters."""
    import fastsdf as sdf
    from fastsdf.shapes.scenes import seed_world

    lift = sdf.Param("y0", -1.1) + sdf.Param("u", 1.0) * sdf.t
    with sdf.transform(offset=[0.0, lift]):
        bar = sdf.Box(minc=[-1.15, -0.01], maxc=[1.15, 0.01])
    box = (
        sdf.Halfspace(normal=[0, 1], d=-1.2)
        | sdf.Halfspace(normal=[0, -1], d=-1.2)
        | sdf.Halfspace(normal=[1, 0], d=-1.2)
        | sdf.Halfspace(normal=[-1, 0], d=-1.2)
    )
    piston = sdf.Halfspace(normal=[1, 0], d=-1.0 + sdf.Param("speed", 0.5) * sdf.t) | sdf.Circle(
        center=[0.5, 0.0], radius=0.2
    )
    return {
        "moving bar": (box | bar, {"u": 6.0, "y0": -1.1}),
        "piston": (piston, {}),
        "seed world (exact SDF)": (seed_world(), {}),
    }


def run(engine, world, params: dict, n: int) -> tuple:
    """Positions, velocities and clock after 60 steps in 4 calls of ``engine``'s simulation."""
    sim = engine.ParticleSimulation(world, n=n, seed=3)
    sim.force_generators.append(engine.Gravity())
    for name, value in params.items():
        sim.params[name] = value
    rng = np.random.default_rng(1)
    sim.p["x"] = np.c_[rng.uniform(-1.1, 1.1, n), rng.uniform(-0.9, 1.1, n)]
    sim.p["v"] = rng.normal(scale=3.0, size=(n, 2))
    for _ in range(4):
        sim.run(15)
    return np.array(sim.p["x"]), np.array(sim.p["v"]), sim.t


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m bench.step_bits",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--rev", required=True, help="git revision of the baseline")
    parser.add_argument("--particles", type=int, default=3000)
    args = parser.parse_args(argv)

    import fastsdf.particles as phys

    from .step_ab import _load_base

    base = _load_base(args.rev)
    same_all = True
    for name, (world, params) in worlds().items():
        a = run(base, world, params, args.particles)
        b = run(phys, world, params, args.particles)
        same = a[2] == b[2] and all(
            np.array_equal(p.view(np.int64), q.view(np.int64))
            for p, q in zip(a[:2], b[:2], strict=True)
        )
        same_all &= same
        print(
            f"{name}: {args.particles} particles, 60 steps in 4 calls: same bits {same}", flush=True
        )
    print("all bit-identical" if same_all else "DIFFERENCES")
    return 0 if same_all else 1


if __name__ == "__main__":
    sys.exit(main())
