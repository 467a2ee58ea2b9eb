"""The :class:`SDF` base class, set operations (hard and blended) and modifiers."""

from __future__ import annotations

import math
import numbers
from collections.abc import Callable, Iterable
from typing import Any

import numpy as np

from fastsdf.expr.graph import (
    Expr,
    gc_paused,
    substitute,
    sym_abs,
    sym_cmin,
    sym_cos,
    sym_exp,
    sym_floor,
    sym_log,
    sym_max,
    sym_min,
    sym_qmin,
    sym_sin,
    sym_smax,
    sym_smin,
)
from fastsdf.expr.interval import note_lipschitz
from fastsdf.expr.validate import (
    FloatOrParam,
    PairOrParam,
    coord2_or_param,
    is_param,
    real_or_param,
    shown,
)
from fastsdf.expr.validate import check_length as _check_length
from fastsdf.expr.validate import length as _length
from fastsdf.function import Function
from fastsdf.shapes.context import _X, _Y, _blend_kind, _smoothness_value, current_blend
from fastsdf.shapes.exactness import (
    _NONE,
    _bbox_meet,
    _bbox_union,
    _blend_depth,
    _complement_info,
    _frame_bbox,
    _grow,
    _Info,
)

__all__ = [
    "SDF",
    "Union",
    "Intersection",
    "Difference",
    "union",
    "intersection",
    "offset",
    "shell",
    "scale",
    "translate",
    "rotate",
    "mirror",
    "repeat",
]


# ---------------------------------------------------------------------------------------------
# Blends: the hard operations, the notebook's exponential blends, the polynomial ones.


def _param_blend_min(a: Expr, b: Expr, k: Expr, kind: str) -> Expr:
    """A blend whose ``k`` is an expression of runtime parameters, from generic operations
    (the ``smin``/``qmin``/``cmin`` nodes take a constant ``k``): the same formulas, so the same
    values, and the gradient (in x, y and t) from the graph."""
    m = sym_min(a, b)
    if kind == "exponential":
        return m - sym_log(1.0 + sym_exp(-k * sym_abs(a - b))) / k
    h = sym_max(k - sym_abs(a - b), 0.0) / k
    return m - (k * h * h * h / 6.0 if kind == "cubic" else k * h * h / 4.0)


def _blend_min(a: Expr, b: Expr, k: FloatOrParam, kind: str) -> Expr:
    if is_param(k):
        return _param_blend_min(a, b, k, kind)
    if k == 0.0:
        return sym_min(a, b)
    if kind == "exponential":
        return sym_smin(a, b, k)
    return (sym_qmin if kind == "quadratic" else sym_cmin)(a, b, k)


def _blend_max(a: Expr, b: Expr, k: FloatOrParam, kind: str) -> Expr:
    if is_param(k):
        return -_param_blend_min(-a, -b, k, kind)
    if k == 0.0:
        return sym_max(a, b)
    if kind == "exponential":
        return sym_smax(a, b, k)
    return -(sym_qmin if kind == "quadratic" else sym_cmin)(-a, -b, k)


def _check_sdf(value: object, name: str) -> SDF:
    if not isinstance(value, SDF):
        raise TypeError(
            f"{name} must be a fastsdf SDF, got {name}={shown(value)} of type "
            f"{type(value).__name__}"
        )
    return value


# ---------------------------------------------------------------------------------------------
# Shapes.


