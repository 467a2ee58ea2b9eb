"""Primitives: the notebook's (Circle, Halfspace, Box) and the others, each built in the local
coordinates of the :func:`~fastsdf.shapes.transform` context. All are exact signed distances
unless their docstring says otherwise.

Units: lengths (coordinates, radii, sizes) are in the units of the coordinates the shape is
queried at (any unit: metres, pixels, the notebook's 4-unit world), and the distances come
back in the same unit; angles are in radians, counter-clockwise. A point is a pair ``(x, y)``
(tuple, list or array). Each number may also be an expression of runtime parameters
(:class:`fastsdf.Param`, the time ``fastsdf.t``; see docs/moving.md), checked at the
parameters' defaults. Bad values raise ``TypeError`` or ``ValueError`` naming the parameter.
Lengths must lie between 1e-150 and 1e150 in magnitude."""

from __future__ import annotations

import functools
import math
import numbers
from collections.abc import Sequence

import numpy as np
from numpy.typing import ArrayLike

from fastsdf.expr.graph import (
    Expr,
    as_expr,
    sym_abs,
    sym_cos,
    sym_length,
    sym_max,
    sym_min,
    sym_prim,
    sym_select,
    sym_sin,
)
from fastsdf.expr.validate import (
    MAX_COORD,
    FloatOrParam,
    Pair,
    PairOrParam,
    coord2_or_param,
    is_param,
    real_or_param,
    shown,
    vec2_or_param,
)
from fastsdf.expr.validate import check_length as _check_length
from fastsdf.expr.validate import coord as _coord
from fastsdf.expr.validate import coord2 as _point
from fastsdf.expr.validate import length as _length
from fastsdf.expr.validate import real as _real
from fastsdf.expr.validate import vec2 as _vec2
from fastsdf.shapes.context import _IDENTITY, _coords, _frame
from fastsdf.shapes.exactness import _center_sym, _edges_symmetry, _points_bbox, _primitive_info
from fastsdf.shapes.operations import SDF


def _has_param(value: object) -> bool:
    """Whether a pair holds an expression of runtime parameters."""
    return isinstance(value, (tuple, list)) and any(is_param(v) for v in value)


def _any_param(*values: object) -> bool:
    """Whether any of the numbers or pairs is (or holds) an expression of parameters."""
    return any(is_param(v) or _has_param(v) for v in values)


def _point_p(value: object, name: str) -> tuple[Pair, np.ndarray]:
    """``(pair, numbers)``: a point whose coordinates may be expressions of parameters (checked
    at the parameters' defaults) and its value there as a float64 array."""
    if _has_param(value):
        return coord2_or_param(value, name)
    p = _point(value, name)
    return p, p


def _positive_p(value: object, name: str, size: bool = True) -> tuple[FloatOrParam, float]:
    """``(value, number)``: :func:`_positive` for a number or an expression of parameters
    (checked at the defaults)."""
    if is_param(value):
        expr, number = real_or_param(value, name)
        if not number > 0:
            raise ValueError(
                f"{name} must be > 0, got {name}={expr} = {shown(number)} at the parameters' "
                f"defaults"
            )
        if size:
            _check_length(number, name)
        return expr, number
    v = _positive(value, name, size)
    return v, v


def _not_param(value: object, name: str, why: str) -> None:
    """``TypeError`` for a number that cannot be a runtime parameter, saying why."""
    if is_param(value) or _has_param(value):
        raise TypeError(f"{name} cannot be a runtime parameter ({why}), got {name}={shown(value)}")


# A segment whose ends meet at run time divides by its length: it is kept above this (the
# smallest supported length is 1e-150), and then the distance is the distance to the point.
_TINY = 1e-300


def _segment_expr_p(x: Expr, y: Expr, a: Pair, b: Pair, normal: tuple | None = None) -> Expr:
    """:func:`_segment_expr` with ends (and normal) that may be expressions of parameters: the
    same formula, with the length and direction computed in the kernel."""
    px, py = x - a[0], y - a[1]
    ex, ey = as_expr(b[0] - a[0]), as_expr(b[1] - a[1])
    length = sym_length(ex, ey)
    safe = sym_max(length, _TINY)
    dx, dy = ex / safe, ey / safe
    nx, ny = (-dy, dx) if normal is None else normal
    t = px * dx + py * dy
    h = px * nx + py * ny
    beyond_b = t - 0.5 * length
    ux = sym_select(beyond_b, px - ex, px)
    uy = sym_select(beyond_b, py - ey, py)
    beside = sym_min(t, length - t)
    return sym_select(beside, sym_abs(h), sym_length(ux, uy))


def _convex_polygon_expr_p(
    x: Expr, y: Expr, vertices: Sequence[Pair], orientation: FloatOrParam = 1.0
) -> Expr:
    """:func:`_convex_polygon_expr` for vertices that may be expressions of parameters, in
    counter-clockwise order when ``orientation`` is 1 and clockwise when it is -1 (a number,
    or an expression that is +-1 at run time)."""
    n = len(vertices)
    dist: Expr | None = None
    line: Expr | None = None
    for i in range(n):
        a, b = vertices[i], vertices[(i + 1) % n]
        ex, ey = as_expr(b[0] - a[0]), as_expr(b[1] - a[1])
        inv = orientation / sym_max(sym_length(ex, ey), _TINY)
        normal = (ey * inv, -ex * inv)  # outward
        seg = _segment_expr_p(x, y, a, b, normal)
        h = (x - a[0]) * normal[0] + (y - a[1]) * normal[1]
        dist = seg if dist is None else sym_min(dist, seg)
        line = h if line is None else sym_max(line, h)
    assert dist is not None and line is not None  # (n >= 3 edges)
    return sym_select(line, dist, line)


def _polygon_expr_p(x: Expr, y: Expr, vertices: Sequence[Pair]) -> Expr:
    """Exact SDF of a simple polygon whose vertices may be expressions of parameters, from
    graph operations: the distance to the nearest edge, negated inside by an even-odd crossing
    count (IQ's sdPolygon: each edge that a ray from the point crosses flips the sign)."""
    n = len(vertices)
    dist: Expr | None = None
    sign: Expr | None = None
    for i in range(n):
        a, b = vertices[i], vertices[i - 1]
        seg = _segment_expr_p(x, y, a, b)
        dist = seg if dist is None else sym_min(dist, seg)
        ex, ey = as_expr(b[0] - a[0]), as_expr(b[1] - a[1])
        wx, wy = x - a[0], y - a[1]
        c1 = sym_select(a[1] - y, -1.0, 1.0)  # y >= a.y
        c2 = sym_select(b[1] - y, 1.0, -1.0)  # y < b.y
        c3 = sym_select(ex * wy - ey * wx, 1.0, -1.0)  # the point left of the edge
        flip = sym_select(sym_abs(c1 + c2 + c3) - 2.0, -1.0, 1.0)  # all three or none
        sign = flip if sign is None else sign * flip
    assert dist is not None and sign is not None  # (n >= 3 edges)
    return sign * dist


