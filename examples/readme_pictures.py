"""The README's pictures: what fastsdf is, an SDF and its gradient, particles in the notebook's
funnel, grains pouring and heaping, a word and an image turned into worlds.

    python examples/readme_pictures.py [DIR] [--small]

Writes ``readme_hero.png``, ``readme_sdf.png``, ``readme_particles.png``, ``readme_grains.png``
and ``readme_geometry.png`` into ``DIR`` (default ``docs/images``). ``--small`` (or
``FASTSDF_EXAMPLE_SMALL=1``, as for the other examples) runs every simulation at a fraction of
its size, as the test suite does; the committed pictures are the full size. Each picture shows
the scene of the README block beside it, at the picture's own sizes (the grains through
``fastsdf.granular.GranularSimulation``, the engine under ``ParticleSimulation(contacts=...)``).
"""

from __future__ import annotations

import argparse
import os

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
from matplotlib.cbook import get_sample_data

import fastsdf as sdf
from fastsdf.geometry import Text, from_image
from fastsdf.granular import ContactLaw, GranularSimulation
from fastsdf.particles import Gravity, ParticleSimulation
from fastsdf.viz.render import draw_particles

HERE = os.path.dirname(os.path.abspath(__file__))
OUT = os.path.join(HERE, "..", "docs", "images")
BOUNDS = [(-2.0, 2.0), (-2.0, 2.0)]
DPI = 80
NAMES = ("hero", "sdf", "particles", "grains", "geometry")


def funnel_world() -> sdf.SDF:
    """The notebook's world (cell 21): a funnel and, under smoothness 10, a cut disc."""
    f = sdf.Halfspace(normal=[0, 1], d=-1.8) | sdf.Halfspace(normal=[1, 1], d=-1.8)
    f |= sdf.Halfspace(normal=[-1, 1], d=-1.8)
    with sdf.smoothness(10):
        f |= sdf.Circle(center=[0, 0], radius=0.5) & sdf.Halfspace(normal=[0.1, 1], d=0.3)
    return f


def _world_axes(ax, f, bounds=BOUNDS, isolines="zero", samples=300) -> None:
    sdf.plot_sdf(
        f,
        ax=ax,
        bounds=bounds,
        samples=samples,
        show_quiver=False,
        show_isolines=isolines,
        filled=True,
    )


def picture_sdf(out: str) -> None:
    """The funnel's distance (isolines, labelled) and its gradient (arrows)."""
    f = funnel_world()
    fig, ax = plt.subplots(figsize=(5.2, 5.2), dpi=DPI)
    sdf.plot_sdf(
        f,
        ax=ax,
        show_quiver=True,
        show_isolines="all",
        show_isolabels=True,
        filled=True,
        colorbar=True,
    )
    ax.set_title("f(x, y): distance (lines, negative inside)\nand its gradient (arrows)")
    fig.tight_layout()
    fig.savefig(os.path.join(out, "readme_sdf.png"))
    plt.close(fig)


def picture_particles(out: str, small: bool) -> None:
    """The notebook's scenario: particles dropped from a blob into the funnel, three moments."""
    f = funnel_world()
    grid = sdf.GridSDF(f, bounds=BOUNDS, samples=[400j, 400j])
    sim = ParticleSimulation(grid, n=2_000 if small else 20_000, timestep=1 / 30, seed=0)
    sim.force_generators += [Gravity()]
    fig, axes = plt.subplots(1, 3, figsize=(10.5, 3.8), dpi=DPI)
    for ax, steps in zip(axes, (0, 60, 240), strict=True):
        sim.run(steps - round(sim.t / sim.dt))
        _world_axes(ax, f)
        x = sim.p["x"]
        draw_particles(ax, x[:, 0], x[:, 1], r=sim.p["r"], bounds=BOUNDS)
        ax.set_title(f"step {steps} (t = {sim.t:.1f} s)")
    fig.suptitle(
        f"{sim.p['x'].shape[0]:,} particles falling into the notebook's funnel "
        "(no particle-particle contacts)"
    )
    fig.tight_layout()
    fig.savefig(os.path.join(out, "readme_particles.png"))
    plt.close(fig)