class SDF(Function):
    """A signed distance function of the plane: negative inside, positive outside.

    Callable as ``f(x, y, compute_gradient=False)`` (see :class:`fastsdf.function.Function`);
    ``f.f`` is its expression. Combine with ``|`` (union), ``&`` (intersection), ``-``
    (difference); ``|=`` and friends work too; ``-f`` is the complement: everything outside
    the shape, the value negated (exact where ``f`` is, unbounded). The operators blend as the
    :func:`smoothness` context says; the methods :meth:`union`, :meth:`intersection`,
    :meth:`difference` take the blend explicitly. :attr:`exactness` says how far the value can
    be trusted as a distance.

    Parameters
    ----------
    expr : Expr
        The expression of the coordinates ``x`` and ``y`` (built by the primitives and
        operations; ``SDF(expr)`` wraps one written by hand, see docs/modelling.md).
    info : internal, default None
        What is known of the expression (exactness, bounding box, symmetries); ``None``:
        nothing (``exactness == 'none'``).
    """

    def __init__(self, expr: Expr, info: _Info | None = None):
        super().__init__(expr, [_X, _Y])
        self._info = _NONE if info is None else info
        # Interval bounds may use |f(p) - f(c)| <= |p - c|: in x and y only, not in runtime
        # parameters (a moving circle's distance changes with its centre too).
        if self._info.bound and not self.f.prms:
            note_lipschitz(self.f, 1.0)

    @property
    def sdf(self) -> Expr:
        """The expression (the name cgraph's SDF nodes used)."""
        return self.f

    # -- exactness -----------------------------------------------------------------------------
    @property
    def exactness(self) -> str:
        """``'exact'``: the value is the Euclidean distance to the boundary of the shape
        ``{f < 0}`` (negative inside) everywhere. ``'bound'``: ``|f|`` never exceeds that
        distance and the sign is right (``f`` is 1-Lipschitz), so sphere tracing and collision
        tests stay safe, but distances can be underestimated. ``'none'``: no guarantee. The
        flags follow the rules in the docs (docs/modelling.md, "Why these flags") and are
        conservative: a result reported ``'bound'`` may happen to be exact."""
        i = self._info
        if i.outside and i.inside:
            return "exact"
        return "bound" if i.bound else "none"

    @property
    def exact_outside(self) -> bool:
        """True where known: the value is the exact distance at every point outside."""
        return self._info.outside

    @property
    def exact_inside(self) -> bool:
        """True where known: the value is the exact (negated) distance at every point inside."""
        return self._info.inside

    # -- set operations ------------------------------------------------------------------------
    def _other(self, other: object, op: str) -> SDF:
        if not isinstance(other, SDF):
            raise TypeError(
                f"cannot {op} an SDF with {shown(other)} of type {type(other).__name__}; "
                "both operands must be fastsdf SDF objects"
            )
        return other

    def __or__(self, other: SDF) -> Union:
        k, kind = current_blend()
        return Union(self, self._other(other, "unite"), k=k, kind=kind)

    def __and__(self, other: SDF) -> Intersection:
        k, kind = current_blend()
        return Intersection(self, self._other(other, "intersect"), k=k, kind=kind)

    def __sub__(self, other: SDF) -> Difference:
        return Difference(self, self._other(other, "subtract"))

    def __neg__(self) -> SDF:
        """The complement: the value negated, so the inside is everything outside the shape
        (``a - b`` is ``a & -b``). The boundary and the distance to it are the same: exact
        where ``f`` is exact (outside where ``f`` was exact inside, and the other way round),
        a bound if ``f`` is one. The complement of a bounded shape is unbounded."""
        return SDF(-self.f, _complement_info(self._info))

    def union(self, other: SDF, k: FloatOrParam = 0.0, kind: str = "exponential") -> SDF:
        """``self | other`` with an explicit blend (the :func:`smoothness` context is ignored):
        ``k = 0`` hard; ``kind='exponential'`` (``k`` = sharpness, 1/distance), ``'quadratic'``
        or ``'cubic'`` (``k`` = blend width, distance). See :class:`Union`."""
        return Union(self, self._other(other, "unite"), k=k, kind=kind)

    def intersection(self, other: SDF, k: FloatOrParam = 0.0, kind: str = "exponential") -> SDF:
        """``self & other`` with an explicit blend, ``k`` and ``kind`` as for :meth:`union`
        (see :class:`Intersection`)."""
        return Intersection(self, self._other(other, "intersect"), k=k, kind=kind)

    def difference(self, other: SDF, k: FloatOrParam = 0.0, kind: str = "exponential") -> SDF:
        """``self - other``, smooth for ``k > 0``; ``k`` and ``kind`` as for :meth:`union` (see
        :class:`Difference`)."""
        return Difference(self, self._other(other, "subtract"), k=k, kind=kind)

    # -- modifiers -----------------------------------------------------------------------------
    def round(self, r: FloatOrParam) -> SDF:
        """Offset: ``f - r`` (``r > 0`` grows the shape and rounds its convex corners by
        ``r``; ``r < 0`` erodes it).

        Exactness, for ``r > 0``: exact outside if ``f`` is; exact inside too if ``f`` is exact
        and its shape is convex (a rounded box, a capsule from a segment). For a non-convex
        shape the inside value is only a bound (filled concavities are deeper than ``r - f``).
        For ``r < 0``: exact inside if ``f`` is, a bound outside. Always a bound if ``f`` is.
        """
        i = self._info
        if is_param(r):  # its sign may change at run time: only a bound is kept
            rp, _ = real_or_param(r, "r")
            return SDF(self.f - rp, _Info(bound=i.bound))
        r = _length(r, "r", zero=True)
        if r == 0:
            return SDF(self.f, i)
        if r > 0:
            info = i._replace(inside=i.inside and i.outside and i.convex, bbox=_grow(i.bbox, r))
        else:
            info = i._replace(outside=False)
        return SDF(self.f - r, info)

    def shell(self, thickness: FloatOrParam) -> SDF:
        """Annulus of the boundary: ``|f| - thickness / 2``, a band of total width
        ``thickness`` centred on the surface (IQ's onion).

        Exact outside the band if ``f`` is exact (inside and outside); inside the band a
        bound (exact inside the band only where the surface is a circle, see :class:`Ring`:
        near a corner the band's inner edge is farther than the formula says).
        """
        t, tv = real_or_param(thickness, "thickness")
        if tv <= 0:
            raise ValueError(f"thickness must be > 0, got thickness={shown(thickness)}")
        _check_length(tv, "thickness")
        i = self._info
        info = _Info(
            outside=i.outside and i.inside,
            inside=False,
            bound=i.bound,
            bbox=None if is_param(t) else _grow(i.bbox, tv / 2),
            sym=i.sym,
        )
        return SDF(sym_abs(self.f) - t / 2, info)

    def scale(self, s: FloatOrParam) -> SDF:
        """Uniform scale about the origin: ``s * f(p / s)`` with ``s > 0``; keeps the value a
        distance, so exactness is kept."""
        factor, sv = real_or_param(s, "s")
        if sv <= 0:
            raise ValueError(f"s must be > 0, got s={shown(factor)}")
        _check_length(sv, "s")
        inv = 1.0 / factor
        i = self._info
        bbox = None if i.bbox is None or is_param(factor) else tuple(v * sv for v in i.bbox)
        return SDF(
            substitute(self.f, {"x": _X * inv, "y": _Y * inv}) * factor, i._replace(bbox=bbox)
        )

    def translate(self, offset: PairOrParam) -> SDF:
        """The shape moved by ``offset``: ``f(p - offset)``, in the coordinates of ``f`` (an
        active :func:`transform` context plays no part). Same as building it under
        ``transform(offset=offset)``; keeps exactness."""
        o, numbers_ = coord2_or_param(offset, "offset")
        i = self._info
        if any(is_param(v) for v in o):  # moved by runtime parameters
            expr = substitute(self.f, {"x": _X - o[0], "y": _Y - o[1]})
            return SDF(expr, i._replace(bbox=None, sym=frozenset()))
        o = numbers_  # (the same array: no parameters)
        bbox = (
            None
            if i.bbox is None
            else (i.bbox[0] + o[0], i.bbox[1] + o[1], i.bbox[2] + o[0], i.bbox[3] + o[1])
        )
        sym = frozenset(a for a, ov in zip("xy", o) if a in i.sym and ov == 0.0)
        expr = substitute(self.f, {"x": _X - float(o[0]), "y": _Y - float(o[1])})
        return SDF(expr, i._replace(bbox=bbox, sym=sym))

    def rotate(self, angle: FloatOrParam) -> SDF:
        """The shape rotated counter-clockwise by ``angle`` (radians) about the origin:
        ``f(R(-angle) p)``. Same as building it under ``transform(angle=angle)``; keeps
        exactness."""
        a, a0 = real_or_param(angle, "angle")  # (a0 = a unless a is a parameter expression)
        i = self._info
        if is_param(a):  # turned by runtime parameters
            pc, ps = sym_cos(a), sym_sin(a)
            expr = substitute(self.f, {"x": _X * pc + _Y * ps, "y": _Y * pc - _X * ps})
            return SDF(expr, i._replace(bbox=None, sym=frozenset()))
        c, s = math.cos(a0), math.sin(a0)
        bbox = _frame_bbox(i.bbox, (c, -s, s, c, 0.0, 0.0))
        sym = i.sym if a0 == 0.0 else frozenset()
        expr = substitute(self.f, {"x": _X * c + _Y * s, "y": _Y * c - _X * s})
        return SDF(expr, i._replace(bbox=bbox, sym=sym))

    def mirror(self, axis: str = "x") -> SDF:
        """Mirror symmetry: ``axis='x'`` evaluates ``f(|x|, y)``, the part of the shape with
        ``x >= 0`` plus its mirror image in the line ``x = 0``; ``'y'`` likewise
        ``f(x, |y|)``; ``'xy'`` both.

        A bound if ``f`` is one. Exact if ``f`` is exact and either already symmetric about
        that axis or known (from its bounding box) to lie strictly on the positive side;
        otherwise the part of the shape on the negative side, now cut away, can make the
        value smaller than the distance.
        """
        if axis not in ("x", "y", "xy"):
            raise ValueError(f"axis must be 'x', 'y' or 'xy', got axis={shown(axis)}")
        f = self
        for ax in axis:
            i = f._info
            if ax in i.sym:
                continue
            j = 0 if ax == "x" else 1
            sub = {"x": sym_abs(_X)} if ax == "x" else {"y": sym_abs(_Y)}
            disjoint = i.bbox is not None and i.bbox[j] > 0.0
            bbox = None
            if i.bbox is not None:
                lo, hi = list(i.bbox[:2]), list(i.bbox[2:])
                top = max(hi[j], 0.0)
                lo[j], hi[j] = -top, top
                bbox = (lo[0], lo[1], hi[0], hi[1])
            info = _Info(
                outside=i.outside and disjoint,
                inside=i.inside and disjoint,
                bound=i.bound,
                bbox=bbox,
                sym=i.sym | {ax},
            )
            f = SDF(substitute(f.f, sub), info)
        return f

    def repeat(self, spacing: FloatOrParam | PairOrParam, count: FloatOrParam | PairOrParam) -> SDF:
        """Finite repetition (IQ's opRepLim): copies of the shape at
        ``(i * spacing_x, j * spacing_y)`` for ``0 <= i < count_x``, ``0 <= j < count_y``.
        ``spacing`` and ``count`` are numbers or pairs; a count of 1 leaves that axis alone.

        Each point evaluates only the copy whose centre (the origin, shifted) is nearest. That
        is exact when ``f`` is exact and mirror-symmetric about each repeated axis (then the
        nearest centre is the nearest copy) and the shape lies within its cell
        ``|x| < spacing_x / 2`` (copies do not overlap); symmetric but overlapping: exact
        outside, a bound inside. For a shape that is not symmetric the nearest copy can be
        another one, and the value jumps at cell borders: exactness ``'none'``. Known symmetry
        comes from the construction (primitives centred at the origin, :meth:`mirror`).
        """
        sp_checked = _pair(spacing, "spacing", lambda v, name: real_or_param(v, name))
        ct = _pair(count, "count", _count)
        spv = [v[1] for v in sp_checked]
        sp = [v[0] for v in sp_checked]
        if not all(v > 0 for v in spv):
            raise ValueError(f"spacing must be > 0, got spacing={shown(spacing)}")
        for v in spv:
            _check_length(v, "spacing", spacing)
        i = self._info
        if any(is_param(v) for v in (*sp, *ct)):  # given by parameters: the copies move
            i = i._replace(bbox=None)
        sub: dict[str, Expr] = {}
        symmetric, contained = True, i.bbox is not None
        lo = list(i.bbox[:2]) if i.bbox is not None else None
        hi = list(i.bbox[2:]) if i.bbox is not None else None
        for j, (ax, s, n) in enumerate(zip("xy", sp, ct)):
            if n == 1:
                continue
            coord = _X if ax == "x" else _Y
            cell = sym_min(sym_max(sym_floor(coord * (1.0 / s) + 0.5), 0.0), n - 1)
            sub[ax] = coord - cell * s
            symmetric = symmetric and ax in i.sym
            if i.bbox is not None and hi is not None:
                contained = contained and max(-i.bbox[j], i.bbox[2 + j]) < spv[j] / 2
                hi[j] += (n - 1) * s
        if not sub:
            return self
        info = _Info(
            outside=symmetric and i.outside,
            inside=symmetric and contained and i.inside,
            bound=symmetric and i.bound,
            bbox=None if lo is None or hi is None else (lo[0], lo[1], hi[0], hi[1]),
        )
        return SDF(substitute(self.f, sub), info)

    def __repr__(self) -> str:
        return f"{type(self).__name__}({str(self.f)[:200]})"


