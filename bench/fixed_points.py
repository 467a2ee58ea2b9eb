"""Do settled particles reach exact fixed points (a step that leaves x and v bit-identical)?

    python -m bench.fixed_points                 # 100,000 particles, steps 200-260
    python -m bench.fixed_points --particles 1000000
    python -m bench.fixed_points --rest-speed 0.1     # and with resting contact (rest_speed)

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
    parser = argparse.ArgumentParser(
        prog="python -m bench.fixed_points",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--particles", type=int, default=100_000)
    parser.add_argument("--start", type=int, default=200)
    parser.add_argument("--steps", type=int, default=60)
    parser.add_argument(
        "--rest-speed",
        type=float,
        default=0.0,
        help="also measure resting contact with this rest_speed",
    )
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args(argv)

    import fastsdf.particles as phys
    from fastsdf import GridSDF
    from fastsdf.shapes.scenes import seed_world

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
    print(
        f"{n:,} particles, steps {args.start}-{args.start + args.steps} of the notebook "
        f"scenario (load average {os.getloadavg()[0]:.1f})"
    )
    print(
        f"  most particles with a state repeated after 1 step: {fixed:,} "
        f"({fixed / n:.2%}); after 2 steps: {cyc2:,}; after 4 steps: {cyc4:,}"
    )
    print(
        f"  resting in the micro-bounce (|v| within 0.1% of cr g dt / (1 + cr) = "
        f"{bounce:.4g}): {resting.sum():,} ({resting.mean():.1%}); their position still "
        f"changes by a median {np.median(creep):.2g} per step (creep on the grid's tilt), "
        f"max {creep.max():.2g}, min {creep.min():.2g}"
    )
    q = np.percentile(speed, [10, 25, 50, 75, 90])
    print("  speed percentiles 10/25/50/75/90: " + " / ".join(f"{v:.3g}" for v in q))
    if args.rest_speed > 0:
        _resting(grid, args.particles, args.rest_speed, args.repeats)
    return 0


def _resting(grid, n, rest_speed, repeats):
    """The same scenario with resting contact (``rest_speed``): the share of particles at an
    exact rest and the speed of ``run(20)`` from steps 200, 300 and 450, side by side with the
    default contact from its own state at the same step and with Taichi's fused kernel
    (``bench/peers.py``, the default contact) on that state."""
    import time

    import numba

    import fastsdf.particles as phys

    from . import peers

    sims = {
        rs: phys.ParticleSimulation(grid, n=n, seed=0, rest_speed=rs) for rs in (0.0, rest_speed)
    }
    for s in sims.values():
        s.force_generators.append(phys.Gravity())
    ti, ti_err = peers.taichi_particles(grid, numba.get_num_threads())
    print(
        f"\nresting contact, rest_speed={rest_speed} (run(20), medians of {repeats}; "
        f"load average {os.getloadavg()[0]:.1f})" + ("" if ti else f"; Taichi: {ti_err}")
    )
    done = 0
    for upto in (200, 300, 450):
        for s in sims.values():
            s.run(upto - done)
        done = upto
        states = {rs: s.p.copy() for rs, s in sims.items()}
        times = {k: [] for k in list(sims) + ["taichi"]}
        for _ in range(repeats):
            for rs, s in sims.items():
                s.p = states[rs].copy()
                t0 = time.perf_counter()
                s.run(20)
                times[rs].append(time.perf_counter() - t0)
            if ti:
                p = states[0.0].copy()
                t0 = time.perf_counter()
                ti(p, 20, 1 / 30, -1.0)
                times["taichi"].append(time.perf_counter() - t0)
        for rs, s in sims.items():
            s.p = states[rs]
        rate = {k: n * 20 / float(np.median(v)) / 1e6 for k, v in times.items() if v}
        at_rest = np.mean(np.all(states[rest_speed]["v"] == 0.0, axis=1))
        line = (
            f"  from step {upto}: {at_rest:.1%} at rest; default {rate[0.0]:.1f} M/s, "
            f"resting contact {rate[rest_speed]:.1f} M/s "
            f"({rate[rest_speed] / rate[0.0]:.2f}x)"
        )
        if "taichi" in rate:
            line += (
                f", Taichi {rate['taichi']:.1f} M/s (resting contact / Taichi "
                f"{rate[rest_speed] / rate['taichi']:.2f}x, default / Taichi "
                f"{rate[0.0] / rate['taichi']:.2f}x)"
            )
        print(line)


if __name__ == "__main__":
    sys.exit(main())
