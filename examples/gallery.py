"""Render one small picture per primitive, modifier and blend into docs/gallery.png.
=================================================================================

    python examples/gallery.py [output.png]

Each panel is ``fastsdf.plot_sdf(..., filled=True, show_quiver=False)`` with the surface drawn
thick and distance isolines every 0.25 (light and dashed inside, where ``d < 0``): where a shape is
``'exact'`` the isolines are evenly spaced offsets of its outline (rounded around corners); where
it is only a ``'bound'`` they bunch up or stay sharp (e.g. outside the corners of an
intersection). Its title names the shape and its ``exactness``.
"""

import math
import os
import sys

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np

import fastsdf as sdf
from fastsdf.viz.plotting import sdf_grid
from fastsdf.viz.progress import progress


def panels():
    star = sdf.Star([0, 0], 1.1, 5, 0.5)
    a, b = sdf.Circle([-0.45, -0.1], 0.6), sdf.Box([-0.1, -0.5], [0.9, 0.45])
    with sdf.transform(angle=0.3):
        tri = sdf.EquilateralTriangle([0, 0], 1.0)
    return [
        ("Circle", sdf.Circle([0.1, -0.1], 0.9)),
        ("Box", sdf.Box([-1.0, -0.6], [0.9, 0.7])),
        ("Halfspace", sdf.Halfspace([0.3, 1.0], -0.2)),
        ("Segment", sdf.Segment([-1, -0.6], [1, 0.7])),
        ("Capsule", sdf.Capsule([-0.9, -0.5], [0.8, 0.6], 0.35)),
        ("RoundedBox", sdf.RoundedBox([-1.1, -0.7], [1.1, 0.7], [0.1, 0.6, 0.0, 0.3])),
        ("OrientedBox", sdf.OrientedBox([-1, -0.7], [0.9, 0.8], 0.6)),
        ("Triangle", sdf.Triangle([-1.1, -0.8], [1.2, -0.4], [-0.2, 1.0])),
        ("EquilateralTriangle", sdf.EquilateralTriangle([0, -0.1], 1.1)),
        ("RegularPolygon n=7", sdf.RegularPolygon([0, 0], 1.1, 7)),
        ("Polygon", sdf.Polygon([[-1.1, -1], [1.1, -1], [1.1, 1], [0.2, -0.2], [-1.1, 1]])),
        ("Star", star),
        ("Ellipse", sdf.Ellipse([0, 0], [1.2, 0.5])),
        ("Ellipse 1000:1", sdf.Ellipse([0, 0], [1.2, 1.2e-3]).round(0.05)),
        ("Arc", sdf.Arc([0, -0.2], 0.9, 4.0, 0.3)),
        ("Ring", sdf.Ring([0, 0], 0.9, 0.35)),
        ("star.round(0.15)", star.round(0.15)),
        ("star.shell(0.12)", star.shell(0.12)),
        ("tri.scale(0.5)", tri.scale(0.5)),
        ("tri.rotate(.5).translate", tri.scale(0.7).rotate(0.5).translate([0.3, 0.1])),
        ("Circle.mirror('x')", sdf.Circle([0.6, 0.3], 0.45).mirror("x")),
        (
            "hexagon.repeat(0.7, 4)",
            sdf.RegularPolygon([0, 0], 0.3, 6).repeat(0.7, 4).translate([-1.05, -1.05]),
        ),
        ("union (hard)", a | b),
        ("union exponential k=8", a.union(b, k=8.0)),
        ("union quadratic k=0.4", a.union(b, k=0.4, kind="quadratic")),
        ("union cubic k=0.4", a.union(b, k=0.4, kind="cubic")),
        (
            "intersection quadratic",
            sdf.Circle([-0.3, -0.1], 0.9).intersection(b, k=0.4, kind="quadratic"),
        ),
        (
            "difference cubic",
            sdf.Box([-1.1, -0.7], [1.1, 0.7]).difference(
                sdf.Circle([0.6, 0.4], 0.6), k=0.3, kind="cubic"
            ),
        ),
    ]


def default_out() -> str:
    """docs/gallery.png of this checkout."""
    return os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "docs", "gallery.png")


def main(out: str | None = None) -> str:
    out = out or default_out()
    items = panels()
    cols = 6
    rows = math.ceil(len(items) / cols)
    fig, axes = plt.subplots(rows, cols, figsize=(2.3 * cols, 2.45 * rows + 0.4))
    bounds = [(-1.5, 1.5), (-1.5, 1.5)]
    levels = np.arange(-1.5, 2.26, 0.25)
    with progress(len(items), "gallery") as bar:
        for ax, (name, f) in zip(axes.flat, items):
            sdf.plot_sdf(
                fig,
                ax,
                f,
                bounds=bounds,
                samples=160,
                filled=True,
                show_quiver=False,
                show_isolines=None,
                axes=False,  # small panels: the shapes alone, no ticks
            )
            xs, ys, d = sdf_grid(f, bounds, 160)
            ax.contour(xs, ys, d, levels=levels[levels > 0], colors="#8a6f3a", linewidths=0.6)
            ax.contour(
                xs,
                ys,
                d,
                levels=levels[levels < 0],
                colors="#c9d6e3",
                linewidths=0.6,
                linestyles="--",
            )
            ax.contour(xs, ys, d, levels=[0.0], colors="#1b1b1b", linewidths=1.4)
            ax.set_title(f"{name}\n{f.exactness}", fontsize=8)
            bar.update(1)
    for ax in list(axes.flat)[len(items) :]:
        ax.axis("off")
    fig.suptitle(
        "fastsdf primitives, modifiers and blends: solid (d < 0) dark, isolines of d "
        "every 0.25 (dashed inside), surface in black; title: exactness",
        fontsize=10,
    )
    fig.tight_layout(rect=(0, 0, 1, 0.975))
    os.makedirs(os.path.dirname(os.path.abspath(out)), exist_ok=True)
    fig.savefig(out, dpi=80)
    print(f"wrote {os.path.abspath(out)}")
    return out


if __name__ == "__main__":
    main(*sys.argv[1:])
