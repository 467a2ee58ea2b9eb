"""Compiled primitives that need loops or iterative solves (graph op ``"prim"``).

Every kind has two ``@njit`` functions of the local coordinates ``(u, v)`` and the kind's
arguments: ``<kind>_vg`` returns ``(d, dd/du, dd/dv)`` and ``<kind>_v`` returns ``d``. The code
generator calls them from the per-point functions and applies the chain rule to ``x, y``;
:mod:`fastsdf.expr.prims_ref` holds independent NumPy references for the tests and
:func:`fastsdf.expr.graph.evaluate_numpy`.

Kinds:

* ``ellipse(u, v, a, b)``: exact signed distance to the ellipse ``(u/a)**2 + (v/b)**2 = 1``
  (semi-axes ``a, b > 0``, any ratio). The closest point is found by a safeguarded Newton
  iteration on a normalized secular equation (see :func:`ellipse_vg`), exact to rounding on the
  axes, at the centre and for very eccentric ellipses; far away a closed form through the
  support point (:func:`_ellipse_far`), where the iteration's variables would overflow.
* ``polygon(u, v, verts)``: exact signed distance to a simple polygon whose vertices are the
  rows of ``verts`` (counter-clockwise); the sign comes from an even-odd crossing test.

The gradient is the unit vector from the closest boundary point (outward normal direction
on the boundary); at points with several closest points (the medial axis) one of them is used.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

__all__ = ["ellipse_v", "ellipse_vg", "polygon_v", "polygon_vg"]

_EPS = 2.220446049250313e-16
_UP = 2.0 ** 600  # brings subnormal and tiny lengths into the normal range, exactly


@njit(cache=True, nogil=True, error_model="numpy")
def _unit(dx, dy):
    """``(r, dx / r, dy / r)`` with ``r = hypot(dx, dy)``; the unit vector is exact also for
    subnormal ``dx, dy`` (rescaled first, where ``1 / r`` would overflow and the quotients lose
    bits); ``(0, 1, 0)`` at the origin."""
    r = math.hypot(dx, dy)
    if r < 1e-150:
        sx = dx * _UP
        sy = dy * _UP
        rs = math.hypot(sx, sy)
        if rs > 0.0:
            return r, sx / rs, sy / rs
        return 0.0, 1.0, 0.0
    return r, dx / r, dy / r


@njit(cache=True, nogil=True, error_model="numpy")
def _ellipse_quadrant(y0, y1, e0, e1):
    """Signed distance and outward unit normal for ``y0, y1 >= 0``, semi-axes ``e0 > e1 > 0``
    (``e0`` along the first coordinate).

    The closest point is ``x_i = y_i e_i**2 / (t + e_i**2)`` for the root ``t`` of
    ``sum((e_i y_i / (t + e_i**2))**2) = 1`` (Eberly). With ``s = t / e1**2 + 1`` this is
    ``psi(s) = 1 / hypot(c0 / (s + r), z1 / s) - 1 = 0`` where ``z1 = y1 / e1``,
    ``c0 = e0 y0 / e1**2`` and ``r = (e0**2 - e1**2) / e1**2``. ``psi`` increases on ``s > 0``
    and is nearly linear (exactly, where one term dominates), so Newton converges in a few
    steps; it is safeguarded by the bracket ``[z1, hypot(c0, z1)]`` with bisection. Then
    ``y - x = (s - 1) (y0 / (s + r), y1 / s)``: the distance keeps its sign and full accuracy.
    """
    if y1 < _TINY_AXIS * (e1 * (e1 / e0)):
        # On the major axis (or so near it, relative to the vertex's radius of curvature
        # e1**2/e0, that the off-axis correction is below rounding; the iteration below would
        # divide by the tiny y1): beyond the centre of curvature of the vertex the vertex is
        # closest; nearer the centre the closest point is off the axis (we take the +y side).
        r2 = (e0 - e1) * (e0 + e1)
        if y0 * e0 >= r2:
            return y0 - e0, 1.0, 0.0
        x0 = e0 * (e0 * y0 / r2)
        q = x0 / e0
        x1 = e1 * math.sqrt(max(0.0, (1.0 - q) * (1.0 + q)))
        dx = x0 - y0
        dist = math.hypot(dx, x1)
        return -dist, dx / dist, x1 / dist
    if y0 == 0.0:
        return y1 - e1, 0.0, 1.0
    z1 = y1 / e1
    r = ((e0 - e1) / e1) * ((e0 + e1) / e1)
    c0 = (e0 / e1) * (y0 / e1)
    lo = z1
    hi = math.hypot(c0, z1)
    s = lo
    for _ in range(100):
        i0 = 1.0 / (s + r)
        i1 = 1.0 / s
        w0 = c0 * i0
        w1 = z1 * i1
        S = math.sqrt(w0 * w0 + w1 * w1)
        if not (1e-150 < S < 1e150):  # far away: avoid overflow of the squares
            S = math.hypot(w0, w1)
        iS = 1.0 / S
        psi = iS - 1.0
        if psi < 0.0:
            lo = s
        elif psi > 0.0:
            hi = s
        else:
            break
        q0 = w0 * iS
        q1 = w1 * iS
        dpsi = (q0 * q0 * i0 + q1 * q1 * i1) * iS
        s_new = s - psi / dpsi
        if not (lo < s_new < hi):  # also catches NaN
            s_new = 0.5 * (lo + hi)
        if abs(s_new - s) <= 2.0 * _EPS * s:
            s = s_new
            break
        s = s_new
    n0 = y0 / (s + r)
    n1 = y1 / s
    nn = math.hypot(n0, n1)
    return (s - 1.0) * nn, n0 / nn, n1 / nn


_TINY_AXIS = 2.0 ** -60
_FAR = 2.0 ** 30


@njit(cache=True, nogil=True, error_model="numpy")
def _ellipse_far(y0, y1, e0, e1):
    """Far from the ellipse (``|p|`` at least ``2**30`` times its largest radius of curvature
    ``max(e)**2 / min(e)``): the closest point is, to below rounding, the support point ``q`` of
    the direction ``n = p / |p|`` (where the outward normal is ``n``); distance ``|p - q|`` and
    gradient ``(p - q) / |p - q|`` (errors of order ``(max(e) / |p|)**2``). The Newton solve
    would overflow here (its variables grow like ``|p| max(e) / min(e)**2``)."""
    r, n0, n1 = _unit(y0, y1)
    h = math.hypot(e0 * n0, e1 * n1)
    q0 = e0 * (e0 * n0 / h)
    q1 = e1 * (e1 * n1 / h)
    return _unit(y0 - q0, y1 - q1)


@njit(cache=True, nogil=True, error_model="numpy")
def ellipse_vg(u: float, v: float, a: float, b: float) -> tuple[float, float, float]:
    """``(d, dd/du, dd/dv)`` of the ellipse with semi-axes ``a`` (along u) and ``b``."""
    su = 1.0 if u >= 0.0 else -1.0
    sv = 1.0 if v >= 0.0 else -1.0
    y0 = abs(u)
    y1 = abs(v)
    if a == b:
        rr, n0, n1 = _unit(y0, y1)
        return rr - a, su * n0, sv * n1
    big = max(a, b)
    if max(y0, y1) >= _FAR * (big * (big / min(a, b))):
        d, n0, n1 = _ellipse_far(y0, y1, a, b)
        return d, su * n0, sv * n1
    if a > b:
        d, n0, n1 = _ellipse_quadrant(y0, y1, a, b)
    else:
        d, n1, n0 = _ellipse_quadrant(y1, y0, b, a)
    return d, su * n0, sv * n1


@njit(cache=True, nogil=True, error_model="numpy")
def ellipse_v(u: float, v: float, a: float, b: float) -> float:
    """Signed distance to the ellipse with semi-axes ``a`` (along u) and ``b``."""
    return ellipse_vg(u, v, a, b)[0]


@njit(cache=True, nogil=True, error_model="numpy")
def polygon_vg(u: float, v: float, verts: np.ndarray) -> tuple[float, float, float]:
    """``(d, dd/du, dd/dv)`` of the simple polygon with counter-clockwise vertices ``verts``
    (an ``(n, 2)`` array, not closed: the last vertex connects to the first).

    Where the nearest boundary point lies inside an edge, the distance is the edge-line distance
    ``|cross(w, e)| / |e|`` and the gradient that edge's outward normal (exact, also on the edge
    and within rounding of it, where ``w - t e`` would be rounding noise in any direction).
    Squared lengths are compared, so vertices should be of moderate magnitude (the modelling
    layer rescales extreme polygons by a power of two)."""
    n = verts.shape[0]
    best = math.inf
    on_edge = False
    bdx = bdy = 0.0  # offset from the nearest vertex
    bex = 1.0  # the nearest edge (for a vertex: an edge that ends there)
    bey = 0.0
    bc = 0.0
    bee = 1.0
    inside = False
    ax = verts[n - 1, 0]
    ay = verts[n - 1, 1]
    for i in range(n):
        bx = verts[i, 0]
        by = verts[i, 1]
        ex = bx - ax
        ey = by - ay
        wx = u - ax
        wy = v - ay
        ee = ex * ex + ey * ey
        t = wx * ex + wy * ey
        edge = False
        c = 0.0
        if t <= 0.0 or ee == 0.0:
            dx = wx
            dy = wy
            dd = dx * dx + dy * dy
        elif t >= ee:
            dx = u - bx
            dy = v - by
            dd = dx * dx + dy * dy
        else:
            c = wx * ey - wy * ex  # > 0 on the outer (right) side of a counter-clockwise edge
            dd = c * (c / ee)
            dx = dy = 0.0
            edge = True
        if i == 0 or dd < best:
            best = dd
            on_edge = edge
            bdx = dx
            bdy = dy
            bex = ex
            bey = ey
            bc = c
            bee = ee
        # the edge crosses the horizontal line through the point, right of the point
        if (ay > v) != (by > v) and u < ax + (v - ay) * (ex / ey):
            inside = not inside
        ax = bx
        ay = by
    s = -1.0 if inside else 1.0
    if on_edge:
        ln = math.sqrt(bee)
        return s * (abs(bc) / ln), bey / ln, -bex / ln
    dist, gx, gy = _unit(bdx, bdy)
    if dist > 0.0:
        return s * dist, s * gx, s * gy
    # exactly on a vertex: the outward normal of an edge that meets there (a limit gradient)
    dist, gx, gy = _unit(bey, -bex)
    return 0.0, gx, gy


@njit(cache=True, nogil=True, error_model="numpy")
def polygon_v(u: float, v: float, verts: np.ndarray) -> float:
    """Signed distance to the simple polygon with counter-clockwise vertices ``verts``."""
    return polygon_vg(u, v, verts)[0]


def _guard():
    import sys

    from fastsdf.backends.kernel.cache import guard_module
    guard_module(sys.modules[__name__])


_guard()
