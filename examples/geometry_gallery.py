"""Worlds from a grey-level image, an SVG drawing and a word, with particles poured over them.
===========================================================================================

    python examples/geometry_gallery.py [output.png]     # default: docs/geometry_gallery.png

Each panel shows the SDF (solid dark, isolines every 0.25), its zero contour from
``fastsdf.geometry.contours`` (orange: vertices refined on the SDF itself) and particles that
fell onto it under gravity (a grid of the world, as simulations use it).
"""

import os
import sys

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np

import fastsdf as sdf
from fastsdf.geometry import SvgPath, Text, contours, from_image
from fastsdf.particles import Gravity, ParticleSimulation

BOUNDS = [(-2.0, 2.0), (-2.0, 2.0)]

# A heart drawn with cubic Beziers, a round window cut by two arcs (even-odd), a quadratic lid.
HEART = (
    "M 0 -25 C -5 -42 -40 -45 -42 -15 C -43 8 -12 25 0 42 C 12 25 43 8 42 -15 "
    "C 40 -45 5 -42 0 -25 Z M -9 -8 A 9 9 0 1 0 9 -8 A 9 9 0 1 0 -9 -8 Z "
    "M -30 -48 Q 0 -62 30 -48 L 30 -44 Q 0 -58 -30 -44 Z"
)


def micrograph(n: int = 240, seed: int = 3) -> np.ndarray:
    """A photo-like grey image: smooth random blobs, anti-aliased at their threshold."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:n, 0:n] / n
    field = np.zeros((n, n))
    for cx, cy, r in zip(
        rng.uniform(0, 1, 40), rng.uniform(0.0, 0.75, 40), rng.uniform(0.03, 0.09, 40), strict=True
    ):
        field += np.exp(-((xx - cx) ** 2 + (yy - cy) ** 2) / (2 * r * r))
    # a soft edge of about one pixel around the level 0.6 (as a camera would blur it)
    grad = np.hypot(*np.gradient(field)) + 1e-9
    return np.clip(0.5 + (field - 0.6) / grad, 0.0, 1.0)[::-1]  # row 0 at the top


def worlds():
    image = micrograph()
    mask_world = from_image(image, BOUNDS)
    heart = SvgPath(HEART, fill_rule="evenodd", scale=0.03, offset=(0.0, -0.4))
    word = Text("fastsdf", size=1.1, position=(-1.95, -1.2))
    return [
        ("grey-level image (240 x 240, anti-aliased): from_image", mask_world, mask_world),
        ("SVG path: cubics, arcs, a quadratic; even-odd: SvgPath", heart, None),
        ("matplotlib TextPath glyphs: Text('fastsdf')", word, None),
    ]


def pour(world, n=700, steps=360, seed=0):
    """Particles dropped from the top of the box onto ``world``; their final positions."""
    sim = ParticleSimulation(world, n=n, timestep=1 / 30, seed=seed, cr=0.2, lipschitz=1.5)
    sim.force_generators.append(Gravity(acceleration=(0.0, -1.0)))
    rng = np.random.default_rng(seed)
    sim.p["x"][:, 0] = rng.uniform(-1.9, 1.9, n)
    sim.p["x"][:, 1] = rng.uniform(1.2, 1.95, n)
    sim.p["v"][:] = 0.0
    sim.p["r"][:] = 0.018
    sim.run(steps)
    return sim.p["x"].copy()


def default_out() -> str:
    """docs/geometry_gallery.png of this checkout."""
    return os.path.join(
        os.path.dirname(os.path.abspath(__file__)), "..", "docs", "geometry_gallery.png"
    )


def main(out: str | None = None, n: int = 700, steps: int = 360) -> str:
    out = out or default_out()
    panels = worlds()
    fig, axes = plt.subplots(1, len(panels), figsize=(5.2 * len(panels), 5.6))
    floor = (
        sdf.Halfspace([0, 1], -1.97) | sdf.Halfspace([1, 0], -1.97) | sdf.Halfspace([-1, 0], -1.97)
    )
    for ax, (title, f, grid) in zip(axes, panels, strict=True):
        sdf.plot_sdf(
            f, ax=ax, bounds=BOUNDS, samples=300, filled=True, show_quiver=False, colorbar=False
        )
        for c in contours(f, bounds=BOUNDS, resolution=200):
            p = np.vstack([c.points, c.points[:1]]) if c.closed else c.points
            ax.plot(p[:, 0], p[:, 1], color="#e8702a", lw=1.2, zorder=3)  # over the surface
        # the particles' world: the shape and the box's walls and floor, as a grid
        if grid is None:
            grid = sdf.GridSDF(
                f | floor, bounds=BOUNDS, samples=[300j, 300j], mode="nearest", gradient="fd"
            )
        else:
            grid = from_image(np.maximum(micrograph(), _walls(240)), BOUNDS)
        x = pour(grid, n=n, steps=steps)
        ax.scatter(x[:, 0], x[:, 1], s=4, color="#2a9df4", lw=0)
        ax.set_title(title, fontsize=10)
    fig.suptitle(
        "fastsdf.geometry: worlds from pixels, SVG paths and text (orange: "
        f"contours refined on the SDF; blue: {n} particles poured over each)",
        fontsize=11,
    )
    fig.tight_layout()
    fig.savefig(out, dpi=90)
    plt.close(fig)
    return out


def _walls(n: int) -> np.ndarray:
    """Solid pixels along the image's left, right and bottom edges (the particles' box)."""
    w = np.zeros((n, n))
    w[-2:] = 1.0
    w[:, :2] = 1.0
    w[:, -2:] = 1.0
    return w


if __name__ == "__main__":
    small = os.environ.get("FASTSDF_EXAMPLE_SMALL") == "1"
    print(main(*sys.argv[1:], **({"n": 200, "steps": 150} if small else {})))