__all__ = [
    "Circle",
    "Halfspace",
    "Box",
    "Segment",
    "Capsule",
    "RoundedBox",
    "OrientedBox",
    "EquilateralTriangle",
    "Triangle",
    "RegularPolygon",
    "Polygon",
    "Star",
    "Ellipse",
    "Arc",
    "Ring",
    "Outline",
]


# ---------------------------------------------------------------------------------------------
# The notebook's primitives.


class Circle(SDF):
    """Disc of ``radius`` around ``center`` (exact distance: ``|p - center| - radius``).

    At the centre, where every direction is steepest, the gradient is the local +x axis.

    Parameters
    ----------
    center : pair (x, y), default (0, 0)
        The centre, in the units of the coordinates.
    radius : float > 0, default 1
        The radius, in the same units.
    """

    center: Pair
    radius: FloatOrParam

    def __init__(self, center: PairOrParam = (0.0, 0.0), radius: FloatOrParam = 1.0):
        if is_param(radius) or _has_param(center):
            center, _ = coord2_or_param(center, "center")
            radius, r0 = real_or_param(radius, "radius")
            if r0 <= 0:
                raise ValueError(f"radius must be > 0, got radius={shown(radius)}")
        else:
            center = _point(center, "center")
            radius = _positive(radius, "radius")
            self.center, self.radius = center, radius
            c0, c1 = center.tolist()
            x, y = _coords()
            # (numbers: the general path's bounding box and symmetries, in Python floats)
            info = _primitive_info(
                (c0 - radius, c1 - radius, c0 + radius, c1 + radius),
                _center_sym((c0, c1)),
                convex=True,
            )
            SDF.__init__(self, sym_length(x - c0, y - c1) - radius, info)
            return
        self.center, self.radius = center, radius
        x, y = _coords()
        moving = is_param(radius) or any(is_param(v) for v in center)
        info = _primitive_info(
            None if moving else _points_bbox([center], r0),
            () if moving else _center_sym(center),
            convex=True,
        )
        super().__init__(sym_length(x - center[0], y - center[1]) - radius, info)


class Halfspace(SDF):
    """Half-plane ``{p : n . p <= d}`` with outward normal ``normal`` (normalized here) and
    signed offset ``d`` from the origin (Hessian normal form; exact distance).

    Parameters
    ----------
    normal : pair (x, y) of non-zero length, default (1, 0)
        The outward normal: the side it points to is outside. Any length; normalized.
    d : float, default 0
        The boundary's signed distance from the origin along ``normal``, in the units of the
        coordinates (``Halfspace((0, 1), -1.8)``: everything below ``y = -1.8``).
    """

    normal: Pair
    d: FloatOrParam

    def __init__(self, normal: PairOrParam = (1.0, 0.0), d: FloatOrParam = 0.0):
        d = real_or_param(d, "d")[0] if is_param(d) else _coord(d, "d")
        if _has_param(normal):  # turned by parameters: normalized in the kernel
            normal, nv = vec2_or_param(normal, "normal")
            if not float(np.hypot(*nv)) > 0:
                raise ValueError(
                    f"normal must have non-zero length, got normal={shown(nv.tolist())} "
                    f"at the parameters' defaults"
                )
            length = sym_length(*normal)
            self.normal, self.d = (normal[0] / length, normal[1] / length), d
            x, y = _coords()
            super().__init__(
                x * self.normal[0] + y * self.normal[1] - d, _primitive_info(None, convex=True)
            )
            return
        normal = _vec2(normal, "normal")
        big = float(np.abs(normal).max())
        if not big > 0:
            raise ValueError(
                f"normal must have non-zero length, got normal={shown(normal.tolist())}"
            )
        n = normal / big  # first to about 1: the direction is exact also for subnormal input
        n = n / float(np.hypot(n[0], n[1]))
        self.normal, self.d = n, d
        x, y = _coords()
        super().__init__(x * n[0] + y * n[1] - d, _primitive_info(None, convex=True))


def _box_expr(qx: Expr, qy: Expr) -> Expr:
    """Exact SDF of a rectangle from the signed distances ``qx, qy`` to its two pairs of
    sides (IQ's box): outside ``length(max(qx, 0), max(qy, 0))``, inside and on the boundary
    ``max(qx, qy)``. On a face the inside branch is taken, whose gradient is the face's
    normal; the sum ``outside + min(0, max(qx, qy))`` has the same value but no unit gradient
    there (both parts tie at zero)."""
    inner = sym_max(qx, qy)
    return sym_select(inner, sym_length(sym_max(qx, 0.0), sym_max(qy, 0.0)), inner)


class Box(SDF):
    """Axis-aligned rectangle from corner ``minc`` to corner ``maxc`` (in local coordinates).

    The distance is exact everywhere. (The notebook's box, an intersection of four half-spaces,
    agrees inside and along the faces but outside the corners gives only a lower bound, the
    L-infinity distance, with an axis-aligned gradient.)

    Parameters
    ----------
    minc, maxc : pair (x, y), default (-1, -1) and (1, 1)
        The lower-left and upper-right corners, ``minc < maxc`` along both axes, in the units of
        the coordinates.
    """

    def __init__(self, minc: PairOrParam = (-1.0, -1.0), maxc: PairOrParam = (1.0, 1.0)):
        if _has_param(minc) or _has_param(maxc):
            (minc, lo), (maxc, hi) = coord2_or_param(minc, "minc"), coord2_or_param(maxc, "maxc")
        else:
            self._init_numbers(_point(minc, "minc"), _point(maxc, "maxc"))
            return
        if not np.all(lo < hi):
            raise ValueError(
                f"minc must be below maxc in both coordinates, got "
                f"minc={shown(lo.tolist())}, maxc={shown(hi.tolist())}"
            )
        _check_length(float(np.min(hi - lo)), "the smaller side maxc - minc")
        self.minc, self.maxc = minc, maxc
        moving = any(is_param(v) for v in (*minc, *maxc))
        center = [(minc[j] + maxc[j]) * 0.5 for j in (0, 1)]
        half = [(maxc[j] - minc[j]) * 0.5 for j in (0, 1)]
        x, y = _coords()
        qx = sym_abs(x - center[0]) - half[0]
        qy = sym_abs(y - center[1]) - half[1]
        sym = set() if moving else {ax for ax, a, b in zip("xy", lo, hi) if a == -b}
        info = _primitive_info(None if moving else _points_bbox([lo, hi]), sym, convex=True)
        super().__init__(_box_expr(qx, qy), info)

    def _init_numbers(self, minc: np.ndarray, maxc: np.ndarray) -> None:
        """The corners are numbers (the common case): the same expression and checks as the
        general path, in Python floats (building many boxes is dominated by NumPy's per-call
        cost on two-element arrays otherwise)."""
        (l0, l1), (h0, h1) = minc.tolist(), maxc.tolist()
        if not (l0 < h0 and l1 < h1):
            raise ValueError(
                f"minc must be below maxc in both coordinates, got "
                f"minc={shown([l0, l1])}, maxc={shown([h0, h1])}"
            )
        _check_length(min(h0 - l0, h1 - l1), "the smaller side maxc - minc")
        self.minc, self.maxc = minc, maxc
        x, y = _coords()
        qx = sym_abs(x - (l0 + h0) * 0.5) - (h0 - l0) * 0.5
        qy = sym_abs(y - (l1 + h1) * 0.5) - (h1 - l1) * 0.5
        sym = {ax for ax, a, b in (("x", l0, h0), ("y", l1, h1)) if a == -b}
        # (the bounding box of the corners: l < h in both coordinates)
        info = _primitive_info((l0, l1, h0, h1), sym, convex=True)
        SDF.__init__(self, _box_expr(qx, qy), info)


