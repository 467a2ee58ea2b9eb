"""Sand in the notebook's world: grains that collide with each other as well as with the world.
============================================================================================

    python examples/sand.py [OUT]        # OUT/sand.png and OUT/sand.mp4 (.gif without ffmpeg)

The same ``ParticleSimulation`` as the notebook's, given start positions, a radius and a contact
law: ``contacts=phys.ContactLaw()`` makes the particles grains (soft-sphere DEM). Without a
stiffness the law derives one from the grains, their density and gravity (a column of grains
as tall as the world overlaps by 1% of a diameter), and the simulation cuts each 1/30 s step
into as many substeps as that contact needs. Everything else is the particle family's: gravity
in ``force_generators``, ``sim.p['x']``, ``sim.run``, the video and the picture.
"""

import os
import sys

import matplotlib

matplotlib.use("Agg")
import numpy as np

import fastsdf as sdf
import fastsdf.particles as phys
from fastsdf.shapes.scenes import seed_world
from fastsdf.viz.frames import record_video
from fastsdf.viz.render import animate, render_frame, save_animation, sim_title, world_figure
from fastsdf.viz.video import ffmpeg_available


def block_of_grains(n: int, radius: float, rng: np.random.Generator) -> np.ndarray:
    """``n`` grain centres in a block 16 grains wide above the world's disc, a little apart."""
    i = np.arange(n)
    pitch = 2.3 * radius
    pos = np.stack([(i % 16 - 7.5) * pitch + 0.3, 0.8 + (i // 16) * pitch], 1)
    return pos + rng.uniform(-0.1 * radius, 0.1 * radius, pos.shape)


def main(out: str = "examples-out", n: int = 1200, frames: int = 60) -> str:
    world = sdf.GridSDF(seed_world(), bounds=[(-2, 2), (-2, 2)], samples=[400j, 400j])
    radius = 0.02
    sim = phys.ParticleSimulation(
        world,
        positions=block_of_grains(n, radius, np.random.default_rng(0)),
        radius=radius,
        contacts=phys.ContactLaw(restitution=0.3),
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
            world=seed_world(),
            size=(640, 560),
            fps=30,
            title=f"{n:,} grains",
        )
    else:
        fig, ax, _ = world_figure(seed_world(), ((-2, 2), (-2, 2)), 400, (6.4, 5.6), 100)
        anim = animate(sim, ax, frames=frames, title=f"{n:,} grains, ")
        video = save_animation(anim, os.path.join(out, "sand.gif"), fps=30)
    x = sim.p["x"]
    png = os.path.join(out, "sand.png")
    render_frame(
        seed_world(),
        x[:, 0],
        x[:, 1],
        r=sim.p["r"],
        out_png=png,
        title=sim_title(sim, f"{n:,} grains, "),
        colorbar=False,
    )
    print(f"wrote {video} and {png}")
    return png


if __name__ == "__main__":
    small = os.environ.get("FASTSDF_EXAMPLE_SMALL") == "1"
    main(*sys.argv[1:], **({"n": 192, "frames": 45} if small else {}))