def _pair(value: object, name: str, check: Callable[[Any, str], Any]) -> tuple:
    if isinstance(value, (tuple, list, np.ndarray)):
        if len(value) != 2:
            raise ValueError(f"{name} must be a number or a pair, got {name}={shown(value)}")
        return tuple(check(v, name) for v in value)
    v = check(value, name)
    return (v, v)


def _count(value: object, name: str) -> Expr | int:
    """A count: an integer >= 1, or an expression of parameters (rounded down at run time,
    checked at the defaults)."""
    if is_param(value):
        expr, number = real_or_param(value, name)
        if number < 1 or number != int(number):
            raise ValueError(
                f"{name} must be an integer >= 1, got {name}={expr} = {shown(number)} "
                f"at the parameters' defaults"
            )
        return sym_floor(expr)
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, numbers.Integral):
        raise TypeError(f"{name} must be an integer, got {name}={shown(value)}")
    if value < 1:
        raise ValueError(f"{name} must be >= 1, got {name}={shown(value)}")
    return int(value)


# Modifiers as functions (the methods of SDF).


def offset(f: SDF, r: FloatOrParam) -> SDF:
    """``f.round(r)``: the shape offset by ``r`` (see :meth:`SDF.round`)."""
    return _check_sdf(f, "f").round(r)


