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
* ``outline(u, v, table)``: exact signed distance to a region bounded by line segments and
  quadratic Bezier segments (fonts, SVG paths), filled by the even-odd or non-zero rule.

The gradient is the unit vector from the closest boundary point (outward normal direction
on the boundary); at points with several closest points (the medial axis) one of them is used.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

__all__ = [
    "ellipse_v",
    "ellipse_vg",
    "outline_v",
    "outline_vg",
    "polygon_v",
    "polygon_vg",
    "quad_closest",
]

_EPS = 2.220446049250313e-16
_UP = 2.0**600  # brings subnormal and tiny lengths into the normal range, exactly


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


_TINY_AXIS = 2.0**-60
_FAR = 2.0**30


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


# ---------------------------------------------------------------------------------------------
# Outlines: closed curves of line segments and quadratic Bezier segments (fonts, SVG paths).
# The table (see fastsdf.geometry.outline.outline_table) has one header row
# ``[fill rule (1: even-odd, 2: non-zero), 0, ...]`` then one row per segment:
# ``[kind (0 line, 1 quadratic), x0, y0, x1, y1, x2, y2, bbox x min, y min, x max, y max]``
# with start (x0, y0), control (x1, y1) (unused by lines) and end (x2, y2). Quadratics are
# monotone in y (split at their y extremum when the table is built), so each crosses a
# horizontal line at most once.
OUTLINE_COLUMNS = 11


@njit(cache=True, nogil=True, error_model="numpy")
def _quad_point(t, x0, y0, x1, y1, x2, y2):
    s = 1.0 - t
    return (s * s * x0 + 2.0 * s * t * x1 + t * t * x2, s * s * y0 + 2.0 * s * t * y1 + t * t * y2)


@njit(cache=True, nogil=True, error_model="numpy")
def _quad_polish(t, u, v, x0, y0, x1, y1, x2, y2):
    """Newton steps on ``(B(t) - p) . B'(t) = 0`` from ``t`` (kept in [0, 1]); returns the
    parameter and squared distance of the best point seen."""
    ax, ay = x1 - x0, y1 - y0  # B'(t) = 2 (a + b t)
    bx, by = x0 - 2.0 * x1 + x2, y0 - 2.0 * y1 + y2
    bt = min(max(t, 0.0), 1.0)
    qx, qy = _quad_point(bt, x0, y0, x1, y1, x2, y2)
    best = (qx - u) ** 2 + (qy - v) ** 2
    t = bt
    for _ in range(4):
        px, py = _quad_point(t, x0, y0, x1, y1, x2, y2)
        dx, dy = ax + bx * t, ay + by * t
        g = (px - u) * dx + (py - v) * dy
        h = dx * dx + dy * dy + (px - u) * bx + (py - v) * by
        if h <= 0.0:
            break
        t = min(max(t - g / h, 0.0), 1.0)
        qx, qy = _quad_point(t, x0, y0, x1, y1, x2, y2)
        dd = (qx - u) ** 2 + (qy - v) ** 2
        if dd < best:
            best = dd
            bt = t
        else:
            break
    return bt, best


@njit(cache=True, nogil=True, error_model="numpy")
def _cbrt(x):
    return math.copysign(abs(x) ** (1.0 / 3.0), x)


@njit(cache=True, nogil=True, error_model="numpy")
def quad_closest(u, v, x0, y0, x1, y1, x2, y2):  # noqa: ANN201 (numba-typed kernel)
    """Parameter ``t`` in [0, 1] and squared distance of the point of the quadratic Bezier
    ``(x0, y0), (x1, y1), (x2, y2)`` closest to ``(u, v)``: the stationary points solve a cubic
    (Inigo Quilez's closed form, sdBezier), each root polished by Newton steps, compared with
    the two ends."""
    ax, ay = x1 - x0, y1 - y0
    bx, by = x0 - 2.0 * x1 + x2, y0 - 2.0 * y1 + y2
    dx, dy = x0 - u, y0 - v
    best_t = 0.0
    best = dx * dx + dy * dy
    ex, ey = x2 - u, y2 - v
    e = ex * ex + ey * ey
    if e < best:
        best, best_t = e, 1.0
    bb = bx * bx + by * by
    scale = max(ax * ax + ay * ay, (x2 - x0) ** 2 + (y2 - y0) ** 2)
    if bb <= 1e-20 * scale:
        # (nearly) a straight line traversed at constant speed: the foot of the perpendicular
        lx, ly = x2 - x0, y2 - y0
        ll = lx * lx + ly * ly
        if ll > 0.0:
            t, dd = _quad_polish(-(dx * lx + dy * ly) / ll, u, v, x0, y0, x1, y1, x2, y2)
            if dd < best:
                best, best_t = dd, t
        return best_t, best
    kk = 1.0 / bb
    kx = kk * (ax * bx + ay * by)
    ky = kk * (2.0 * (ax * ax + ay * ay) + (dx * bx + dy * by)) / 3.0
    kz = kk * (dx * ax + dy * ay)
    p = ky - kx * kx
    q = kx * (2.0 * kx * kx - 3.0 * ky) + kz
    h = q * q + 4.0 * p * p * p
    if h >= 0.0:
        h = math.sqrt(h)
        t, dd = _quad_polish(
            _cbrt(0.5 * (h - q)) + _cbrt(0.5 * (-h - q)) - kx, u, v, x0, y0, x1, y1, x2, y2
        )
        if dd < best:
            best, best_t = dd, t
    else:
        z = math.sqrt(-p)
        c = min(max(q / (p * z * 2.0), -1.0), 1.0)
        ang = math.acos(c) / 3.0
        m = math.cos(ang)
        n = math.sin(ang) * 1.7320508075688772
        for r in ((m + m) * z - kx, (-n - m) * z - kx, (n - m) * z - kx):
            t, dd = _quad_polish(r, u, v, x0, y0, x1, y1, x2, y2)
            if dd < best:
                best, best_t = dd, t
    return best_t, best


