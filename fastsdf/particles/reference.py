"""The notebook's step in NumPy: the reference for tests and the baseline for benchmarks."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

__all__ = ["reference_step"]


def reference_step(
    p: Any, f: Any, dt: float, force_generators: Sequence = (), t: float = 0.0
) -> None:
    """One step of ``dt`` seconds of the notebook's ``ParticleSimulation.advance()``, in NumPy,
    in place.

    ``p`` is a :class:`Particles` (or a structured array with the same fields), ``f`` any SDF
    or GridSDF callable as ``f(x, y, compute_gradient=True)``. Forces are the sum of
    ``gen(p, t)`` over ``force_generators`` (Python callables; :class:`Gravity` and :class:`Drag`
    work too); then explicit Euler, one batch SDF query at the new positions, and the response
    wherever ``d - r <= 0`` (velocity responds regardless of ``v . n``, as in the notebook).
    This is what ``ParticleSimulation(..., integrator='euler', collision='notebook',
    prevent_tunnelling=False)`` computes in one fused compiled loop.
    """
    x, v = p["x"], p["v"]
    m = np.asarray(p["m"], dtype=np.float64)[:, None]
    force = np.zeros(x.shape)
    for gen in force_generators:
        force += gen(p, t)
    x += v * dt
    v += force / m * dt
    d, grad = f(x[:, 0], x[:, 1], compute_gradient=True)
    d = d - p["r"]
    c = np.flatnonzero(d <= 0)
    if c.size:
        g = grad[c]
        n = g / np.linalg.norm(g, axis=1)[:, None]
        vc = v[c]
        vn = (vc * n).sum(axis=1)[:, None] * n
        vt = vc - vn
        cr = np.asarray(p["cr"])[c][:, None]
        cf = np.asarray(p["cf"])[c][:, None]
        x[c] -= (1.0 + cr) * d[c][:, None] * n
        v[c] = -cr * vn + (1.0 - cf) * vt
