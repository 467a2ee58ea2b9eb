"""Grains pour from a hopper onto a floor and build a heap that keeps its slope.
=============================================================================

    python examples/heap.py [OUT] [--grains 400] [--friction 0.5] [--rolling 0.3]

writes OUT/heap.png (OUT defaults to the current folder; ``FASTSDF_EXAMPLE_SMALL=1``: 150
grains).

Discs of diameter 0.8-1.2 (mean 1) under ``Gravity()`` (1 length unit / s**2, downward) fall
into a hopper whose outlet, eight diameters wide (narrower ones jam: grains with rolling
resistance arch like sand), sits above the middle of a rough floor. The contact law keeps a
tangential spring per contact (``history=True``: static friction, Cundall-Strack) and rolling
resistance (``rolling_friction``): without them discs roll away and the heap flattens. The angle
of repose is measured by ``fastsdf.granular.repose_angle`` (a straight-line fit to each flank of
the heap's surface: the highest grain in each bin of one diameter, between 20% and 80% of the
heap's height) and printed.
"""

from __future__ import annotations

import argparse
import math
import os
import time

import numba
import numpy as np

import fastsdf as fs
from fastsdf.granular import repose_angle
from fastsdf.particles import ContactLaw, Gravity, ParticleSimulation
from fastsdf.shapes import union


def hopper(outlet_y: float, outlet: float = 8.0) -> fs.SDF:
    """A floor at y = 0 and a V-shaped hopper (walls 1 thick) with its outlet, ``outlet`` wide,
    at ``outlet_y``."""
    half = outlet / 2 + 0.5
    return union(
        [
            fs.Halfspace((0.0, 1.0), 0.0),
            fs.Capsule((-half, outlet_y), (-half - 12.0, outlet_y + 12.0), 0.5),
            fs.Capsule((half, outlet_y), (half + 12.0, outlet_y + 12.0), 0.5),
        ]
    )


def outlet_height(grains: int) -> float:
    """The hopper's outlet: 2 above the top of a 25-degree heap of ``grains`` discs."""
    return math.sqrt(grains * 0.9 * math.tan(math.radians(25.0))) + 2.0


def pour(grains: int, law: ContactLaw, seed: int = 0, time_limit: float = 200.0):
    """Pour ``grains`` discs through the hopper until they rest; returns the simulation (a
    ``GrainSimulation``: ``sim.p['x']``, ``sim.p['r']``, ``sim.t``)."""
    rng = np.random.default_rng(seed)
    outlet_y = outlet_height(grains)
    per_row = 18
    i = np.arange(grains)
    pos = np.stack(
        [
            (i % per_row - (per_row - 1) / 2) * 1.25 + rng.uniform(-0.1, 0.1, grains),
            outlet_y + 13.0 + (i // per_row) * 1.25,
        ],
        1,
    )
    radius = rng.uniform(0.4, 0.6, grains)
    sim = ParticleSimulation(
        hopper(outlet_y), positions=pos, radius=radius, contacts=law, timestep=1.0
    )
    sim.force_generators.append(Gravity())  # (0, -1) length / s**2
    while sim.t < time_limit:
        sim.run(5)
        if np.abs(sim.p["v"]).max() < 0.02 and sim.p["x"][:, 1].max() < outlet_y:
            break
    return sim


def main() -> None:
    ap = argparse.ArgumentParser(description=(__doc__ or "").strip().split("\n")[0])
    ap.add_argument("out", nargs="?", default=".")
    small = os.environ.get("FASTSDF_EXAMPLE_SMALL") == "1"
    ap.add_argument("--grains", type=int, default=150 if small else 400)
    ap.add_argument("--friction", type=float, default=0.5)
    ap.add_argument("--rolling", type=float, default=0.3)
    a = ap.parse_args()
    # a few hundred grains: waking threads every substep costs more than it saves
    numba.set_num_threads(1)
    law = ContactLaw(
        stiffness=2e3,
        restitution=0.3,
        friction=a.friction,
        history=True,
        rolling_friction=a.rolling,
    )
    t0 = time.perf_counter()
    sim = pour(a.grains, law)
    # the floor is at y = 0; bins one mean diameter (1) wide
    p, r = sim.p["x"], sim.p["r"]
    left, right, lines = repose_angle(p, r, floor=0.0, bin_width=1.0)
    print(
        f"{a.grains} grains, mu = {a.friction}, mu_r = {a.rolling}: angle of repose "
        f"{left:.1f} (left) and {right:.1f} (right) degrees, mean {(left + right) / 2:.1f}; "
        f"t = {sim.t:.0f}, {time.perf_counter() - t0:.0f} s"
    )
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.collections import EllipseCollection

    fig, ax = plt.subplots(figsize=(8, 4.5), dpi=100)
    xs = np.linspace(-30, 30, 601)
    top = outlet_height(a.grains) + 13.0
    ys = np.linspace(-1, top, 301)
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
    for slope, intercept in lines:  # each flank's fitted line, drawn from the floor up
        if math.isfinite(slope):
            x0 = -intercept / slope
            xs_line = np.array([x0, x0 + 0.9 * (p[:, 1].max() + 0.5) / slope])
            ax.plot(xs_line, slope * xs_line + intercept, "--", color="tab:red", lw=1.2)
    ax.set_title(
        f"angle of repose {left:.1f}° / {right:.1f}° (mu = {a.friction}, mu_r = {a.rolling})"
    )
    ax.set_aspect("equal")
    ax.set_xlim(-30, 30)
    ax.set_ylim(-1, ys[-1])
    fig.tight_layout()
    os.makedirs(a.out, exist_ok=True)
    path = os.path.join(a.out, "heap.png")
    fig.savefig(path)
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