@njit(cache=True, nogil=True, error_model="numpy")
def _quad_root_y(v, y0, y1, y2):
    """The parameter in [0, 1] where a y-monotone quadratic reaches height ``v``."""
    a = y0 - 2.0 * y1 + y2
    b = 2.0 * (y1 - y0)
    c = y0 - v
    if abs(a) <= 1e-14 * (abs(b) + abs(c)):
        t = -c / b if b != 0.0 else 0.0
    else:
        disc = math.sqrt(max(b * b - 4.0 * a * c, 0.0))
        qq = -0.5 * (b + math.copysign(disc, b))
        t1 = qq / a
        t2 = c / qq if qq != 0.0 else t1
        t = t1 if (t1 >= -1e-12 and t1 <= 1.0 + 1e-12) else t2
    return min(max(t, 0.0), 1.0)


@njit(cache=True, nogil=True, error_model="numpy")
def outline_vg(u, v, table):  # noqa: ANN201 (numba-typed kernel)
    """``(d, dd/du, dd/dv)`` of the region bounded by the outline ``table`` (line and
    quadratic Bezier segments, see ``OUTLINE_COLUMNS``), filled by the table's rule.

    The distance is to the nearest segment (exact: the quadratics' closest points solve a
    cubic); segments whose bounding box is farther than the best so far are skipped. The sign
    counts crossings of the ray from ``(u, v)`` towards +x (half-open in y, so a crossing at a
    shared end is counted once). The gradient is the unit vector from the closest point,
    negated inside; on the curve, its normal."""
    nonzero = table[0, 0] == 2.0
    # An upper bound first (the nearest segment start), so that the bounding-box test below
    # skips most segments before any closest-point solve.
    best = math.inf
    for i in range(1, table.shape[0]):
        best = min(best, (u - table[i, 1]) ** 2 + (v - table[i, 2]) ** 2)
    best = best * (1.0 + 1e-12)  # a start is itself on a segment: keep it reachable below
    bkind = -1
    bi = 0
    bt = 0.0
    wind = 0
    for i in range(1, table.shape[0]):
        x0 = table[i, 1]
        y0 = table[i, 2]
        x2 = table[i, 5]
        y2 = table[i, 6]
        kind = table[i, 0]
        if (y0 > v) != (y2 > v):
            if kind == 0.0:
                xc = x0 + (v - y0) * ((x2 - x0) / (y2 - y0))
            else:
                t = _quad_root_y(v, y0, table[i, 4], y2)
                xc = _quad_point(t, x0, y0, table[i, 3], table[i, 4], x2, y2)[0]
            if u < xc:
                wind += 1 if y2 > y0 else -1
        # lower bound: the distance to the segment's bounding box
        gx = max(table[i, 7] - u, 0.0, u - table[i, 9])
        gy = max(table[i, 8] - v, 0.0, v - table[i, 10])
        if gx * gx + gy * gy > best:
            continue
        if kind == 0.0:
            ex, ey = x2 - x0, y2 - y0
            ee = ex * ex + ey * ey
            t = 0.0
            if ee > 0.0:
                t = min(max(((u - x0) * ex + (v - y0) * ey) / ee, 0.0), 1.0)
            qx, qy = x0 + t * ex, y0 + t * ey
            dd = (u - qx) ** 2 + (v - qy) ** 2
        else:
            t, dd = quad_closest(u, v, x0, y0, table[i, 3], table[i, 4], x2, y2)
        if dd <= best:
            best, bkind, bi, bt = dd, kind, i, t
    inside = (wind != 0) if nonzero else (wind % 2 != 0)
    s = -1.0 if inside else 1.0
    if bkind < 0:
        return math.inf, 0.0, 0.0
    x0, y0 = table[bi, 1], table[bi, 2]
    x1, y1 = table[bi, 3], table[bi, 4]
    x2, y2 = table[bi, 5], table[bi, 6]
    if bkind == 0.0:
        qx, qy = x0 + bt * (x2 - x0), y0 + bt * (y2 - y0)
        tx, ty = x2 - x0, y2 - y0
    else:
        qx, qy = _quad_point(bt, x0, y0, x1, y1, x2, y2)
        tx = (x1 - x0) + (x0 - 2.0 * x1 + x2) * bt
        ty = (y1 - y0) + (y0 - 2.0 * y1 + y2) * bt
    dist, gx, gy = _unit(u - qx, v - qy)
    if dist > 0.0:
        return s * dist, s * gx, s * gy
    # on the curve: a normal (the tangent turned clockwise; its sign is a limit choice)
    dist, gx, gy = _unit(ty, -tx)
    return 0.0, gx, gy


@njit(cache=True, nogil=True, error_model="numpy")
def outline_v(u, v, table):  # noqa: ANN201 (numba-typed kernel)
    """Signed distance to the region bounded by the outline ``table``."""
    return outline_vg(u, v, table)[0]