# ---------------------------------------------------------------------------------------------
# Segments, boxes, polygons, ellipses, rings and arcs, and the geometry helpers they share.


def _segment_expr(
    x: Expr, y: Expr, a: np.ndarray, b: np.ndarray, normal: tuple | None = None
) -> Expr:
    """Unsigned distance from (x, y) to the segment a-b (a point if a == b).

    Beside the segment (its foot between ``a`` and ``b``) the distance is ``|h|``, the distance
    from the line along the unit ``normal`` (default: the left normal of ``b - a``), not the
    length of ``p - foot``: that difference cancels to rounding noise near the segment, and its
    direction (the gradient) with it, while ``h`` has the exact normal as its gradient, also on
    the segment itself (where ``|h|`` takes the side of ``+normal``). Beyond the ends it is the
    distance to the nearer end. Only lengths and unit vectors are used (no squared lengths),
    so the formula does not over- or underflow at any scale.
    """
    a, b = np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64)
    px, py = x - float(a[0]), y - float(a[1])
    ex, ey = float(b[0] - a[0]), float(b[1] - a[1])
    length = math.hypot(ex, ey)
    if length == 0.0:
        return sym_length(px, py)
    dx, dy = ex / length, ey / length
    nx, ny = (-dy, dx) if normal is None else normal
    t = px * dx + py * dy  # distance along the segment from a
    h = px * nx + py * ny
    beyond_b = t - 0.5 * length
    ux = sym_select(beyond_b, px - ex, px)  # from the nearer end
    uy = sym_select(beyond_b, py - ey, py)
    beside = sym_min(t, length - t)
    return sym_select(beside, sym_abs(h), sym_length(ux, uy))


def _ccw(vertices: np.ndarray) -> np.ndarray:
    """The vertices in counter-clockwise order (by the sign of the shoelace area)."""
    v = vertices
    w = (v - v[0]) / (float(np.abs(v - v[0]).max()) or 1.0)  # scaled: no over- or underflow
    area2 = float(np.sum(w[:, 0] * np.roll(w[:, 1], -1) - np.roll(w[:, 0], -1) * w[:, 1]))
    return v if area2 > 0 else v[::-1].copy()


def _convex_polygon_expr(x: Expr, y: Expr, vertices: np.ndarray) -> Expr:
    """Exact SDF of a convex polygon (counter-clockwise vertices) from graph operations:
    outside the distance to the nearest edge, inside (and on the boundary) the largest signed
    edge-line distance (which for a convex polygon is minus the distance to the nearest edge).

    Each edge's line distance ``h`` is one node shared by both sides, so where rounding puts a
    point just outside an edge, that edge's segment distance is ``|h| = h`` and the gradient is
    the edge's outward normal on both sides and on the edge itself."""
    n = len(vertices)
    dist: Expr | None = None
    line: Expr | None = None
    for i in range(n):
        a, b = vertices[i], vertices[(i + 1) % n]
        e = b - a
        length = math.hypot(*e)
        normal = (e[1] / length, -e[0] / length)  # outward
        seg = _segment_expr(x, y, a, b, normal)
        h = (x - float(a[0])) * normal[0] + (y - float(a[1])) * normal[1]
        dist = seg if dist is None else sym_min(dist, seg)
        line = h if line is None else sym_max(line, h)
    assert dist is not None and line is not None  # (n >= 3 edges)
    return sym_select(line, dist, line)


def _vertices(value: object, name: str, minimum: int = 3) -> np.ndarray:
    try:
        arr = np.asarray(value)
    except Exception:
        raise TypeError(
            f"{name} must be a sequence of (x, y) pairs, got {name}={shown(value)}"
        ) from None
    if arr.dtype.kind not in "iuf":
        raise TypeError(
            f"{name} must be a sequence of (x, y) pairs of real numbers, got {name}={shown(value)}"
        )
    if arr.ndim != 2 or arr.shape[1] != 2:
        raise ValueError(
            f"{name} must have shape (n, 2), got shape {arr.shape} for {name}={shown(value)}"
        )
    arr = arr.astype(np.float64)
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} must be finite, got {name}={shown(value)}")
    if np.any(np.abs(arr) > MAX_COORD):
        raise ValueError(
            f"{name} must have coordinates at most {MAX_COORD:g} in magnitude (the "
            f"supported range of fastsdf geometry is 1e-150 to 1e150), got "
            f"{name}={shown(value)}"
        )
    if len(arr) < minimum:
        raise ValueError(f"{name} needs at least {minimum} vertices, got {len(arr)}")
    return arr


def _is_convex(v: np.ndarray) -> bool:
    """Counter-clockwise vertices: every turn is left (or straight)."""
    e = np.roll(v, -1, axis=0) - v
    cross = e[:, 0] * np.roll(e[:, 1], -1) - e[:, 1] * np.roll(e[:, 0], -1)
    scale = np.hypot(e[:, 0], e[:, 1]) * np.roll(np.hypot(e[:, 0], e[:, 1]), -1)
    return bool(np.all(cross >= -1e-12 * scale))


