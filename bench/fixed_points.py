"""Do settled particles reach exact fixed points (a step that leaves x and v bit-identical)?

    python -m bench.fixed_points                 # 100,000 particles, steps 200-260
    python -m bench.fixed_points --particles 1000000

The notebook scenario of ``bench/bench_particles.py`` (seed world, 400x400 GridSDF, gravity
(0, -1), dt = 1/30, the defaults cr = 0.6, cf = 0.3) is advanced to step 200 (the benchmark's
settled phase) and then one step at a time. For each step it counts the particles whose state
repeats exactly after 1, 2 or 4 steps (a fixed point or a short cycle: skipping such particles
would be exact), and the particles that rest in the restitution micro-bounce: at a contact every
step, the velocity after the response settles at the fixed point of ``v -> cr (g dt - v)``,
``v_n = cr g dt / (1 + cr)`` (0.0125 here), while the tangential velocity, multiplied by
``1 - cf`` at each contact, balances the tangential part of gravity at
``v_t = (1 - cf) g_t dt / cf``: a particle on a surface tilted by any angle creeps.
"""

from __future__ import annotations

import argparse
import os
import sys

import numpy as np


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="python -m bench.fixed_points", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--particles", type=int, default=100_000)
    parser.add_argument("--start", type=int, default=200)
    parser.add_argument("--steps", type=int, default=60)
    args = parser.parse_args(argv)

    import fastsdf.particles as phys
    from fastsdf import GridSDF
    from fastsdf.scenes import seed_world

    grid = GridSDF(seed_world(), bounds=[(-2, 2), (-2, 2)], samples=[400j, 400j])
    sim = phys.ParticleSimulation(grid, n=args.particles, seed=0)
    sim.force_generators.append(phys.Gravity())
    sim.run(args.start)
    hist = [sim.p.copy()]
    for _ in range(args.steps):
        sim.run(1)
        hist.append(sim.p.copy())

    def repeats(a, b):
        return (a["x"] == b["x"]).all(1) & (a["v"] == b["v"]).all(1)

    last = hist[-1]
    n = len(last)
    fixed = max(repeats(hist[k], hist[k + 1]).sum() for k in range(len(hist) - 1))
    cyc2 = max(repeats(hist[k], hist[k + 2]).sum() for k in range(len(hist) - 2))
    cyc4 = max(repeats(hist[k], hist[k + 4]).sum() for k in range(len(hist) - 4))
    g_dt = sim.dt * 1.0
    bounce = sim.cr * g_dt / (1 + sim.cr)
    speed = np.hypot(*last["v"].T)
    resting = np.abs(speed - bounce) < 1e-3 * bounce
    creep = np.hypot(*(hist[-1]["x"] - hist[-2]["x"]).T)[resting]
    print(f"{n:,} particles, steps {args.start}-{args.start + args.steps} of the notebook "
          f"scenario (load average {os.getloadavg()[0]:.1f})")
    print(f"  most particles with a state repeated after 1 step: {fixed:,} "
          f"({fixed / n:.2%}); after 2 steps: {cyc2:,}; after 4 steps: {cyc4:,}")
    print(f"  resting in the micro-bounce (|v| within 0.1% of cr g dt / (1 + cr) = "
          f"{bounce:.4g}): {resting.sum():,} ({resting.mean():.1%}); their position still "
          f"changes by a median {np.median(creep):.2g} per step (creep on the grid's tilt), "
          f"max {creep.max():.2g}, min {creep.min():.2g}")
    q = np.percentile(speed, [10, 25, 50, 75, 90])
    print("  speed percentiles 10/25/50/75/90: " + " / ".join(f"{v:.3g}" for v in q))
    return 0


if __name__ == "__main__":
    sys.exit(main())
