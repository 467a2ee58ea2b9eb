"""Sand in the notebook's world: grains poured from a hopper build a cone on the disc.
===================================================================================

    python examples/sand.py [OUT]        # OUT/sand.png and OUT/sand.mp4 (.gif without ffmpeg)

The same ``ParticleSimulation`` as the notebook's, given start positions, radii and a contact
law: ``contacts=phys.ContactLaw(history=True, rolling_friction=0.5)`` makes the particles
grains (soft-sphere DEM) with static friction and rolling resistance, so that they hold a
slope. Without a stiffness the law derives one from the grains, their density and gravity (a
column of grains as tall as the world overlaps by 1% of a diameter), and the simulation cuts
each 1/30 s step into as many substeps as that contact needs. The world is the notebook's with
a hopper above its disc (``fastsdf.apps.demo.sand_world``, the world of ``fastsdf demo --scene
sand``): the grains build a cone on the disc, whose angle of repose
``fastsdf.granular.repose_angle`` measures, and what runs off it fills the funnel. Everything
else is the particle family's: gravity in ``force_generators``, ``sim.p['x']``, ``sim.run``,
the video and the picture.
"""

import os
import sys

import matplotlib

matplotlib.use("Agg")
import numpy as np

import fastsdf as sdf
import fastsdf.particles as phys
from fastsdf.apps.demo import hopper_fill, sand_world
from fastsdf.granular import repose_angle
from fastsdf.viz.frames import record_video
from fastsdf.viz.render import animate, render_frame, save_animation, sim_title, world_figure
from fastsdf.viz.video import ffmpeg_available


def main(out: str = "examples-out", n: int = 900, frames: int = 180) -> str:
    world = sand_world("seed")
    # mode="exact": the hopper rises above the grid; beyond it the exact SDF answers
    grid = sdf.GridSDF(world, bounds=[(-2, 2), (-2, 2)], samples=[400j, 400j], mode="exact")
    rng = np.random.default_rng(0)
    radius = 0.022 * rng.uniform(0.9, 1.1, n)  # unequal discs: equal ones stack as a crystal
    sim = phys.ParticleSimulation(
        grid,
        positions=hopper_fill(n, radius, rng),
        radius=radius,
        contacts=phys.ContactLaw(history=True, rolling_friction=0.5),
    )
    # the world read in metres: the Earth's gravity (Gravity() is the notebook's (0, -1))
    sim.force_generators.append(phys.Gravity((0.0, -9.81)))
    print(f"{n} grains, {sim.substeps_per_frame} substeps per 1/30 s step")

    os.makedirs(out, exist_ok=True)
    if ffmpeg_available():
        video = record_video(
            sim,
            os.path.join(out, "sand.mp4"),
            frames=frames,
            steps_per_frame=1,
            world=world,
            size=(640, 560),
            fps=30,
            title=f"{n:,} grains",
        )
    else:
        fig, ax, _ = world_figure(world, ((-2, 2), (-2, 2)), 400, (6.4, 5.6), 100)
        anim = animate(sim, ax, frames=frames, title=f"{n:,} grains, ")
        video = save_animation(anim, os.path.join(out, "sand.gif"), fps=30)
    x, v, r = sim.p["x"], sim.p["v"], sim.p["r"]
    # the cone: grains at rest on the disc (|x| <= 0.5, its top near y = 0.3)
    cone = (np.hypot(v[:, 0], v[:, 1]) < 0.05) & (np.abs(x[:, 0]) < 0.6) & (x[:, 1] > 0.0)
    cone &= x[:, 1] < 0.95  # below the hopper's outlet
    angle = repose_angle(x[cone], r[cone], bin_width=0.022)  # bins one radius wide
    print(
        f"cone on the disc: {int(cone.sum())} grains at rest; angle of repose "
        f"{angle.left:.1f} (left) and {angle.right:.1f} (right) degrees (nan: no cone yet)"
    )
    png = os.path.join(out, "sand.png")
    render_frame(
        world,
        x[:, 0],
        x[:, 1],
        r=r,
        out_png=png,
        title=sim_title(sim, f"{n:,} grains, "),
        colorbar=False,
    )
    print(f"wrote {video} and {png}")
    return png


if __name__ == "__main__":
    small = os.environ.get("FASTSDF_EXAMPLE_SMALL") == "1"
    main(*sys.argv[1:], **({"n": 192, "frames": 45} if small else {}))
