"""Particles in the seed world, saved as a video.
==============================================

    python examples/save_video.py [OUT]          # OUT/particles.mp4 (.gif without ffmpeg)

``fastsdf.viz.frames.record_video`` runs a simulation from its current state (it never resets
it) and writes a frame every few steps: the world, axes and colour bar are drawn once, the
particles splatted per frame in compiled code, one colour scale for the whole video. MP4 needs
ffmpeg: a system one, or ``pip install 'fastsdf[video]'`` (imageio-ffmpeg ships a binary);
without it this writes a GIF through Matplotlib (``fastsdf.viz.render.animate`` and
``save_animation``, a figure drawn per frame).
"""

import os
import sys

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt

import fastsdf as sdf
import fastsdf.particles as phys
from fastsdf.shapes.scenes import seed_world
from fastsdf.viz.frames import record_video
from fastsdf.viz.render import animate, save_animation
from fastsdf.viz.video import ffmpeg_available


def main(out: str = "examples-out", n: int = 200_000, frames: int = 90) -> str:
    world = sdf.GridSDF(seed_world(), bounds=[(-2, 2), (-2, 2)], samples=[400j, 400j])
    sim = phys.ParticleSimulation(world, n=n, timestep=1 / 30, seed=0)
    sim.force_generators.append(phys.Gravity())
    sim.run(15)  # let them fall for half a second first: the video starts from here

    os.makedirs(out, exist_ok=True)
    if ffmpeg_available():
        # one colour scale for the whole video, with room for the pile on the floor
        path = record_video(
            sim,
            os.path.join(out, "particles.mp4"),
            frames=frames,
            steps_per_frame=2,
            world=seed_world(),
            size=(640, 560),
            fps=30,
            title=f"{n:,} particles",
            vmax=max(10.0, n / 1000),
        )
    else:
        fig, ax = plt.subplots(figsize=(6.4, 5.6), layout="constrained")
        sdf.plot_sdf(world, ax=ax, filled=True, show_quiver=False, show_isolines="zero")
        anim = animate(
            sim, ax, frames=frames, steps_per_frame=2, colorbar=True, title=f"{n:,} particles, "
        )
        path = save_animation(anim, os.path.join(out, "particles.gif"), fps=30)
        plt.close(fig)
    print(f"wrote {path}")
    return path


if __name__ == "__main__":
    small = os.environ.get("FASTSDF_EXAMPLE_SMALL") == "1"
    main(*sys.argv[1:], **({"n": 500, "frames": 3} if small else {}))