def _check_simple(v: np.ndarray, name: str) -> None:
    """Raise ValueError unless the closed polygon ``v`` is simple: no two non-adjacent edges
    touch, no adjacent edges fold back onto each other, non-zero area."""
    n = len(v)
    a, b = v, np.roll(v, -1, axis=0)
    scale = float(np.abs(v).max()) or 1.0
    w = v - v[0]
    far = w[np.argmax(np.hypot(w[:, 0], w[:, 1]))]
    if np.all(np.abs(w[:, 0] * far[1] - w[:, 1] * far[0]) <= 1e-12 * scale * scale):
        raise ValueError(
            f"{name} must enclose a non-zero area (got collinear or coincident "
            f"vertices: {shown(v.tolist())})"
        )

    def orient(p: np.ndarray, q: np.ndarray, r: np.ndarray) -> np.ndarray:
        return (q[..., 0] - p[..., 0]) * (r[..., 1] - p[..., 1]) - (q[..., 1] - p[..., 1]) * (
            r[..., 0] - p[..., 0]
        )

    tol = 1e-12 * scale * scale
    for i in range(n):
        # adjacent edge i -> i+1: folds back if collinear and pointing backwards
        e1, e2 = b[i] - a[i], b[(i + 1) % n] - a[(i + 1) % n]
        if abs(e1[0] * e2[1] - e1[1] * e2[0]) <= tol and e1 @ e2 < 0:
            raise ValueError(
                f"{name} is not simple: edges {i} and {(i + 1) % n} overlap "
                f"(the polygon folds back at vertex {(i + 1) % n})"
            )
        j = np.arange(i + 2, n)
        if i == 0:
            j = j[j != n - 1]
        if not len(j):
            continue
        p1, p2, q1, q2 = a[i], b[i], a[j], b[j]
        o1, o2 = orient(p1, p2, q1), orient(p1, p2, q2)
        o3, o4 = orient(q1, q2, p1), orient(q1, q2, p2)
        proper = (o1 * o2 < 0) & (o3 * o4 < 0)

        def on_seg(p, q, r, o):  # r on segment p-q, given their orientation o ~ 0
            eps = 1e-12 * scale
            ok = np.abs(o) <= tol
            for c in (0, 1):
                lo_c = np.minimum(p[..., c], q[..., c])
                hi_c = np.maximum(p[..., c], q[..., c])
                ok = ok & (lo_c <= r[..., c] + eps) & (r[..., c] <= hi_c + eps)
            return ok

        touch = (
            on_seg(p1, p2, q1, o1)
            | on_seg(p1, p2, q2, o2)
            | on_seg(q1, q2, np.broadcast_to(p1, q1.shape), o3)
            | on_seg(q1, q2, np.broadcast_to(p2, q1.shape), o4)
        )
        bad = proper | touch
        if np.any(bad):
            k = int(j[np.argmax(bad)])
            raise ValueError(
                f"{name} is not simple: edge {i} ({a[i].tolist()} -> "
                f"{b[i].tolist()}) meets edge {k} ({a[k].tolist()} -> "
                f"{b[k].tolist()})"
            )
    area2 = float(np.sum(a[:, 0] * b[:, 1] - b[:, 0] * a[:, 1]))
    if abs(area2) <= 1e-12 * scale * scale:
        raise ValueError(
            f"{name} must enclose a non-zero area (got collinear or coincident "
            f"vertices: {shown(v.tolist())})"
        )


class Segment(SDF):
    """The line segment from ``a`` to ``b`` (``a == b`` gives a point).

    A shape of zero thickness: the value is the exact *unsigned* distance, ``>= 0``
    everywhere and 0 only on the segment (there is no inside). On the segment itself (its
    spine) the gradient is the unit normal to the left of ``b - a`` (local +y for a segment
    along +x), a one-sided choice as at a circle's centre: a particle there is pushed off
    sideways; at a point segment (``a == b``) it is the local +x axis.
    ``Segment(a, b).round(r)`` is the same shape as ``Capsule(a, b, r)``.

    Parameters
    ----------
    a, b : pair (x, y), default (0, 0) and (1, 0)
        The ends, in the units of the coordinates.
    """

    def __init__(self, a: PairOrParam = (0.0, 0.0), b: PairOrParam = (1.0, 0.0)):
        if _any_param(a, b):
            (a, av), (b, bv) = _point_p(a, "a"), _point_p(b, "b")
            _segment_length(av, bv)
            self.a, self.b = a, b
            super().__init__(_segment_expr_p(*_coords(), a, b), _primitive_info(None, convex=True))
            return
        a, b = _point(a, "a"), _point(b, "b")
        _segment_length(a, b)
        self.a, self.b = a, b
        info = _primitive_info(
            _points_bbox([a, b]), _edges_symmetry([a, b], closed=False), convex=True
        )
        super().__init__(_segment_expr(*_coords(), a, b), info)


class Capsule(SDF):
    """The segment ``a``-``b`` thickened by ``radius`` (a stadium; a disc if ``a == b``).

    On the spine (the segment ``a``-``b``) the gradient is the unit normal to the left of
    ``b - a``, as for :class:`Segment`.

    Parameters
    ----------
    a, b : pair (x, y), default (0, 0) and (1, 0)
        The ends of the spine, in the units of the coordinates.
    radius : float > 0, default 0.25
        Half the width, in the same units.
    """

    def __init__(
        self, a: PairOrParam = (0.0, 0.0), b: PairOrParam = (1.0, 0.0), radius: FloatOrParam = 0.25
    ):
        if _any_param(a, b, radius):
            (a, av), (b, bv) = _point_p(a, "a"), _point_p(b, "b")
            radius, _ = _positive_p(radius, "radius")
            _segment_length(av, bv)
            self.a, self.b, self.radius = a, b, radius
            super().__init__(
                _segment_expr_p(*_coords(), a, b) - radius, _primitive_info(None, convex=True)
            )
            return
        a, b = _point(a, "a"), _point(b, "b")
        radius = _positive(radius, "radius")
        _segment_length(a, b)
        self.a, self.b, self.radius = a, b, radius
        info = _primitive_info(
            _points_bbox([a, b], radius), _edges_symmetry([a, b], closed=False), convex=True
        )
        super().__init__(_segment_expr(*_coords(), a, b) - radius, info)


class RoundedBox(SDF):
    """Axis-aligned rectangle ``minc``-``maxc`` with rounded corners.

    Parameters
    ----------
    minc, maxc : pair (x, y), default (-1, -1) and (1, 1)
        The corners of the rectangle before rounding, ``minc < maxc``, in the units of the
        coordinates.
    radii : float, or 4 floats, default 0.25
        One radius for every corner, or four in the order of the quadrants (counter-clockwise
        from the upper right): ``(upper-right, upper-left, lower-left, lower-right)``; each in
        ``[0, min(width, height) / 2]`` (0 keeps the corner sharp).
    """

    def __init__(
        self,
        minc: PairOrParam = (-1.0, -1.0),
        maxc: PairOrParam = (1.0, 1.0),
        radii: FloatOrParam | PairOrParam = 0.25,
    ):
        # Any of the numbers may be an expression of parameters: the checks run at the
        # parameters' defaults, the formulas are the same.
        (minc, lo), (maxc, hi) = _point_p(minc, "minc"), _point_p(maxc, "maxc")
        if not np.all(lo < hi):
            raise ValueError(
                f"minc must be below maxc in both coordinates, got "
                f"minc={shown(lo.tolist())}, maxc={shown(hi.tolist())}"
            )
        _check_length(float(np.min(hi - lo)), "the smaller side maxc - minc")

        def radius(v):
            if is_param(v):
                v, number = real_or_param(v, "radii")
                _length(number, "radii", zero=True)
                return v, number
            v = _length(v, "radii", zero=True)
            return v, v

        if isinstance(radii, (tuple, list, np.ndarray)):
            if len(radii) != 4:
                raise ValueError(
                    f"radii must be one number or four (upper-right, upper-left, "
                    f"lower-left, lower-right), got radii={shown(radii)}"
                )
            r, rv = zip(*[radius(v) for v in radii])
        else:
            r, rv = zip(*[radius(radii)] * 4)
        limit = float(min((hi - lo) / 2))
        if not all(0.0 <= v <= limit for v in rv):
            raise ValueError(
                f"radii must be in [0, {shown(limit)}] (half the smaller side), got "
                f"radii={shown(radii)}"
            )
        moving = _any_param(minc, maxc, *r)
        self.minc, self.maxc, self.radii = minc, maxc, tuple(r)
        center = [(minc[j] + maxc[j]) / 2 for j in (0, 1)]
        half = [(maxc[j] - minc[j]) / 2 for j in (0, 1)]
        x, y = _coords()
        px, py = x - center[0], y - center[1]
        if all(v is r[0] for v in r) or (not moving and len(set(r)) == 1):
            rad = r[0]
        else:  # the radius of the quadrant the point is in
            rad = sym_select(px, sym_select(py, r[0], r[3]), sym_select(py, r[1], r[2]))
        qx = sym_abs(px) - half[0] + rad
        qy = sym_abs(py) - half[1] + rad
        expr = _box_expr(qx, qy) - rad
        sym = set()
        if not moving and center[0] == 0 and r[0] == r[1] and r[2] == r[3]:
            sym.add("x")
        if not moving and center[1] == 0 and r[0] == r[3] and r[1] == r[2]:
            sym.add("y")
        info = _primitive_info(None if moving else _points_bbox([lo, hi]), sym, convex=True)
        super().__init__(expr, info)


