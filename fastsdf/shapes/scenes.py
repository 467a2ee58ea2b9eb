"""The notebook's worlds, as reusable builders (used by the demo, the benchmarks and tests)."""

from __future__ import annotations

import numpy as np

from fastsdf.expr.graph import gc_paused
from fastsdf.expr.validate import count
from fastsdf.shapes import SDF, Box, Circle, Halfspace, smoothness, transform

__all__ = ["funnel", "seed_world", "box_world", "mixed_scene"]


def funnel() -> SDF:
    """The notebook's floor: three half-spaces forming a funnel (cells 13, 18 and 21)."""
    return (
        Halfspace(normal=[0, 1], d=-1.8)
        | Halfspace(normal=[1, 1], d=-1.8)
        | Halfspace(normal=[-1, 1], d=-1.8)
    )


def seed_world() -> SDF:
    """Notebook cell 21: the funnel, smoothly united (k=10) with a cut disc."""
    f = funnel()
    with smoothness(10):
        f |= Circle(center=[0, 0.0], radius=0.5) & Halfspace(normal=[0.1, 1], d=0.3)
    return f


def box_world(n_boxes: int = 20, seed: int = 0) -> SDF:
    """Notebook cell 13: the funnel and ``n_boxes`` random rotated boxes, united with
    smoothness 5. The random draws follow the notebook (angle in [-0.8, 0.8], offset in
    [-2, 2]^2, corners in [-0.3, -0.1] and [0.1, 0.3]) from ``numpy.random.default_rng(seed)``.
    """
    n_boxes = count(n_boxes, "n_boxes", 0)
    with gc_paused():  # a bulk build (see fastsdf.expr.graph._GCPaused)
        return _box_world(n_boxes, seed)


def _box_world(n_boxes: int, seed: int) -> SDF:
    rng = np.random.default_rng(seed)
    f = funnel()
    for _ in range(n_boxes):
        with (
            transform(angle=rng.uniform(-0.8, 0.8), offset=rng.uniform(-2, 2, size=2)),
            smoothness(5),
        ):
            f |= Box(minc=rng.uniform(-0.3, -0.1, size=2), maxc=rng.uniform(0.1, 0.3, size=2))
    return f


def mixed_scene(n: int, seed: int = 1) -> SDF:
    """A scene of ``n`` primitives without repeated structure next to each other: a floor and
    ``n - 1`` randomly placed and rotated circles and boxes, alternating kind, operation (union,
    intersection with a cut, union) and smoothness (0, 5, 10), from
    ``numpy.random.default_rng(seed)``. The worst case for code generation and compile time
    (used by the benchmarks and tests)."""
    n = count(n, "n")
    with gc_paused():  # a bulk build (see fastsdf.expr.graph._GCPaused)
        return _mixed_scene(n, seed)


def _mixed_scene(n: int, seed: int) -> SDF:
    rng = np.random.default_rng(seed)
    f: SDF = Halfspace([0, 1], -1.8)
    for i in range(int(n) - 1):
        with (
            transform(angle=rng.uniform(-3, 3), offset=rng.uniform(-2, 2, 2)),
            smoothness([0, 5, 10][i % 3]),
        ):
            s = (
                Circle([0, 0], rng.uniform(0.1, 0.3))
                if i % 2
                else Box(-rng.uniform(0.1, 0.3, 2), rng.uniform(0.1, 0.3, 2))
            )
            # (only the operation used is built: the same scene as building all three)
            f = f & (Circle([0, 0], 3.0) - s) if i % 3 == 1 else f | s
    return f
