"""Janssen: the pressure at the bottom of a tall column of grains saturates with the height of
the fill (the walls carry the rest by friction).

    python -m bench.bench_janssen [--rows 8 16 32 64 96] [--width 6]

Discs of diameter 0.8-1 fall from a loose grid (rows 1.6 apart: each settles by a fraction of
a diameter, enough to mobilize the wall friction) into a column of width W between rough walls,
gravity 1, ``ContactLaw(stiffness=2e3, restitution=0.3, friction=0.5, history=True)`` for
grains and walls, until at rest. The floor's load is the sum of ``k_n delta`` over the grains
overlapping it (the floor at y = 0); Janssen's law for the load per width,
``p(h) = rho g lambda (1 - exp(-h / lambda))`` with ``lambda = W / (2 mu_w K)``, saturates
within a few ``lambda``; without wall friction (or without history: the walls' viscous friction
lets the grains creep down) the floor carries the whole weight. One thread.
"""

import argparse
import os
import time

import numba
import numpy as np

import fastsdf as fs
from fastsdf.granular import ContactLaw, GranularSimulation
from fastsdf.shapes import union


def column(
    rows: int, width: float, history: bool = True, seed: int = 0, k: float = 2e3, gap: float = 1.6
) -> dict:
    world = union(
        [
            fs.Halfspace((0.0, 1.0), 0.0),
            fs.Halfspace((1.0, 0.0), 0.0),
            fs.Halfspace((-1.0, 0.0), -width),
        ]
    )
    rng = np.random.default_rng(seed)
    per = int(width // 1.2)
    i = np.arange(rows * per)
    pos = np.stack(
        [0.6 + (i % per) * 1.2 + rng.uniform(-0.05, 0.05, len(i)), 0.6 + (i // per) * gap], 1
    )
    r = rng.uniform(0.4, 0.5, len(i))
    law = ContactLaw(stiffness=k, restitution=0.3, friction=0.5, history=history)
    sim = GranularSimulation(
        world, positions=pos, radius=r, contacts=law, gravity=(0, -1), timestep=1.0
    )
    for _ in range(60):
        sim.run(2)
        if np.abs(sim.velocities).max() < 1e-3:
            break
    loads = []  # the floor's load, averaged over 2 time units (the pile may still ring)
    for _ in range(20):
        sim.advance(max(1, sim.substeps_per_frame // 10))
        p, rr = sim.positions, sim.radius
        loads.append(float((k * np.clip(rr - p[:, 1], 0, None)).sum()))
    load = float(np.mean(loads))
    weight = float((np.pi * rr**2).sum())
    return {"height": float((p[:, 1] + rr).max()), "load": load, "weight": weight, "t": sim.time}


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--rows", nargs="+", type=int, default=[8, 16, 32, 64, 96])
    ap.add_argument("--width", type=float, default=6.0)
    ap.add_argument("--no-history", action="store_true")
    ap.add_argument("--gap", type=float, default=1.6, help="rows of the loose grid apart")
    a = ap.parse_args()
    numba.set_num_threads(1)
    load0 = os.getloadavg()[0]
    t0 = time.perf_counter()
    print("| fill height | weight | floor load | load / weight |")
    print("| --- | --- | --- | --- |")
    for rows in a.rows:
        c = column(rows, a.width, history=not a.no_history, gap=a.gap)
        print(
            f"| {c['height']:.1f} | {c['weight']:.1f} | {c['load']:.1f} | "
            f"{c['load'] / c['weight']:.3f} |",
            flush=True,
        )
    print(f"{time.perf_counter() - t0:.0f} s, load {load0:.1f} -> {os.getloadavg()[0]:.1f}")


if __name__ == "__main__":
    main()
