"""A rotating stirrer in a box: a moving wall built with time ``sdf.t``, 1e6 particles.
====================================================================================

    python examples/moving_walls.py [OUT]      # OUT/moving_walls.mp4 (needs ffmpeg),
                                               # OUT/moving_walls.png (four frames)

The stirrer is built under ``sdf.transform(angle=OMEGA * sdf.t, ...)``: its angle is an
expression of time, so the scene compiles once and the simulation evaluates it at its own time
every step; the particles are pushed by the blades (the response uses the velocity of the wall,
``-dd/dt / |grad d|`` along the normal). A GridSDF would freeze the scene, so the simulation
uses the exact SDF. ``make_simulation`` and ``stirrer_world`` are reused by the benchmark
(``python -m bench --only params``).
"""

import os
import sys
import time

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np

import fastsdf as sdf
import fastsdf.particles as phys
from fastsdf.viz.frames import VideoWriter
from fastsdf.viz.progress import Progress
from fastsdf.viz.render import draw_particles

#: Angular speed of the stirrer, rad/s (blade tips at 1.2 move at about 1 length/s).
OMEGA = 0.8
BOUNDS = [(-2.0, 2.0), (-2.0, 2.0)]


def stirrer_world(omega=OMEGA):
    """A box (inside [-1.9, 1.9]^2) with a four-bladed stirrer turning at ``omega`` rad/s
    around (0, -0.75), its blades sweeping just into the floor: negative inside the walls and
    the blades."""
    box = (
        sdf.Halfspace(normal=[0, 1], d=-1.9)
        | sdf.Halfspace(normal=[0, -1], d=-1.9)
        | sdf.Halfspace(normal=[1, 0], d=-1.9)
        | sdf.Halfspace(normal=[-1, 0], d=-1.9)
    )
    with sdf.transform(angle=omega * sdf.t, offset=[0.0, -0.75]):
        blades = sdf.Box(minc=[-1.2, -0.06], maxc=[1.2, 0.06]) | sdf.Box(
            minc=[-0.06, -1.2], maxc=[0.06, 1.2]
        )
        hub = sdf.Circle(center=[0.0, 0.0], radius=0.2)
    return box | blades | hub


def make_simulation(world, n=1_000_000, seed=0):
    """``n`` small particles dropped into the upper part of the box, under gravity."""
    sim = phys.ParticleSimulation(world, n=n, timestep=1 / 30, seed=seed, cr=0.3, cf=0.1)
    rng = np.random.default_rng(seed)
    sim.p["x"] = np.stack([rng.uniform(-1.8, 1.8, n), rng.uniform(0.7, 1.8, n)], axis=1)
    sim.p["v"] = 0.0
    sim.p["r"] = 0.004
    sim.force_generators.append(phys.Gravity((0.0, -2.0)))
    return sim


def _draw_walls(ax, world, t, grid):
    d = world(grid[0], grid[1], t=t)
    return ax.contourf(grid[0], grid[1], d, levels=[-1e9, 0.0], colors=["0.35"], zorder=2)


def main(out="examples-out", n=1_000_000, frames=300):
    """One run of ``frames`` steps: every step a video frame (the walls drawn at the frame's
    time by :class:`fastsdf.viz.frames.VideoWriter`), four of them the snapshots of the picture."""
    world = stirrer_world()
    sim = make_simulation(world, n=n)
    os.makedirs(out, exist_ok=True)
    shots = [0, frames // 3, 2 * frames // 3, frames]
    snapshots = []  # (t, step, positions)
    video = os.path.join(out, "moving_walls.mp4")
    title = f"{n:,} particles, a stirrer turning at {OMEGA} rad/s"
    t0 = time.perf_counter()
    with (
        VideoWriter(video, world, bounds=BOUNDS, size=(960, 720), title=title) as writer,
        Progress(frames + 1, "moving walls: steps and frames") as bar,
    ):
        for i in range(frames + 1):
            if i:
                sim.run(1)
            writer.add_simulation(sim)
            if i in shots:
                snapshots.append((sim.t, i, np.array(sim.p["x"], dtype=np.float64)))
            bar.step()
    run_s = time.perf_counter() - t0
    print(f"wrote {video} ({frames} steps and {frames + 1} frames in {run_s:.1f} s)")

    # Four snapshots side by side.
    xs = np.linspace(*BOUNDS[0], 400)
    ys = np.linspace(*BOUNDS[1], 400)
    grid = np.meshgrid(xs, ys)
    fig, axes = plt.subplots(1, 4, figsize=(16, 4.4), layout="constrained")
    for ax, (t, k, x) in zip(axes, snapshots):
        ax.set_xlim(*BOUNDS[0])
        ax.set_ylim(*BOUNDS[1])
        ax.set_aspect("equal")
        _draw_walls(ax, world, t, grid)
        draw_particles(ax, x[:, 0], x[:, 1], bounds=BOUNDS)
        ax.set_title(f"t = {t:.1f} s (step {k})")
    fig.suptitle(
        f"{n:,} particles and a stirrer turning at {OMEGA} rad/s "
        f"(the scene compiled once; {frames} steps)"
    )
    png = os.path.join(out, "moving_walls.png")
    fig.savefig(png, dpi=80)
    plt.close(fig)
    print(f"wrote {png}")
    return png, video


if __name__ == "__main__":
    small = os.environ.get("FASTSDF_EXAMPLE_SMALL") == "1"
    main(*sys.argv[1:], **({"n": 2000, "frames": 6} if small else {}))