class OrientedBox(SDF):
    """Rectangle along the segment ``a``-``b``: length ``|b - a|``, total width ``thickness``
    (IQ's oriented box; the ends are flat, at ``a`` and ``b``).

    Parameters
    ----------
    a, b : pair (x, y), ``a != b``, default (-1, 0) and (1, 0)
        The middles of the two flat ends, in the units of the coordinates.
    thickness : float > 0, default 0.5
        The total width across the segment, in the same units.
    """

    def __init__(
        self,
        a: PairOrParam = (-1.0, 0.0),
        b: PairOrParam = (1.0, 0.0),
        thickness: FloatOrParam = 0.5,
    ):
        if _any_param(a, b, thickness):
            (a, av), (b, bv) = _point_p(a, "a"), _point_p(b, "b")
            thickness, _ = _positive_p(thickness, "thickness")
            if not _segment_length(av, bv) > 0:
                raise ValueError(
                    f"a and b must differ, got a={shown(av.tolist())}, "
                    f"b={shown(bv.tolist())} at the parameters' defaults"
                )
            self.a, self.b, self.thickness = a, b, thickness
            ex, ey = as_expr(b[0] - a[0]), as_expr(b[1] - a[1])
            span = sym_length(ex, ey)
            dx, dy = ex / sym_max(span, _TINY), ey / sym_max(span, _TINY)
            x, y = _coords()
            px, py = x - (a[0] + b[0]) / 2, y - (a[1] + b[1]) / 2
            qx = sym_abs(px * dx + py * dy) - span / 2
            qy = sym_abs(py * dx - px * dy) - thickness / 2
            super().__init__(_box_expr(qx, qy), _primitive_info(None, convex=True))
            return
        a, b = _point(a, "a"), _point(b, "b")
        thickness = _positive(thickness, "thickness")
        length = _segment_length(a, b)
        if not length > 0:
            raise ValueError(
                f"a and b must differ, got a={shown(a.tolist())}, b={shown(b.tolist())}"
            )
        self.a, self.b, self.thickness = a, b, thickness
        d = (b - a) / length
        m = (a + b) / 2
        x, y = _coords()
        px, py = x - float(m[0]), y - float(m[1])
        u = px * float(d[0]) + py * float(d[1])
        v = py * float(d[0]) - px * float(d[1])
        qx = sym_abs(u) - length / 2
        qy = sym_abs(v) - thickness / 2
        expr = _box_expr(qx, qy)
        n = np.array([-d[1], d[0]]) * thickness / 2
        corners = [a - n, b - n, b + n, a + n]
        info = _primitive_info(_points_bbox(corners), _edges_symmetry(corners), convex=True)
        super().__init__(expr, info)


class Triangle(SDF):
    """The triangle with corners ``p0, p1, p2`` (either orientation; not collinear).

    Parameters
    ----------
    p0, p1, p2 : pair (x, y), default (-1, -0.5), (1, -0.5), (0, 1)
        The corners, in the units of the coordinates.
    """

    vertices: np.ndarray | tuple

    def __init__(
        self,
        p0: PairOrParam = (-1.0, -0.5),
        p1: PairOrParam = (1.0, -0.5),
        p2: PairOrParam = (0.0, 1.0),
    ):
        pts = [_point_p(p, name) for p, name in ((p0, "p0"), (p1, "p1"), (p2, "p2"))]
        v = np.array([p[1] for p in pts])
        size = float(np.abs(v - v[0]).max())
        _check_length(size, "the triangle's size max|p_i - p0|")
        w = (v - v[0]) / size  # the checks in a frame of size 1: no over- or underflow
        e1, e2 = w[1], w[2]
        area2 = e1[0] * e2[1] - e1[1] * e2[0]
        scale = float(max(np.hypot(*e1), np.hypot(*e2), np.hypot(*(w[2] - w[1]))))
        if not abs(area2) > 1e-12 * scale * scale:
            raise ValueError(
                f"p0, p1, p2 must not be collinear, got p0={shown(v[0].tolist())}, "
                f"p1={shown(v[1].tolist())}, p2={shown(v[2].tolist())}"
            )
        if _any_param(p0, p1, p2):
            # Either orientation at run time: the sign of the (doubled) area picks the normals.
            (a, b, c) = [p[0] for p in pts]
            area2 = (b[0] - a[0]) * (c[1] - a[1]) - (b[1] - a[1]) * (c[0] - a[0])
            self.vertices = (a, b, c)
            expr = _convex_polygon_expr_p(*_coords(), self.vertices, sym_select(area2, 1.0, -1.0))
            super().__init__(expr, _primitive_info(None, convex=True))
            return
        ccw = _ccw(v)
        self.vertices = ccw
        info = _primitive_info(_points_bbox(v), _edges_symmetry(v), convex=True)
        super().__init__(_convex_polygon_expr(*_coords(), ccw), info)


def _regular_vertices(
    center: np.ndarray, radius: float, n: int, phase: float = math.pi / 2
) -> np.ndarray:
    t = phase + 2 * math.pi * np.arange(n) / n
    return np.stack([center[0] + radius * np.cos(t), center[1] + radius * np.sin(t)], -1)


def _check_n(n: object, name: str = "n", minimum: int = 3) -> int:
    if isinstance(n, (bool, np.bool_)) or not isinstance(n, numbers.Integral):
        raise TypeError(f"{name} must be an integer, got {name}={shown(n)}")
    if n < minimum:
        raise ValueError(f"{name} must be >= {minimum}, got {name}={shown(n)}")
    return int(n)


def _positive(value: object, name: str, size: bool = True) -> float:
    """A positive real; with ``size``, a length in the supported range."""
    value = _real(value, name)
    if value <= 0:
        raise ValueError(f"{name} must be > 0, got {name}={shown(value)}")
    if size:
        _check_length(value, name)
    return value


def _segment_length(a: np.ndarray, b: np.ndarray) -> float:
    """``|b - a|`` (overflow-free), which must be 0 or a length in the supported range."""
    e = b - a
    big = float(np.abs(e).max())
    length = big * math.hypot(*(e / big)) if big > 0 else 0.0
    if length > 0:
        _check_length(length, "the segment length |b - a|")
    return length


