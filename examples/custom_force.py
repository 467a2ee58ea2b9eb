"""A force of your own: a swirling wind that blows particles back up out of the funnel.

    python examples/custom_force.py [OUT]        # writes OUT/custom_force.png

A force generator is any callable ``(p, t) -> (n, 2)`` array of forces (mass * length / s**2)
given the particle state ``p`` (fields ``x``, ``v``, ``m``, ...) and the time ``t`` in seconds.
It is evaluated with NumPy before each compiled step, so it costs a pass over the state per step;
the built-in :class:`fastsdf.particles.Gravity` and :class:`fastsdf.particles.Drag` are fused into
the compiled loop instead.
"""

import os
import sys

import matplotlib

matplotlib.use("Agg")
import numpy as np  # noqa: E402

import fastsdf as sdf  # noqa: E402
import fastsdf.particles as phys  # noqa: E402
from fastsdf._progress import progress  # noqa: E402
from fastsdf.render import render_frame, sim_title  # noqa: E402
from fastsdf.scenes import seed_world  # noqa: E402


def updraft(p, t):
    """A column of rising air around x = 0 below y = -0.5, gusting with a 2 s period."""
    x = p["x"]
    strength = 3.0 * (0.5 + 0.5 * np.sin(np.pi * t))
    column = np.exp(-(x[:, 0] / 0.3) ** 2) * (x[:, 1] < -0.5)
    force = np.zeros_like(x)
    force[:, 1] = p["m"] * strength * column
    force[:, 0] = -0.2 * p["m"] * x[:, 0] * column  # and a pull towards its centre
    return force


def main(out: str = "examples-out", n: int = 20_000, steps: int = 240) -> str:
    world = sdf.GridSDF(seed_world(), bounds=[(-2, 2), (-2, 2)], samples=[400j, 400j])
    sim = phys.ParticleSimulation(world, n=n, timestep=1 / 30, seed=0)
    sim.force_generators += [phys.Gravity(), phys.Drag(0.05), updraft]
    with progress(steps, "simulate") as bar:
        for _ in range(steps):
            sim.run(1)
            bar.update(1)
    os.makedirs(out, exist_ok=True)
    path = os.path.join(out, "custom_force.png")
    x = sim.p["x"]
    render_frame(world, x[:, 0], x[:, 1], r=sim.p["r"], out_png=path,
                 title=sim_title(sim, f"{n:,} particles in an updraft, "))
    print(f"wrote {os.path.abspath(path)}")
    return path


if __name__ == "__main__":
    small = os.environ.get("FASTSDF_EXAMPLE_SMALL") == "1"
    main(*sys.argv[1:], **({"n": 300, "steps": 5} if small else {}))
