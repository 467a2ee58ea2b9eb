"""A silo drains through a slot in its floor; the flow rate is measured and printed.
=================================================================================

    python examples/silo.py [OUT] [--grains 800] [--slot 6]

writes OUT/silo.png (OUT defaults to the current folder; ``FASTSDF_EXAMPLE_SMALL=1``: 300
grains). Discs of diameter 0.8-1.2 (mean 1) under ``Gravity()`` (1 length unit / s**2, downward)
fill a flat-bottomed silo 20 wide; the slot opens at t = 0. The contacts keep a tangential
spring (static friction). The flow rate (grains per unit time) is the slope of the count of
grains out of the silo against time while 10-50% of them are out: constant, whatever the height
of the fill above the slot (Beverloo's law, ``W = C sqrt(g) (D - k d)**1.5`` in 2D;
``bench/bench_silo.py`` fits it over several slots).
"""

from __future__ import annotations

import argparse
import os
import time

import numba
import numpy as np

import fastsdf as fs
from fastsdf.particles import ContactLaw, Gravity, ParticleSimulation
from fastsdf.shapes import union

WIDTH = 20.0


def silo(slot: float) -> fs.SDF:
    """Walls at x = 0 and 20, a floor at y = 0 (1 thick) with a centred slot, a catch floor
    at y = -30."""
    half = slot / 2
    return union(
        [
            fs.Halfspace((1.0, 0.0), 0.0),
            fs.Halfspace((-1.0, 0.0), -WIDTH),
            fs.Box((-1.0, -1.0), (WIDTH / 2 - half, 0.0)),
            fs.Box((WIDTH / 2 + half, -1.0), (WIDTH + 1.0, 0.0)),
            fs.Halfspace((0.0, 1.0), -30.0),
        ]
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=(__doc__ or "").strip().split("\n")[0])
    ap.add_argument("out", nargs="?", default=".")
    small = os.environ.get("FASTSDF_EXAMPLE_SMALL") == "1"
    ap.add_argument("--grains", type=int, default=300 if small else 800)
    ap.add_argument("--slot", type=float, default=6.0)
    a = ap.parse_args()
    numba.set_num_threads(1)  # a few hundred grains: one thread is fastest
    rng = np.random.default_rng(0)
    n = a.grains
    per_row = int(WIDTH // 1.25)
    i = np.arange(n)
    x0 = (WIDTH - (per_row - 1) * 1.25) / 2  # the columns centred: clear of both walls
    pos = np.stack(
        [x0 + (i % per_row) * 1.25 + rng.uniform(-0.05, 0.05, n), 0.8 + (i // per_row) * 1.25], 1
    )
    law = ContactLaw(stiffness=1e4, restitution=0.5, friction=0.5, history=True)
    sim = ParticleSimulation(
        silo(a.slot), positions=pos, radius=rng.uniform(0.4, 0.6, n), contacts=law, timestep=0.5
    )
    sim.force_generators.append(Gravity())  # (0, -1) length / s**2
    t0 = time.perf_counter()
    times, out = [], []
    snapshot = None
    while True:
        sim.run(1)
        count = int((sim.p["x"][:, 1] < -1.0).sum())
        times.append(sim.t)
        out.append(count)
        if snapshot is None and count >= 0.3 * n:
            snapshot = (sim.p["x"].copy(), sim.p["r"].copy())
        if count > 0.6 * n or sim.t > 400:
            break
    times_a, out_a = np.array(times), np.array(out)
    window = (out_a >= 0.1 * n) & (out_a <= 0.5 * n)
    rate, icpt = np.polyfit(times_a[window], out_a[window], 1)
    print(
        f"{n} grains, slot {a.slot:g}: flow rate {rate:.2f} grains per unit time "
        f"(fit while 10-50% are out); {time.perf_counter() - t0:.0f} s"
    )
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.collections import EllipseCollection

    fig, (ax, bx) = plt.subplots(1, 2, figsize=(10, 5), dpi=100, width_ratios=[1.1, 1])
    p, r = snapshot if snapshot is not None else (sim.p["x"], sim.p["r"])
    xs = np.linspace(-2, WIDTH + 2, 441)
    ys = np.linspace(-31, p[:, 1].max() + 2, 601)
    gx, gy = np.meshgrid(xs, ys)
    d = np.asarray(sim.world(gx.ravel(), gy.ravel())).reshape(gx.shape)
    ax.contourf(gx, gy, d, levels=[-1e9, 0], colors=["0.35"])
    ax.add_collection(
        EllipseCollection(
            2 * r,
            2 * r,
            0,
            units="xy",
            offsets=p,
            offset_transform=ax.transData,
            facecolors="#d9a441",
            edgecolors="#7a5a1a",
            linewidths=0.3,
        )
    )
    ax.set_aspect("equal")
    ax.set_xlim(xs[0], xs[-1])
    ax.set_ylim(ys[0], ys[-1])
    ax.set_title("draining (30% out)")
    bx.plot(times_a, out_a, color="#7a5a1a", label="grains out")
    tw = times_a[window]
    bx.plot(tw, rate * tw + icpt, "--", color="tab:red", label=f"fit: {rate:.2f} per unit time")
    bx.set_xlabel("time")
    bx.set_ylabel("grains out of the silo")
    bx.legend(loc="upper left")
    bx.set_title(f"flow rate through a slot {a.slot:g} wide")
    fig.tight_layout()
    os.makedirs(a.out, exist_ok=True)
    path = os.path.join(a.out, "silo.png")
    fig.savefig(path)
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
