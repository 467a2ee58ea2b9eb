"""A tiny stand-in for ``fastsdf.GridSDF`` (branch ``grid``), following its contract, so that
the particle tests can exercise the grid path before the real class is merged.

Remove once ``fastsdf.GridSDF`` is on ``main``.
"""

import math

import numpy as np
from numba import njit


@njit(cache=True, nogil=True, inline="always")
def standin_sampler(data, x, y):
    """Bilinear interpolation of sampled value and gradient: (d, gx, gy, inside)."""
    x0, y0, ihx, ihy, table = data
    nx = table.shape[1]
    ny = table.shape[0]
    u = (x - x0) * ihx
    w = (y - y0) * ihy
    inside = (u >= 0.0) and (u <= nx - 1.0) and (w >= 0.0) and (w <= ny - 1.0)
    u = min(max(u, 0.0), nx - 1.0)
    w = min(max(w, 0.0), ny - 1.0)
    if not (u == u and w == w):
        return math.nan, math.nan, math.nan, False
    i = min(int(u), nx - 2)
    j = min(int(w), ny - 2)
    fu = u - i
    fw = w - j
    a = (1.0 - fu) * (1.0 - fw)
    b = fu * (1.0 - fw)
    c = (1.0 - fu) * fw
    e = fu * fw
    d = a * table[j, i, 0] + b * table[j, i + 1, 0] + c * table[j + 1, i, 0] + e * table[j + 1, i + 1, 0]
    gx = a * table[j, i, 1] + b * table[j, i + 1, 1] + c * table[j + 1, i, 1] + e * table[j + 1, i + 1, 1]
    gy = a * table[j, i, 2] + b * table[j, i + 1, 2] + c * table[j + 1, i, 2] + e * table[j + 1, i + 1, 2]
    return d, gx, gy, inside


class StandinGridSDF:
    """``StandinGridSDF(f, bounds=[(-2, 2), (-2, 2)], samples=[400j, 400j], mode='exact')``."""

    def __init__(self, f, bounds=((-2, 2), (-2, 2)), samples=(400j, 400j), mode="exact"):
        (xa, xb), (ya, yb) = bounds
        nx, ny = int(abs(samples[0])), int(abs(samples[1]))
        xs = np.linspace(xa, xb, nx)
        ys = np.linspace(ya, yb, ny)
        X, Y = np.meshgrid(xs, ys)
        d, g = f(X.ravel(), Y.ravel(), compute_gradient=True)
        table = np.empty((ny, nx, 3))
        table[..., 0] = d.reshape(ny, nx)
        table[..., 1] = g[:, 0].reshape(ny, nx)
        table[..., 2] = g[:, 1].reshape(ny, nx)
        self.spacing = ((xb - xa) / (nx - 1), (yb - ya) / (ny - 1))
        self.exact = f
        self.mode = mode
        self.sampler = standin_sampler
        self.sampler_data = (float(xa), float(ya), (nx - 1) / (xb - xa), (ny - 1) / (yb - ya), table)

    def __call__(self, x, y, compute_gradient=False):
        xs = np.asarray(x, dtype=np.float64).ravel()
        ys = np.asarray(y, dtype=np.float64).ravel()
        out = np.empty((xs.shape[0], 3))
        for i, (a, b) in enumerate(zip(xs, ys)):
            d, gx, gy, inside = standin_sampler(self.sampler_data, a, b)
            if not inside and self.mode == "exact":
                d, gx, gy = self.exact.point_fn(a, b)
            out[i] = d, gx, gy
        if compute_gradient:
            return out[:, 0], out[:, 1:]
        return out[:, 0]