def shell(f: SDF, thickness: FloatOrParam) -> SDF:
    """``f.shell(thickness)`` (see :meth:`SDF.shell`)."""
    return _check_sdf(f, "f").shell(thickness)


def scale(f: SDF, s: FloatOrParam) -> SDF:
    """``f.scale(s)`` (see :meth:`SDF.scale`)."""
    return _check_sdf(f, "f").scale(s)


def translate(f: SDF, offset: PairOrParam) -> SDF:  # shadows offset() here only
    """``f.translate(offset)`` (see :meth:`SDF.translate`)."""
    return _check_sdf(f, "f").translate(offset)


def rotate(f: SDF, angle: FloatOrParam) -> SDF:
    """``f.rotate(angle)`` (see :meth:`SDF.rotate`)."""
    return _check_sdf(f, "f").rotate(angle)


def mirror(f: SDF, axis: str = "x") -> SDF:
    """``f.mirror(axis)`` (see :meth:`SDF.mirror`)."""
    return _check_sdf(f, "f").mirror(axis)


def repeat(f: SDF, spacing: FloatOrParam | PairOrParam, count: FloatOrParam | PairOrParam) -> SDF:
    """``f.repeat(spacing, count)`` (see :meth:`SDF.repeat`)."""
    return _check_sdf(f, "f").repeat(spacing, count)