class RegularPolygon(SDF):
    """Regular ``n``-gon inscribed in the circle of ``radius`` (circumradius) around
    ``center``, one vertex pointing up (+y). Built from graph operations: ``n`` segments (one
    loop over a table in the generated code for ``n >= 4``).

    Parameters
    ----------
    center : pair (x, y), default (0, 0)
        The centre, in the units of the coordinates.
    radius : float > 0, default 1
        The circumradius (centre to vertex), in the same units.
    n : int >= 3, default 6
        The number of sides.
    """

    vertices: np.ndarray | list

    def __init__(self, center: PairOrParam = (0.0, 0.0), radius: FloatOrParam = 1.0, n: int = 6):
        _not_param(n, "n", "the number of vertices sets the structure of the generated code")
        n = _check_n(n)
        if _any_param(center, radius):
            center, _ = _point_p(center, "center")
            radius, _ = _positive_p(radius, "radius")
            self.center, self.radius, self.n = center, radius, n
            ang = math.pi / 2 + 2 * math.pi * np.arange(n) / n
            self.vertices = [
                (center[0] + radius * float(math.cos(a)), center[1] + radius * float(math.sin(a)))
                for a in ang
            ]
            super().__init__(
                _convex_polygon_expr_p(*_coords(), self.vertices),
                _primitive_info(None, convex=True),
            )
            return
        center = _point(center, "center")
        radius = _positive(radius, "radius")
        self.center, self.radius, self.n = center, radius, n
        v = _regular_vertices(center, radius, n)
        self.vertices = v
        sym = {"x"} if center[0] == 0 else set()
        if center[1] == 0 and n % 2 == 0:
            sym.add("y")
        info = _primitive_info(_points_bbox(v), sym, convex=True)
        super().__init__(_convex_polygon_expr(*_coords(), v), info)


class EquilateralTriangle(RegularPolygon):
    """Equilateral triangle inscribed in the circle of ``radius`` around ``center``, one
    corner pointing up (+y).

    ``center`` and ``radius`` (the circumradius: centre to corner) as for
    :class:`RegularPolygon`.
    """

    def __init__(self, center: PairOrParam = (0.0, 0.0), radius: FloatOrParam = 1.0):
        super().__init__(center=center, radius=radius, n=3)


@functools.lru_cache(maxsize=1024)
def _polygon_local(key: bytes, n: int) -> tuple:
    """What a polygon's checks and bookkeeping derive from its (deduplicated) vertices alone:
    ``(w, unit, data, bbox, sym, convex)``. Cached by the vertices' bytes: scenes repeat one
    shape many times (at other places, under :func:`transform`), and the simplicity check is
    O(n^2). A polygon that fails a check raises every time (exceptions are not cached)."""
    v = np.frombuffer(key, dtype=np.float64).reshape(n, 2)
    _check_length(float(np.abs(v - v[0]).max()), "the polygon's size max|v_i - v_0|")
    # Checks and the compiled loop (which compares squared lengths) work on the vertices
    # divided by a power of two near their magnitude: exact, and free of over- and
    # underflow at any scale. Polygons of moderate magnitude are left as they are.
    k = math.frexp(float(np.abs(v).max()))[1]
    unit = math.ldexp(1.0, -k) if abs(k) > 100 else 1.0
    w = v * unit
    _check_simple(w, "vertices")
    w = _ccw(w)
    w.flags.writeable = False  # shared by every polygon with these vertices
    data = tuple((float(p[0]), float(p[1])) for p in w)
    return w, unit, data, _points_bbox(v), _edges_symmetry(v), _is_convex(w)


class Polygon(SDF):
    """Any simple polygon, given by its vertices (either orientation, not repeated at the end).

    Collinear vertices (extra points on an edge) and consecutive duplicates are fine; the
    polygon must not intersect or touch itself and must enclose a non-zero area (checked, in
    O(n^2)). Evaluated by a compiled loop over the edges (graph op ``prim``, kind
    ``'polygon'``): O(n) per point; the vertices are a table in the generated module.

    Parameters
    ----------
    vertices : array (n, 2) or sequence of pairs (x, y), n >= 3
        The corners in order, in the units of the coordinates.
    """

    def __init__(self, vertices: ArrayLike | Sequence[PairOrParam]):
        if isinstance(vertices, (tuple, list)) and any(_any_param(p) for p in vertices):
            self._init_param(vertices)
            return
        v = _vertices(vertices, "vertices")
        if len(v) > 1 and np.all(v[0] == v[-1]):
            v = v[:-1]  # closed by repeating the first vertex: accepted
        keep = np.any(v != np.roll(v, 1, axis=0), axis=1)  # drop consecutive duplicates
        v = v[keep] if np.any(keep) else v[:1]
        if len(v) < 3:
            raise ValueError(
                f"vertices needs at least 3 distinct vertices, got "
                f"{shown(np.asarray(vertices).tolist())}"
            )
        w, unit, data, bbox, sym, convex = _polygon_local(v.tobytes(), len(v))
        self.vertices = w / unit
        x, y = _coords()
        if unit == 1.0:
            expr = sym_prim("polygon", x, y, data=data)
        else:
            expr = sym_prim("polygon", x * unit, y * unit, data=data) * (1.0 / unit)
        info = _primitive_info(bbox, sym, convex=convex)
        super().__init__(expr, info)

    def _init_param(self, vertices: Sequence[PairOrParam]) -> None:
        """Vertices given by parameters: checked at the parameters' defaults (simple, non-zero
        area, in range) and evaluated by graph operations (an unrolled loop over the edges)
        instead of the compiled loop, whose vertex table is part of the generated code."""
        pts = [_point_p(p, "vertices") for p in vertices]
        v = _vertices([p[1] for p in pts], "vertices")
        if len(v) > 1 and np.all(v[0] == v[-1]):
            pts, v = pts[:-1], v[:-1]
        keep = np.any(v != np.roll(v, 1, axis=0), axis=1)
        if np.any(keep):
            pts, v = [p for p, k in zip(pts, keep) if k], v[keep]
        if len(v) < 3:
            raise ValueError(f"vertices needs at least 3 distinct vertices, got {shown(vertices)}")
        _check_length(float(np.abs(v - v[0]).max()), "the polygon's size max|v_i - v_0|")
        _check_simple(v, "vertices")
        self.vertices = [p[0] for p in pts]
        SDF.__init__(self, _polygon_expr_p(*_coords(), self.vertices), _primitive_info(None))


