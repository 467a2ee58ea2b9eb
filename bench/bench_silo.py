"""Silo discharge through a slot in a flat bottom, against Beverloo's law (2D).

    python -m bench.bench_silo [--widths 4 5 6 8] [--grains 1200] [--history] [--fills 600 1200]

A flat-bottomed silo of width 20 (grain diameters 0.8-1.2, mean 1), the slot of width D in the
middle of its floor, gravity 1, ``ContactLaw(stiffness=1e4, restitution=0.5, friction=0.5)``
for grains and walls. Grains start on a loose grid and fall; the flow rate ``W`` (grains per
unit time) is the slope of the number of grains below the floor against time, fitted while
between 10% and 50% of them are out (the fill height then is many slot widths: Beverloo's
regime). Beverloo's 2D law ``W = C sqrt(g) (D - k d)**1.5`` is fitted over the widths: the
exponent free (expected 1.5 +- 0.15), then ``C`` and ``k`` with the exponent fixed at 1.5
(expected ``k`` between 1 and 3). A benchmark, not a test: minutes on a loaded machine.

``--history``: the contacts keep a tangential spring (``ContactLaw(history=True)``, static
friction). ``--fills A B``: the rate of the first width for each fill (the rate must not depend
on the fill height). One thread (a few thousand grains: waking threads every substep costs more
than it saves).
"""

from __future__ import annotations

import argparse
import os
import time

import numba
import numpy as np
from scipy.optimize import curve_fit

import fastsdf as fs
from fastsdf.granular import ContactLaw, GranularSimulation
from fastsdf.shapes import union

WIDTH, G = 20.0, 1.0


def silo(slot: float):
    """Walls at x = 0 and 20, a floor at y = 0 with a slot of width ``slot``, a catch floor
    far below."""
    half = slot / 2
    return union(
        [
            fs.Halfspace((1.0, 0.0), 0.0),
            fs.Halfspace((-1.0, 0.0), -WIDTH),
            fs.Box((-1.0, -1.0), (WIDTH / 2 - half, 0.0)),
            fs.Box((WIDTH / 2 + half, -1.0), (WIDTH + 1.0, 0.0)),
            fs.Halfspace((0.0, 1.0), -40.0),
        ]
    )


def discharge(slot: float, grains: int, seed: int = 0, history: bool = False) -> float:
    rng = np.random.default_rng(seed)
    per_row = int(WIDTH // 1.3)
    i = np.arange(grains)
    pos = np.stack(
        [0.8 + (i % per_row) * 1.3 + rng.uniform(-0.05, 0.05, grains), 1.0 + (i // per_row) * 1.3],
        1,
    )
    radius = rng.uniform(0.4, 0.6, grains)
    sim = GranularSimulation(
        silo(slot),
        positions=pos,
        radius=radius,
        gravity=(0.0, -G),
        contacts=ContactLaw(stiffness=1e4, restitution=0.5, friction=0.5, history=history),
        timestep=0.5,
    )
    print(
        f"  slot {slot}, {grains} grains: {sim.substeps_per_frame} substeps per frame", flush=True
    )
    times, out = [], []
    while True:
        sim.run(1)
        n_out = int((sim.positions[:, 1] < -1.0).sum())
        times.append(sim.time)
        out.append(n_out)
        if n_out > 0.5 * grains or sim.time > 2000:
            break
        if len(out) > 100 and out[-1] == out[-100]:  # jammed: an arch over the slot
            return float("nan")
    times, out = np.array(times), np.array(out)
    window = (out >= 0.1 * grains) & (out <= 0.5 * grains)
    slope = np.polyfit(times[window], out[window], 1)[0]
    return float(slope)


def main() -> None:
    global WIDTH
    ap = argparse.ArgumentParser()
    ap.add_argument("--widths", nargs="+", type=float, default=[4.0, 5.0, 6.0, 8.0])
    ap.add_argument("--grains", type=int, default=1200)
    ap.add_argument("--history", action="store_true")
    ap.add_argument("--width", type=float, default=WIDTH, help="width of the silo")
    ap.add_argument("--fills", nargs="*", type=int, default=[])
    a = ap.parse_args()
    numba.set_num_threads(1)
    WIDTH = a.width
    load0 = os.getloadavg()[0]
    t0 = time.perf_counter()
    rates = []
    for w in a.widths:
        rates.append(discharge(w, a.grains, history=a.history))
        print(f"slot {w}: {rates[-1]:.3f} grains per unit time", flush=True)
    widths, rates = np.array(a.widths), np.array(rates)
    flowing = np.isfinite(rates)  # NaN: the slot jammed (an arch)
    widths, rates = widths[flowing], rates[flowing]

    def law(d, c, k, p):
        return c * np.sqrt(G) * np.clip(d - k, 1e-9, None) ** p

    if len(widths) >= 4:
        (c, k, p), _ = curve_fit(law, widths, rates, p0=(0.6, 1.5, 1.5), maxfev=20000)
        print(f"free fit: C = {c:.3f}, k = {k:.2f}, exponent = {p:.2f}")
    if len(widths) >= 3:
        (c15, k15), _ = curve_fit(lambda d, c, k: law(d, c, k, 1.5), widths, rates, p0=(0.6, 1.5))
        print(f"exponent 1.5: C = {c15:.3f}, k = {k15:.2f}")
    for fill in a.fills:
        rate = discharge(a.widths[0], fill, history=a.history)
        print(f"fill {fill} grains, slot {a.widths[0]}: {rate:.3f} grains per unit time")
    print(f"{time.perf_counter() - t0:.0f} s, load {load0:.1f} -> {os.getloadavg()[0]:.1f}")


if __name__ == "__main__":
    main()