# ---------------------------------------------------------------------------------------------
# Set operations.


def _k_and_kind(k: object, kind: object) -> tuple[FloatOrParam, str]:
    return _smoothness_value(k), _blend_kind(kind)


def _operands(a: object, b: object, k: object, kind: object) -> tuple:
    """``(a, b, k, kind)`` of a set operation, checked."""
    return (_check_sdf(a, "a"), _check_sdf(b, "b"), *_k_and_kind(k, kind))


class Union(SDF):
    """Union of two SDFs: ``min(a, b)``, or a smooth minimum for ``k > 0``: the notebook's
    exponential one (``kind='exponential'``, ``k`` = sharpness in 1/distance, deepens by at
    most ``log(2)/k``), or the polynomial ones (``'quadratic'``, ``'cubic'``, ``k`` = blend width
    in distance units: exactly ``min`` where ``|a - b| >= k``, deepened by ``k/4`` resp. ``k/6``
    where ``a = b``; C1 resp. C2).

    Exactness: the hard union of exact SDFs is exact outside and a bound inside (where the
    shapes overlap, the boundary of the union is farther than the nearer shape's). Every blend
    of bounds is a bound: its gradient is a convex combination of the operands' gradients, so
    it is 1-Lipschitz.

    Parameters
    ----------
    a, b : SDF
        The operands.
    k : float >= 0, default 0
        The blend: 0 is hard; for ``kind='exponential'`` the sharpness, in 1 / (unit of the
        coordinates); for the polynomial kinds the blend width, in the units of the
        coordinates. Also an expression of runtime parameters.
    kind : 'exponential' (default), 'quadratic' or 'cubic'
        The blend's formula.
    """

    def __init__(self, a: SDF, b: SDF, k: FloatOrParam = 0.0, kind: str = "exponential"):
        a, b, k, kind = _operands(a, b, k, kind)
        joined = _union([a, b], k, kind)  # (the rules of many shapes' union, for two)
        super().__init__(joined.f, joined._info)