class Star(Polygon):
    """Star with ``n`` points: a polygon alternating between ``radius`` (the tips, one
    pointing up) and ``inner_radius`` (default ``radius / 2``) around ``center``.

    Parameters
    ----------
    center : pair (x, y), default (0, 0)
        The centre, in the units of the coordinates.
    radius : float > 0, default 1
        The tips' distance from the centre, in the same units.
    n : int >= 2, default 5
        The number of tips.
    inner_radius : float, 0 < inner_radius < radius, or None (default: radius / 2)
        The notches' distance from the centre.
    """

    def __init__(
        self,
        center: PairOrParam = (0.0, 0.0),
        radius: FloatOrParam = 1.0,
        n: int = 5,
        inner_radius: FloatOrParam | None = None,
    ):
        _not_param(n, "n", "the number of points sets the structure of the generated code")
        if _any_param(center, radius, inner_radius):
            (center, _), (radius, rv) = _point_p(center, "center"), _positive_p(radius, "radius")
            inner, iv = (
                (radius / 2, rv / 2)
                if inner_radius is None
                else _positive_p(inner_radius, "inner_radius")
            )
            n = _check_n(n, minimum=2)
            if not iv < rv:
                raise ValueError(
                    f"inner_radius must be < radius, got inner_radius={shown(inner)}, "
                    f"radius={shown(radius)} (at the parameters' defaults)"
                )
            ang = math.pi / 2 + math.pi * np.arange(2 * n) / n
            pts = [
                (
                    center[0] + (radius if k % 2 == 0 else inner) * float(math.cos(a)),
                    center[1] + (radius if k % 2 == 0 else inner) * float(math.sin(a)),
                )
                for k, a in enumerate(ang)
            ]
            super().__init__(pts)
            self.center, self.radius, self.n, self.inner_radius = center, radius, n, inner
            return
        center = _point(center, "center")
        radius = _positive(radius, "radius")
        n = _check_n(n, minimum=2)
        inner = radius / 2 if inner_radius is None else _positive(inner_radius, "inner_radius")
        if not inner < radius:
            raise ValueError(
                f"inner_radius must be < radius, got inner_radius={shown(inner)}, "
                f"radius={shown(radius)}"
            )
        t = math.pi / 2 + math.pi * np.arange(2 * n) / n
        rr = np.where(np.arange(2 * n) % 2 == 0, radius, inner)
        v = np.stack([center[0] + rr * np.cos(t), center[1] + rr * np.sin(t)], -1)
        super().__init__(v)
        self.center, self.radius, self.n, self.inner_radius = center, radius, n, inner
        sym = {"x"} if center[0] == 0 else set()
        if center[1] == 0 and n % 2 == 0:
            sym.add("y")
        self._info = self._info._replace(
            sym=frozenset(sym) if _frame() == _IDENTITY else frozenset()
        )


# Beyond this axis ratio the closest-point solve's variables (which grow like the ratio
# cubed) could overflow.
_MAX_ECCENTRICITY = 1e50


class Ellipse(SDF):
    """Ellipse around ``center`` with semi-axes ``axes = (a, b)`` along the local x and y axes
    (exact for axis ratios up to 1e50; equal axes give a circle).

    Evaluated by a compiled closest-point solve (graph op ``prim``, kind ``'ellipse'``): a
    safeguarded Newton iteration, typically 3 to 6 steps (about 10x the cost of a circle);
    far away (beyond ``2**30`` times the largest radius of curvature) a closed form through
    the support point, exact to rounding there. At the centre the gradient points along the
    minor axis (+y for ``a > b``).

    Parameters
    ----------
    center : pair (x, y), default (0, 0)
        The centre, in the units of the coordinates.
    axes : pair (a, b) of floats > 0, default (1, 0.5)
        The semi-axes along the local x and y axes, in the same units.
    """

    def __init__(self, center: PairOrParam = (0.0, 0.0), axes: PairOrParam = (1.0, 0.5)):
        if _any_param(center, axes):
            (center, _), (axes_p, av) = _point_p(center, "center"), vec2_or_param(axes, "axes")
            self._check_axes(av)
            self.center, self.axes = center, axes_p
            x, y = _coords()
            # The axes are arguments of the compiled solve; its derivative in them (for dd/dt)
            # comes from the closest point (see fastsdf.expr.ops).
            expr = sym_prim("ellipse", x - center[0], y - center[1], axes_p[0], axes_p[1])
            super().__init__(expr, _primitive_info(None, convex=True))
            return
        center = _point(center, "center")
        axes = _vec2(axes, "axes")
        self._check_axes(axes)
        self.center, self.axes = center, axes
        x, y = _coords()
        expr = sym_prim(
            "ellipse", x - float(center[0]), y - float(center[1]), float(axes[0]), float(axes[1])
        )
        info = _primitive_info(
            _points_bbox([center - axes, center + axes]), _center_sym(center), convex=True
        )
        super().__init__(expr, info)

    @staticmethod
    def _check_axes(axes: np.ndarray) -> None:
        if not np.all(axes > 0):
            raise ValueError(f"axes must be > 0, got axes={shown(axes.tolist())}")
        for v in axes:
            _check_length(float(v), "axes", axes.tolist())
        if axes.max() / axes.min() > _MAX_ECCENTRICITY:
            raise ValueError(
                f"axes must not differ by more than a factor "
                f"{_MAX_ECCENTRICITY:g}, got axes={shown(axes.tolist())}"
            )


class Ring(SDF):
    """Annulus: the circle of ``radius`` around ``center`` thickened to total width
    ``thickness`` (``0 < thickness < 2 radius``): ``|length(p - c) - radius| - thickness/2``.

    Parameters
    ----------
    center : pair (x, y), default (0, 0)
        The centre, in the units of the coordinates.
    radius : float > 0, default 1
        The radius of the ring's centre line, in the same units.
    thickness : float, 0 < thickness < 2 radius, default 0.2
        The total width, in the same units.
    """

    def __init__(
        self,
        center: PairOrParam = (0.0, 0.0),
        radius: FloatOrParam = 1.0,
        thickness: FloatOrParam = 0.2,
    ):
        (center, cv), (radius, rv) = _point_p(center, "center"), _positive_p(radius, "radius")
        thickness, tv = _positive_p(thickness, "thickness")
        if not tv < 2 * rv:
            raise ValueError(
                f"thickness must be < 2 * radius (the hole would close), got "
                f"thickness={shown(thickness)}, radius={shown(radius)}"
            )
        self.center, self.radius, self.thickness = center, radius, thickness
        x, y = _coords()
        expr = sym_abs(sym_length(x - center[0], y - center[1]) - radius) - thickness / 2
        moving = _any_param(center, radius, thickness)
        info = _primitive_info(
            None if moving else _points_bbox([cv], rv + tv / 2), () if moving else _center_sym(cv)
        )
        super().__init__(expr, info)