def pour(small: bool) -> tuple:
    """Grains released as a column above the funnel; their states at a few frames."""
    f = funnel_world()
    r = 0.03 if small else 0.022
    nx, ny = (10, 12) if small else (22, 40)
    gx, gy = np.meshgrid(np.arange(nx), np.arange(ny))
    xy = np.column_stack([(gx.ravel() - (nx - 1) / 2) * 2.05 * r, 0.75 + gy.ravel() * 2.05 * r])
    xy[:, 0] += np.random.default_rng(0).uniform(-0.1, 0.1, len(xy)) * r  # break the lattice
    # stiffness: a column as tall as the world overlaps by about 1% of a diameter
    m = np.pi * r * r
    stiffness = 4.0 / (2 * r) * m * 1.0 / (0.01 * 2 * r)
    sim = GranularSimulation(
        f,
        positions=xy,
        radius=r,
        contacts=ContactLaw(stiffness=stiffness, history=True, rolling_friction=0.3),
        gravity=(0.0, -1.0),
        timestep=1 / 30,
    )
    frames = (0, 40, 160) if small else (0, 45, 240)
    states = []
    for k in frames:
        sim.run(k - (states[-1][0] if states else 0))
        states.append((k, sim.positions, sim.radius, np.linalg.norm(sim.velocities, axis=1)))
    return f, states


def _grains(ax, x, r, speed) -> None:
    from matplotlib.collections import EllipseCollection

    ax.add_collection(
        EllipseCollection(
            2 * r,
            2 * r,
            0.0,
            units="xy",
            offsets=x,
            offset_transform=ax.transData,
            array=speed,
            cmap="YlOrBr_r",
            clim=(0.0, 1.5),
            edgecolors="#5a3a12",
            linewidths=0.3,
            zorder=5,
        )
    )


def picture_grains(out: str, f, states) -> None:
    fig, axes = plt.subplots(1, 3, figsize=(10.5, 3.8), dpi=DPI)
    for ax, (k, x, r, speed) in zip(axes, states, strict=True):
        _world_axes(ax, f)
        _grains(ax, x, r, speed)
        ax.set_title(f"frame {k} (t = {k / 30:.1f} s)")
    fig.suptitle(
        f"{len(states[0][1]):,} grains poured into the funnel collide, stick and heap "
        "on the disc (lighter = faster)"
    )
    fig.tight_layout()
    fig.savefig(os.path.join(out, "readme_grains.png"))
    plt.close(fig)


def picture_hero(out: str, small: bool) -> None:
    """A word as a world (an exact SDF of its glyphs, on a floor), grains poured onto it."""
    world = Text("fastsdf", size=1.05, position=(-1.9, -0.6)) | sdf.Halfspace([0, 1], -1.0)
    bounds = [(-2.0, 2.0), (-1.1, 1.3)]
    # grains meet a 400 x 240 grid of the world (a bilinear query instead of 400 glyph segments)
    grid = sdf.GridSDF(world, bounds=[(-2.2, 2.2), (-1.3, 1.5)], samples=[400j, 240j])
    r = 0.03 if small else 0.016
    nx, ny = (40, 4) if small else (110, 12)
    gx, gy = np.meshgrid(np.arange(nx), np.arange(ny))
    xy = np.column_stack([-1.9 + gx.ravel() * 3.8 / (nx - 1), 0.75 + gy.ravel() * 2.1 * r])
    xy[:, 0] += np.random.default_rng(2).uniform(-0.2, 0.2, len(xy)) * r
    m = np.pi * r * r
    sim = GranularSimulation(
        grid,
        positions=xy,
        radius=r,
        contacts=ContactLaw(stiffness=100 * m / (0.01 * 2 * r)),
        gravity=(0.0, -1.0),
        timestep=1 / 30,
    )
    sim.run(40 if small else 120)
    fig, ax = plt.subplots(figsize=(6.4, 4.0), dpi=DPI)
    _world_axes(ax, world, bounds=bounds, isolines="all", samples=(400, 240))
    _grains(ax, sim.positions, sim.radius, np.linalg.norm(sim.velocities, axis=1))
    ax.set_title(f"Text('fastsdf') as an SDF (lines: distance), {len(xy):,} grains poured on it")
    fig.tight_layout()
    fig.savefig(os.path.join(out, "readme_hero.png"))
    plt.close(fig)


