"""Where the time of a particle step goes: forces + integration, the SDF query, the collision
response, the tunnelling sweep, measured by switching stages on one at a time.

    python -m bench.profile_particles                       # 1e6 particles, seed-world grid
    python -m bench.profile_particles --particles 200000 --world box20 --exact

The state is first advanced to the chosen phase (``--settle`` steps: by default 150, when most
particles rest on the funnel, the expensive phase), then each variant runs from a copy of that
state. Stages that are separate passes (integration alone, query alone) read and write memory
that the fused step touches once, so the differences are estimates of each stage's cost inside
the fused loop, not exact parts of it.
"""

from __future__ import annotations

import argparse
import sys
import time

import numba
import numpy as np
from numba import njit, prange


@njit(parallel=True, cache=True)
def _integrate(x, v, dt, ay):
    """Forces (gravity) and semi-implicit Euler alone: the step without any SDF work."""
    for i in prange(x.shape[0]):
        v[i, 1] += ay * dt
        x[i, 0] += v[i, 0] * dt
        x[i, 1] += v[i, 1] * dt


@njit(parallel=True, cache=True)
def _integrate_and_query(query_one, data, x, v, r, dt, ay, out):
    """Integration plus one SDF query (value and gradient) per particle, no response."""
    for i in prange(x.shape[0]):
        v[i, 1] += ay * dt
        x[i, 0] += v[i, 0] * dt
        x[i, 1] += v[i, 1] * dt
        d, gx, gy = query_one(data, x[i, 0], x[i, 1])
        out[i] = d - r[i] + 1e-30 * (gx + gy)


def _median_ms(fn, repeats):
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return 1e3 * float(np.median(times))


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m bench.profile_particles",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--particles", type=int, default=1_000_000)
    parser.add_argument("--world", choices=["seed", "box20"], default="seed")
    parser.add_argument("--exact", action="store_true", help="query the exact SDF, not a grid")
    parser.add_argument("--grid", type=int, default=400, help="grid samples per axis")
    parser.add_argument("--settle", type=int, default=150, help="steps before measuring")
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args(argv)

    import fastsdf as sdf
    import fastsdf.particles as phys
    from fastsdf.shapes.scenes import box_world, seed_world

    world = seed_world() if args.world == "seed" else box_world(20)
    f = (
        world
        if args.exact
        else sdf.GridSDF(world, bounds=[(-2, 2), (-2, 2)], samples=[args.grid * 1j, args.grid * 1j])
    )
    n, dt = args.particles, 1 / 30
    sim = phys.ParticleSimulation(f, n=n, timestep=dt, seed=0)
    sim.force_generators.append(phys.Gravity())
    sim.run(args.settle)
    state = sim.p.copy()
    query_one = sim.engine.kernel()[0]._query  # the fused kernel's own inlined query

    def fresh():  # restore the state in place: no allocation, no page faults in the timings
        for field in phys.Particles.FIELDS:
            sim.p[field] = state[field]

    def fused(tunnelling, steps=1):
        def go():
            fresh()
            sim.prevent_tunnelling = tunnelling
            sim.run(steps)

        return go

    out = np.empty(n)
    x0, v0, r0 = state["x"].copy(), state["v"].copy(), state["r"].copy()
    x, v = np.empty_like(x0), np.empty_like(v0)

    def copy_only():
        np.copyto(x, x0)
        np.copyto(v, v0)

    def integrate():
        copy_only()
        _integrate(x, v, dt, -1.0)

    def integrate_query():
        copy_only()
        _integrate_and_query(query_one, sim.engine.data, x, v, r0, dt, -1.0, out)

    def copy_state():
        fresh()

    for fn in (integrate, integrate_query, fused(False), fused(True), copy_only, copy_state):
        fn()  # compile
    copy_xv = _median_ms(copy_only, args.repeats)
    copy_all = _median_ms(copy_state, args.repeats)
    integ = _median_ms(integrate, args.repeats) - copy_xv
    query = _median_ms(integrate_query, args.repeats) - copy_xv
    plain = _median_ms(fused(False), args.repeats) - copy_all
    swept = _median_ms(fused(True), args.repeats) - copy_all
    ten = (_median_ms(fused(True, 10), max(2, args.repeats // 2)) - copy_all) / 10
    kind = "exact SDF" if args.exact else f"GridSDF {args.grid}x{args.grid}"
    print(
        f"{n:,} particles, {args.world} world via {kind}, after {args.settle} steps, "
        f"{numba.get_num_threads()} threads (ms per step, medians of {args.repeats}; the "
        f"copy of the starting state is subtracted)"
    )
    for name, ms in (
        ("forces + integration (separate pass)", integ),
        ("... + SDF query, value and gradient", query),
        ("fused step, no tunnelling sweep: run(1)", plain),
        ("fused step with the sweep (default): run(1)", swept),
        ("fused step, run(10), per step", ten),
    ):
        print(f"  {name:<46} {ms:8.2f} ms  {n / ms / 1e3:8.1f} M particle-steps/s")
    print(
        f"\nestimated stages: integration {integ:.2f} ms, SDF query {query - integ:.2f} ms, "
        f"collision response and loop {plain - query:.2f} ms, tunnelling sweep "
        f"{swept - plain:.2f} ms; run(10) saves {swept - ten:.2f} ms per step (skipped "
        f"queries of particles proven clear, block kept in cache)."
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
