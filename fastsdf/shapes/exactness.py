"""Exactness bookkeeping: what is known about each shape (exact outside/inside, a bound,
convexity, bounding box, mirror symmetries) and the rules that carry it through operations."""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from typing import Any, NamedTuple

import numpy as np
from numpy.typing import ArrayLike

from fastsdf.expr.validate import FloatOrParam
from fastsdf.shapes.context import _IDENTITY, _frame

__all__ = ["EXACTNESS"]

#: Values of :attr:`fastsdf.shapes.SDF.exactness`.
EXACTNESS = ("exact", "bound", "none")

#
# Every SDF carries an _Info: whether its value is the exact distance outside (f > 0) and
# inside (f < 0), whether it is a bound (1-Lipschitz: |f| <= distance to the boundary of
# {f < 0}, with the correct sign), and what is known about its shape that later operations use
# to keep exactness: convexity, a bounding box, mirror symmetries about the coordinate axes.
# Unknown means False / None / empty: the flags are conservative.


class _Info(NamedTuple):  # (a named tuple: cheaper to build than a frozen dataclass)
    outside: bool = False  # exact where f > 0
    inside: bool = False  # exact where f < 0
    bound: bool = False  # 1-Lipschitz (implies |f| <= true distance, sign correct)
    convex: bool = False  # the shape {f <= 0} is convex
    bbox: tuple | None = None  # (xmin, ymin, xmax, ymax) containing the shape
    sym: frozenset = frozenset()  # 'x': f(-x, y) = f(x, y); 'y': f(x, -y) = f(x, y)


_NONE = _Info()


def _frame_bbox(bbox: tuple | None, frame: tuple | None = None) -> tuple | None:
    """World bounding box of a local bounding box under the current (or given) frame."""
    frame = _frame() if frame is None else frame
    if bbox is None or frame is None:  # no frame: the primitive moves with parameters
        return None
    m00, m01, m10, m11, tx, ty = frame
    xs, ys = (bbox[0], bbox[2]), (bbox[1], bbox[3])
    cx = [m00 * u + m01 * v + tx for u in xs for v in ys]
    cy = [m10 * u + m11 * v + ty for u in xs for v in ys]
    return (min(cx), min(cy), max(cx), max(cy))


def _grow(bbox: tuple | None, r: float) -> tuple | None:
    if bbox is None:
        return None
    return (bbox[0] - r, bbox[1] - r, bbox[2] + r, bbox[3] + r)


def _primitive_info(
    bbox: tuple | None, sym: Iterable[str] = (), convex: bool = False, exact: bool = True
) -> _Info:
    """Info of a primitive built now, from its local bounding box and symmetries."""
    world_sym = frozenset(sym) if _frame() == _IDENTITY else frozenset()
    return _Info(
        outside=exact,
        inside=exact,
        bound=True,
        convex=convex,
        bbox=_frame_bbox(bbox),
        sym=world_sym,
    )


def _points_bbox(
    points: Sequence[Any] | np.ndarray, r: float = 0.0
) -> tuple[float, float, float, float]:
    p = np.asarray(points, dtype=np.float64)
    return (
        float(p[:, 0].min() - r),
        float(p[:, 1].min() - r),
        float(p[:, 0].max() + r),
        float(p[:, 1].max() + r),
    )


def _edges_symmetry(points: ArrayLike, closed: bool = True) -> frozenset:
    """Axes about which the polyline through ``points`` is mirror-symmetric (to 1e-12)."""
    p = np.asarray(points, dtype=np.float64)
    tol = 1e-12 * (float(np.abs(p).max()) or 1.0)  # relative: also for tiny shapes
    q = np.roll(p, -1, axis=0) if closed else p[1:]
    p = p if closed else p[:-1]
    edges = np.concatenate([p, q], axis=1)
    edges = np.concatenate([edges, edges[:, [2, 3, 0, 1]]])  # both directions

    # equal as sets of edges, to the tolerance (conservative at its edge)
    def same(a: np.ndarray, b: np.ndarray) -> bool:
        a, b = np.round(a / tol), np.round(b / tol)
        return np.array_equal(a[np.lexsort(a.T[::-1])], b[np.lexsort(b.T[::-1])])

    out = set()
    if same(edges, edges * [-1, 1, -1, 1]):
        out.add("x")
    if same(edges, edges * [1, -1, 1, -1]):
        out.add("y")
    return frozenset(out)


def _center_sym(center: Iterable) -> set:
    return {axis for axis, c in zip("xy", center) if c == 0.0}


def _blend_depth(k: FloatOrParam, kind: str) -> float | None:
    """How far a smooth union can reach beyond the hard one (bounding boxes grow by this)."""
    if not isinstance(k, float):
        return None  # a blend width given by parameters: unknown
    if k == 0.0:
        return 0.0
    return {"exponential": math.log(2.0) / k, "quadratic": k / 4.0, "cubic": k / 6.0}[kind]


def _bbox_union(a: tuple | None, b: tuple | None, grow: float | None = 0.0) -> tuple | None:
    if a is None or b is None or grow is None:
        return None
    return _grow((min(a[0], b[0]), min(a[1], b[1]), max(a[2], b[2]), max(a[3], b[3])), grow)


def _complement_info(info: _Info) -> _Info:
    """Info of the complement ``-f``: the shape ``{f > 0}``, with the same boundary. Exact
    outside where ``f`` was exact inside and the other way round; a bound if ``f`` is one
    (``|-f| = |f|``, the sign flips with the side); mirror symmetries kept. Unbounded (no
    bounding box) and, conservatively, not convex (only a half-plane's complement is)."""
    return _Info(outside=info.inside, inside=info.outside, bound=info.bound, sym=info.sym)


def _bbox_meet(a: tuple | None, b: tuple | None) -> tuple | None:
    if a is None:
        return b
    if b is None:
        return a
    return (max(a[0], b[0]), max(a[1], b[1]), min(a[2], b[2]), min(a[3], b[3]))
