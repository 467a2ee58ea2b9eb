"""A scene of your own from primitives, blends and modifiers, drawn with plot_sdf.
===============================================================================

    python examples/custom_scene.py [OUT]        # writes OUT/custom_scene.png (default
    ./examples-out)

A cup: a rounded box hollowed by a smaller one, a ring for a handle, a repeated row of holes, and
a smooth (quadratic) blend where the handle meets the body. Left: the filled shape with distance
isolines and a colour bar of the distance (negative inside); right: the gradient field.
"""

import os
import sys

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt

import fastsdf as sdf


def cup() -> sdf.SDF:
    body = sdf.RoundedBox([-0.8, -1.0], [0.8, 0.9], 0.25)
    hollow = sdf.RoundedBox([-0.6, -0.8], [0.6, 1.2], 0.15)
    handle = sdf.Ring([0.95, 0.0], 0.45, 0.15)
    holes = sdf.Circle([0, 0], 0.08).repeat([0.35, 1.0], [4, 1]).translate([-0.52, -0.9])
    shape = (body - hollow).union(handle, k=0.15, kind="quadratic")
    return shape - holes


def main(out: str = "examples-out") -> str:
    f = cup()
    os.makedirs(out, exist_ok=True)
    fig, (left, right) = plt.subplots(1, 2, figsize=(10, 4.4), layout="constrained")
    sdf.plot_sdf(f, ax=left, filled=True, show_quiver=False, show_isolines="all")
    left.set_title(f"a cup ({f.exactness}): solid and isolines of d")
    sdf.plot_sdf(f, ax=right, show_isolines="zero", show_quiver=True)
    right.set_title("grad d: arrows point out of the solid")
    path = os.path.join(out, "custom_scene.png")
    fig.savefig(path, dpi=90)
    plt.close(fig)
    print(f"wrote {os.path.abspath(path)}")
    return path


if __name__ == "__main__":
    main(*sys.argv[1:])