def picture_geometry(out: str, small: bool) -> None:
    """Text('fastsdf') as an exact SDF; matplotlib's logo image as a grid world with particles."""
    word = Text("fastsdf", size=1.0, position=(-1.8, -0.3))
    image = plt.imread(get_sample_data("logo2.png", asfileobj=False))
    # the logo's background is transparent: composite it over white
    grey = image[..., :3].mean(axis=-1) * image[..., 3] + (1.0 - image[..., 3])
    h, w = grey.shape
    wb = [(-2.0, 2.0), (-2.0 * h / w, 2.0 * h / w)]
    logo = from_image(grey, wb, threshold=0.5, dark_inside=True)
    sim = ParticleSimulation(logo, n=500 if small else 3_000, timestep=1 / 60, seed=1)
    rng = np.random.default_rng(1)
    sim.p["x"][:, 0] = rng.uniform(-2.0, 2.0, sim.p["x"].shape[0])
    sim.p["x"][:, 1] = rng.uniform(wb[1][1] + 0.1, wb[1][1] + 0.6, sim.p["x"].shape[0])
    sim.p["r"][:] = 0.01
    sim.force_generators += [Gravity(acceleration=(0.0, -2.0))]
    sim.run(60 if small else 240)  # 4 s: they rest on the letters or fall between them

    fig, (a1, a2) = plt.subplots(2, 1, figsize=(7.0, 5.6), dpi=DPI)
    wbounds = [(-2.0, 2.0), (-0.8, 0.8)]
    sdf.plot_sdf(
        word,
        ax=a1,
        bounds=wbounds,
        samples=(400, 160) if not small else (200, 80),
        show_quiver=False,
        show_isolines="all",
        filled=True,
    )
    a1.axhline(-0.3, color="tab:red", lw=0.8, ls="--")
    a1.set_title("Text('fastsdf', size=1.0, position=(-1.8, -0.3)): baseline dashed")
    lb = [(-2.0, 2.0), (wb[1][0], wb[1][1] + 0.7)]
    _world_axes(a2, logo, bounds=lb, isolines="zero", samples=(400, 160))
    x = sim.p["x"]
    draw_particles(a2, x[:, 0], x[:, 1], r=sim.p["r"], bounds=lb)
    a2.set_title("from_image(matplotlib's logo): particles poured on it rest on the letters")
    fig.tight_layout()
    fig.savefig(os.path.join(out, "readme_geometry.png"))
    plt.close(fig)


def main(out: str = OUT, small: bool = False) -> list[str]:
    """Write every picture into ``out``; returns their paths."""
    os.makedirs(out, exist_ok=True)
    picture_hero(out, small)
    picture_sdf(out)
    picture_particles(out, small)
    f, states = pour(small)
    picture_grains(out, f, states)
    picture_geometry(out, small)
    return [os.path.join(out, f"readme_{n}.png") for n in NAMES]


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=(__doc__ or "").strip().split("\n")[0])
    parser.add_argument("out", nargs="?", default=OUT, help="output folder (default docs/images)")
    parser.add_argument("--small", action="store_true", help="small simulations (tests)")
    args = parser.parse_args()
    small = args.small or os.environ.get("FASTSDF_EXAMPLE_SMALL", "") not in ("", "0")
    for path in main(args.out, small):
        print(path)