class Intersection(SDF):
    """Intersection of two SDFs: ``max(a, b)``, or a smooth maximum for ``k > 0`` (the blends
    of :class:`Union`, mirrored: ``smax(a, b) = -smin(-a, -b)``).

    Exactness: the hard intersection of exact SDFs is exact inside and a bound outside (near a
    corner the distance to the intersection is larger than either operand). Blends: a bound.

    ``a``, ``b``: the operands (SDFs); ``k``, ``kind``: the blend, as for :class:`Union`
    (default: hard).
    """

    def __init__(self, a: SDF, b: SDF, k: FloatOrParam = 0.0, kind: str = "exponential"):
        a, b, k, kind = _operands(a, b, k, kind)
        joined = _intersection([a, b], k, kind)
        super().__init__(joined.f, joined._info)


class Difference(SDF):
    """``a`` with ``b`` cut away: ``max(a, -b)``. Hard by default, as in the notebook (and ``-``
    is always hard); ``k > 0`` blends like :class:`Intersection` with ``-b``.

    Exactness: exact inside where ``a`` is exact inside and ``b`` exact outside; a bound
    outside. Blends: a bound.

    ``a``: the shape, ``b``: the shape cut from it (SDFs); ``k``, ``kind``: the blend, as for
    :class:`Union` (default: hard).
    """

    def __init__(self, a: SDF, b: SDF, k: FloatOrParam = 0.0, kind: str = "exponential"):
        a, b, k, kind = _operands(a, b, k, kind)
        ia, ib = a._info, b._info
        info = _Info(
            inside=k == 0 and ia.inside and ib.outside,
            bound=ia.bound and ib.bound,
            bbox=ia.bbox,
            sym=ia.sym & ib.sym,
        )
        super().__init__(_blend_max(a.f, -b.f, k, kind), info)


