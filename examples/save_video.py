"""Particles in the seed world, saved as a video.

    python examples/save_video.py [OUT]          # OUT/particles.mp4 (.gif without ffmpeg)

``fastsdf.viz.render.animate`` animates a simulation from its current state (it never resets it);
``save_animation`` picks the writer from the extension. MP4 needs ffmpeg: a system one, or
``pip install 'fastsdf[video]'`` (imageio-ffmpeg ships a binary); otherwise this writes a GIF.
"""

import os
import sys

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt

import fastsdf as sdf
import fastsdf.particles as phys
from fastsdf.shapes.scenes import seed_world
from fastsdf.viz.render import animate, save_animation
from fastsdf.viz.video import ffmpeg_available


def main(out: str = "examples-out", n: int = 200_000, frames: int = 90) -> str:
    world = sdf.GridSDF(seed_world(), bounds=[(-2, 2), (-2, 2)], samples=[400j, 400j])
    sim = phys.ParticleSimulation(world, n=n, timestep=1 / 30, seed=0)
    sim.force_generators.append(phys.Gravity())
    sim.run(15)  # let them fall for half a second first: the video starts from here

    fig, ax = plt.subplots(figsize=(6.4, 5.6), layout="constrained")
    sdf.plot_sdf(world, ax=ax, filled=True, show_quiver=False, show_isolines="zero", ticks=True)
    anim = animate(sim, ax, frames=frames, steps_per_frame=2, colorbar=True,
                   title=f"{n:,} particles, ")
    os.makedirs(out, exist_ok=True)
    ext = ".mp4" if ffmpeg_available() else ".gif"
    path = save_animation(anim, os.path.join(out, "particles" + ext), fps=30)
    plt.close(fig)
    print(f"wrote {path}")
    return path


if __name__ == "__main__":
    small = os.environ.get("FASTSDF_EXAMPLE_SMALL") == "1"
    main(*sys.argv[1:], **({"n": 500, "frames": 3} if small else {}))