class Arc(SDF):
    """Circular arc of ``radius`` around ``center``, spanning the angle ``aperture`` (radians,
    ``0 < aperture <= 2 pi``) symmetrically about the local +y axis, thickened to total width
    ``thickness`` with round ends (IQ's sdArc; rotate it with ``transform``).

    Exact when ``thickness < 2 radius`` and the two round ends do not overlap (their centres
    are at least ``thickness`` apart, or the arc is a full circle); otherwise exact outside and
    a bound inside (reported as ``'bound'``).

    Parameters
    ----------
    center : pair (x, y), default (0, 0)
        The circle's centre, in the units of the coordinates.
    radius : float > 0, default 1
        The radius of the arc's centre line, in the same units.
    aperture : float in (0, 2 pi], default pi
        The angle the arc spans, in radians.
    thickness : float > 0, default 0.2
        The total width, in the units of the coordinates.
    """

    def __init__(
        self,
        center: PairOrParam = (0.0, 0.0),
        radius: FloatOrParam = 1.0,
        aperture: FloatOrParam = math.pi,
        thickness: FloatOrParam = 0.2,
    ):
        (center, cv), (radius, rv) = _point_p(center, "center"), _positive_p(radius, "radius")
        aperture, apv = _positive_p(aperture, "aperture", size=False)
        if apv > 2 * math.pi:
            raise ValueError(f"aperture must be <= 2 pi, got aperture={shown(aperture)}")
        thickness, tv = _positive_p(thickness, "thickness")
        if not tv < 2 * rv:
            raise ValueError(
                f"thickness must be < 2 * radius, got thickness={shown(thickness)}, "
                f"radius={shown(radius)}"
            )
        moving = _any_param(center, radius, aperture, thickness)
        self.center, self.radius = center, radius
        self.aperture, self.thickness = aperture, thickness
        x, y = _coords()
        px, py = x - center[0], y - center[1]
        ring = sym_abs(sym_length(px, py) - radius)
        if not is_param(aperture) and aperture == 2 * math.pi:
            dist = ring
        else:
            # (at a full circle given by parameters, the end point's branch is the circle's
            # own value: the formula is continuous there)
            s, c = (
                (sym_sin(aperture / 2), sym_cos(aperture / 2))
                if is_param(aperture)
                else (math.sin(apv / 2), math.cos(apv / 2))
            )  # (apv = aperture: a number)
            ax = sym_abs(px)
            # beyond the end's ray the end point is nearest, else the circle
            dist = sym_select(ax * c - py * s, sym_length(ax - s * radius, py - c * radius), ring)
        gap = 2 * rv * math.sin(math.pi - apv / 2)  # distance between the ends
        exact = not _any_param(radius, aperture, thickness) and (apv == 2 * math.pi or gap >= tv)
        info = _primitive_info(
            None if moving else _points_bbox([cv], rv + tv / 2),
            set() if moving else _center_sym(cv) & {"x"},
        )
        if not exact:
            info = info._replace(inside=False)
        super().__init__(dist - thickness / 2, info)


# ---------------------------------------------------------------------------------------------
# Outlines of line and quadratic Bezier segments (fonts, SVG paths: fastsdf.geometry builds
# them from text and path data, cubics and arcs converted with a stated tolerance).

FILL_RULES = ("evenodd", "nonzero")


def _split_quadratic_y(row):
    """A quadratic segment row split at its y extremum (de Casteljau): one or two rows, each
    monotone in y."""
    kind, x0, y0, x1, y1, x2, y2 = row
    den = y0 - 2.0 * y1 + y2
    if kind != 1.0 or den == 0.0:
        return [row]
    t = (y0 - y1) / den
    if not 0.0 < t < 1.0:
        return [row]
    ax, ay = x0 + t * (x1 - x0), y0 + t * (y1 - y0)
    bx, by = x1 + t * (x2 - x1), y1 + t * (y2 - y1)
    mx, my = ax + t * (bx - ax), ay + t * (by - ay)
    return [(1.0, x0, y0, ax, ay, mx, my), (1.0, mx, my, bx, by, x2, y2)]


def outline_table(segments: ArrayLike, fill_rule: str = "nonzero") -> np.ndarray:
    """The table of the compiled ``outline`` primitive
    (:func:`fastsdf.backends.kernel.prims.outline_vg`)
    from segment rows ``[kind, x0, y0, x1, y1, x2, y2]`` (kind 0: the line from ``(x0, y0)``
    to ``(x2, y2)``; kind 1: the quadratic Bezier with control ``(x1, y1)``): quadratics split
    into y-monotone pieces, a bounding box per row, a header row with the fill rule."""
    if fill_rule not in FILL_RULES:
        raise ValueError(f"fill_rule must be one of {FILL_RULES}, got fill_rule={shown(fill_rule)}")
    seg = np.asarray(segments, dtype=np.float64)
    if seg.ndim != 2 or seg.shape[1] != 7 or len(seg) == 0:
        raise ValueError(
            f"segments must be rows [kind, x0, y0, x1, y1, x2, y2], got an array "
            f"of shape {seg.shape}"
        )
    if not np.isfinite(seg).all():
        raise ValueError("segments must hold finite numbers")
    if not np.isin(seg[:, 0], (0.0, 1.0)).all():
        raise ValueError(
            f"segment kinds must be 0 (line) or 1 (quadratic), got "
            f"{sorted(set(seg[:, 0].tolist()))}"
        )
    # Every end must be the start of another segment: closed loops (to a relative 1e-9).
    scale = float(np.abs(seg[:, 1:]).max()) or 1.0
    starts = np.round(seg[:, 1:3] / (1e-9 * scale))
    ends = np.round(seg[:, 5:7] / (1e-9 * scale))
    if not np.array_equal(starts[np.lexsort(starts.T)], ends[np.lexsort(ends.T)]):
        raise ValueError("segments must form closed loops (every segment's end is another's start)")
    rows = [r for row in seg.tolist() for r in _split_quadratic_y(tuple(row))]
    body = np.array(rows)
    pts = body[:, 1:7].reshape(-1, 3, 2)
    lines = body[:, 0] == 0.0
    pts[lines, 1] = pts[lines, 0]  # a line's unused control: not in its box
    lo, hi = pts.min(axis=1), pts.max(axis=1)
    table = np.zeros((len(body) + 1, 11))
    table[0, 0] = 1.0 if fill_rule == "evenodd" else 2.0
    table[1:, :7] = body
    table[1:, 7:9] = lo
    table[1:, 9:11] = hi
    return table


class Outline(SDF):
    """A region bounded by closed loops of line segments and quadratic Bezier segments, filled
    by the ``'nonzero'`` (default) or ``'evenodd'`` rule, holes included.

    ``segments``: rows ``[kind, x0, y0, x1, y1, x2, y2]`` (kind 0: a line from ``(x0, y0)`` to
    ``(x2, y2)``; kind 1: a quadratic Bezier with control point ``(x1, y1)``), forming closed
    loops. Exact distances (a quadratic's closest point solves a cubic, in closed form); one
    compiled loop over the segments (graph op ``prim``, kind ``'outline'``), skipping those
    whose bounding box is farther than the best so far. ``fastsdf.geometry`` builds outlines
    from SVG path data and text (cubics and arcs converted within a stated tolerance).

    Parameters
    ----------
    segments : array (n, 7)
        The rows above, in the units of the coordinates.
    fill_rule : 'nonzero' (default) or 'evenodd'
        Which points the loops enclose: a non-zero winding number, or an odd one.
    """

    def __init__(self, segments: ArrayLike, fill_rule: str = "nonzero"):
        table = outline_table(segments, fill_rule)
        self.segments = table[1:, :7]
        self.fill_rule = fill_rule
        data = tuple(map(tuple, table.tolist()))
        x, y = _coords()
        expr = sym_prim("outline", x, y, data=data)
        bbox = (
            float(table[1:, 7].min()),
            float(table[1:, 8].min()),
            float(table[1:, 9].max()),
            float(table[1:, 10].max()),
        )
        super().__init__(expr, _primitive_info(bbox))