# ---------------------------------------------------------------------------------------------
# Many shapes at once.


def _shapes_list(shapes: Iterable[SDF], name: str) -> list[SDF]:
    if isinstance(shapes, SDF):
        raise TypeError(
            f"{name} takes an iterable of SDFs (a list, a generator), got one SDF; "
            f"write {name}([a, b, ...])"
        )
    try:
        out = list(shapes)
    except TypeError:
        raise TypeError(
            f"shapes must be an iterable of fastsdf SDF objects, got "
            f"{shown(shapes)} of type {type(shapes).__name__}"
        ) from None
    if not out:
        raise ValueError(f"{name} needs at least one shape, got an empty iterable")
    for i, f in enumerate(out):
        _check_sdf(f, f"shapes[{i}]")
    return out


def union(shapes: Iterable[SDF], k: FloatOrParam = 0.0, kind: str = "exponential") -> SDF:
    """The union of many shapes: ``shapes[0] | shapes[1] | ...`` with one blend (``k`` and
    ``kind`` as for :class:`Union`; the :func:`smoothness` context is not used).

    The same expression as the left fold of :class:`Union` (so the same kernels and exactness
    flags), built in one step instead of one intermediate :class:`SDF` per shape: write a large
    scene as ``union(Box(lo, hi) for lo, hi in corners)``. One shape is returned as it is.
    """
    out = _shapes_list(shapes, "union")
    k, kind = _k_and_kind(k, kind)
    if len(out) == 1:
        return out[0]
    with gc_paused():  # a bulk pass (see fastsdf.expr.graph._GCPaused)
        return _union(out, k, kind)


def _union(out: list, k: FloatOrParam, kind: str) -> SDF:
    e, info = out[0].f, out[0]._info
    outside, bound, bbox, sym = info.outside, info.bound, info.bbox, info.sym
    depth = _blend_depth(k, kind)
    for f in out[1:]:
        i = f._info
        e = _blend_min(e, f.f, k, kind)
        # the rules of Union, step by step (the bounding box grows at every blend)
        outside = k == 0 and outside and i.outside
        bound = bound and i.bound
        bbox = _bbox_union(bbox, i.bbox, depth)
        sym = sym & i.sym
        if bound and not e.prms:  # as the intermediate Union would note (see SDF)
            note_lipschitz(e, 1.0)
    return SDF(e, _Info(outside=outside, bound=bound, bbox=bbox, sym=sym))


def intersection(shapes: Iterable[SDF], k: FloatOrParam = 0.0, kind: str = "exponential") -> SDF:
    """The intersection of many shapes: ``shapes[0] & shapes[1] & ...`` with one blend (``k``
    and ``kind`` as for :class:`Union`; the :func:`smoothness` context is not used), built in
    one step (see :func:`union`)."""
    out = _shapes_list(shapes, "intersection")
    k, kind = _k_and_kind(k, kind)
    if len(out) == 1:
        return out[0]
    with gc_paused():
        return _intersection(out, k, kind)


def _intersection(out: list, k: FloatOrParam, kind: str) -> SDF:
    e, info = out[0].f, out[0]._info
    inside, bound, convex, bbox, sym = info.inside, info.bound, info.convex, info.bbox, info.sym
    for f in out[1:]:
        i = f._info
        e = _blend_max(e, f.f, k, kind)
        inside = k == 0 and inside and i.inside
        bound = bound and i.bound
        convex = k == 0 and convex and i.convex
        bbox = _bbox_meet(bbox, i.bbox)
        sym = sym & i.sym
        if bound and not e.prms:
            note_lipschitz(e, 1.0)
    return SDF(e, _Info(inside=inside, bound=bound, convex=convex, bbox=bbox, sym=sym))
