"""Forces of your own: a fused force field, and a time-varying Python force.
=========================================================================

    python examples/custom_force.py [OUT]        # writes OUT/custom_force.png

Two ways to add a force to ``sim.force_generators``:

- ``phys.FieldForce(fx, fy)`` (or ``FieldForce(potential=U)``): a field written with the graph
  API, compiled like an SDF and fused into the compiled step (it costs about what its arithmetic
  costs). Here: a vortex around the disc, ``(-y, x) * k * exp(-r^2 / s^2)``, an acceleration
  (``per_mass=True``).
- any callable ``(p, t) -> (n, 2)`` array of forces (mass * length / s**2), given the particle
  state ``p`` (fields ``x``, ``v``, ``m``, ...) and the time ``t`` in seconds. It is evaluated
  with NumPy before each compiled step (a pass over the state per step: the slow path), but it
  can depend on time. Here: an updraft that gusts with a 2 s period.
"""

import os
import sys
import time

import matplotlib

matplotlib.use("Agg")
import numpy as np

import fastsdf as sdf
import fastsdf.graph as cg
import fastsdf.particles as phys
from fastsdf.shapes.scenes import seed_world
from fastsdf.viz.progress import progress
from fastsdf.viz.render import render_frame, sim_title


def vortex(k: float = 1.5, s: float = 1.0) -> phys.FieldForce:
    """A counter-clockwise swirl around the origin, fading with distance (an acceleration)."""
    x, y = cg.Symbol("x"), cg.Symbol("y")
    fade = k * cg.sym_exp(-(x * x + y * y) / (s * s))
    return phys.FieldForce(-y * fade, x * fade, per_mass=True)


def updraft(p, t):
    """A column of rising air around x = 0 below y = -0.5, gusting with a 2 s period."""
    x = p["x"]
    strength = 3.0 * (0.5 + 0.5 * np.sin(np.pi * t))
    column = np.exp(-((x[:, 0] / 0.3) ** 2)) * (x[:, 1] < -0.5)
    force = np.zeros_like(x)
    force[:, 1] = p["m"] * strength * column
    force[:, 0] = -0.2 * p["m"] * x[:, 0] * column  # and a pull towards its centre
    return force


def main(out: str = "examples-out", n: int = 20_000, steps: int = 240) -> str:
    world = sdf.GridSDF(seed_world(), bounds=[(-2, 2), (-2, 2)], samples=[400j, 400j])
    sim = phys.ParticleSimulation(world, n=n, timestep=1 / 30, seed=0)
    sim.force_generators += [phys.Gravity(), phys.Drag(0.05), vortex(), updraft]
    sim.run(1)  # compile (or load) the step with the fused vortex
    t0 = time.perf_counter()
    with progress(steps - 1, "simulate") as bar:
        for _ in range(steps - 1):
            sim.run(1)  # one step at a time: the Python updraft is evaluated before each
            bar.update(1)
    took = time.perf_counter() - t0
    print(
        f"{n:,} particles x {steps - 1} steps in {took:.2f} s "
        f"({(steps - 1) * n / took / 1e6:.1f} M particle-steps/s with a Python force in the "
        f"loop; without it, run(k) stays in compiled code)"
    )
    os.makedirs(out, exist_ok=True)
    path = os.path.join(out, "custom_force.png")
    x = sim.p["x"]
    render_frame(
        world,
        x[:, 0],
        x[:, 1],
        r=sim.p["r"],
        out_png=path,
        title=sim_title(sim, f"{n:,} particles, vortex + updraft, "),
    )
    print(f"wrote {os.path.abspath(path)}")
    return path


if __name__ == "__main__":
    small = os.environ.get("FASTSDF_EXAMPLE_SMALL") == "1"
    main(*sys.argv[1:], **({"n": 300, "steps": 5} if small else {}))
