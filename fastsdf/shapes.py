"""The modelling DSL: primitives, set operations and the modelling context.

Usage mirrors the notebook's ``cgraph.sdf``::

    import fastsdf as sdf
    f = sdf.Halfspace(normal=[0, 1], d=-1.8) | sdf.Halfspace(normal=[1, 1], d=-1.8)
    with sdf.smoothness(10), sdf.transform(angle=-0.3, offset=[0.5, 0]):
        f |= sdf.Circle(center=[0, 0], radius=0.5) & sdf.Box(minc=[-1, -0.2], maxc=[1, 0.2])
    d, grad = f(x, y, compute_gradient=True)

Every shape is an :class:`SDF`: a :class:`fastsdf.graph.Function` of the symbols ``x`` and
``y``, callable on points, negative inside and positive outside, in the units of the
coordinates. ``a | b`` is the union, ``a & b`` the intersection, ``a - b`` the difference. Under
``smoothness(k)`` with ``k > 0``, union and intersection become the notebook's exponential
blends (``-log(exp(-k a) + exp(-k b)) / k`` and its mirror), evaluated in a form that cannot
overflow; the difference is always hard, as in the notebook. ``transform(angle, offset)`` places
newly created primitives rotated by ``angle`` (radians, counter-clockwise) and then moved by
``offset``. Both context managers nest: transforms compose (the outer one applied last).

Beyond the notebook: more primitives with exact distances (:class:`Segment`, :class:`Capsule`,
:class:`RoundedBox`, :class:`OrientedBox`, :class:`Triangle`, :class:`EquilateralTriangle`,
:class:`RegularPolygon`, :class:`Polygon`, :class:`Star`, :class:`Ellipse`, :class:`Arc`,
:class:`Ring`), modifiers (``f.round(r)``, ``f.shell(t)``, ``f.scale(s)``, ``f.translate(o)``,
``f.rotate(a)``, ``f.mirror(axis)``, ``f.repeat(spacing, count)``), polynomial blends
(``a.union(b, k=0.1, kind='quadratic')``, ``smoothness(0.1, kind='cubic')``) and
``f.exactness`` (``'exact'``, ``'bound'`` or ``'none'``), tracked through all of them.
"""

from __future__ import annotations

import math
import numbers
from contextlib import contextmanager
from dataclasses import dataclass, replace

import numpy as np

from ._validate import real as _real
from .interval import note_lipschitz
from ._validate import vec2 as _vec2
from .graph import (Expr, Function, Symbol, substitute, sym_abs, sym_cmin, sym_floor, sym_length,
                    sym_max, sym_min, sym_prim, sym_qmin, sym_select, sym_smax, sym_smin)

__all__ = ["SDF", "Circle", "Halfspace", "Box", "Union", "Intersection", "Difference",
           "smoothness", "transform", "current_smoothness", "current_blend", "BLEND_KINDS",
           "EXACTNESS",
           "Segment", "Capsule", "RoundedBox", "OrientedBox", "EquilateralTriangle", "Triangle",
           "RegularPolygon", "Polygon", "Star", "Ellipse", "Arc", "Ring",
           "offset", "shell", "scale", "translate", "rotate", "mirror", "repeat"]

_X, _Y = Symbol("x"), Symbol("y")

#: The blends of ``|``, ``&`` and the set-operation methods: ``k`` is the sharpness
#: (1/distance) for ``'exponential'`` and the blend width (distance) for the polynomial ones.
BLEND_KINDS = ("exponential", "quadratic", "cubic")
#: Values of :attr:`SDF.exactness`.
EXACTNESS = ("exact", "bound", "none")

# The frame of new primitives: local -> world is ``world = M local + t`` with
# ``frame = (m00, m01, m10, m11, tx, ty)``; used only for the exactness bookkeeping (bounding
# boxes and symmetries), the coordinates themselves live in "x" and "y".
_IDENTITY = (1.0, 0.0, 0.0, 1.0, 0.0, 0.0)

# The modelling state: the coordinate expressions new primitives are built in, and the
# smoothness (and blend kind) of | and &. Context managers replace it and restore it on exit.
_state = {"x": _X, "y": _Y, "smoothness": 0.0, "blend": "exponential", "frame": _IDENTITY}


# ---------------------------------------------------------------------------------------------
# Parameter validation: errors name the parameter and the value.

def _smoothness_value(k) -> float:
    if k is None:
        return 0.0
    if isinstance(k, (bool, np.bool_)) or not isinstance(k, numbers.Real):
        raise TypeError(f"smoothness k must be a real number, got k={k!r}")
    k = float(k)
    if not math.isfinite(k) or k < 0:
        raise ValueError(f"smoothness k must be finite and >= 0 (0 means a hard min/max), got k={k!r}")
    return k


# ---------------------------------------------------------------------------------------------
# The modelling context.

@contextmanager
def _properties(**props):
    global _state
    previous = _state
    _state = {**_state, **props}
    try:
        yield
    finally:
        _state = previous


def smoothness(k, kind="exponential"):
    """Context manager: ``|`` and ``&`` created inside blend with parameter ``k``.

    ``kind='exponential'`` (the default, the notebook's blend): ``k`` is the sharpness in
    1/distance; ``k = 0`` (or None) gives the hard ``min``/``max``; larger ``k`` gives a sharper
    blend that rounds the result by at most ``log(2) / k``. ``kind='quadratic'`` or ``'cubic'``:
    the local polynomial blends, ``k`` is the blend width in distance units (exactly
    ``min``/``max`` where the operands differ by ``k`` or more; ``k = 0`` is hard). ``k`` must be
    finite and ``>= 0``. The difference ``-`` stays hard, as in the notebook; use
    :meth:`SDF.difference` for a smooth one.
    """
    return _properties(smoothness=_smoothness_value(k), blend=_blend_kind(kind))


def current_smoothness() -> float:
    """The smoothness that ``|`` and ``&`` use right now."""
    return _state["smoothness"]


def current_blend() -> tuple:
    """``(k, kind)``: the blend that ``|`` and ``&`` use right now."""
    return _state["smoothness"], _state["blend"]


def transform(angle=0.0, offset=(0.0, 0.0)):
    """Context manager: primitives created inside are rotated by ``angle`` (radians,
    counter-clockwise) about their own origin, then translated by ``offset``.

    Nested transforms compose, the outer one applied last. Rotations and translations keep
    distances exact.
    """
    angle = _real(angle, "angle")
    offset = _vec2(offset, "offset")
    c, s = math.cos(angle), math.sin(angle)
    x, y = _state["x"], _state["y"]
    # Primitives are built in local coordinates: the inverse transform of the current ones.
    local_x = x * c + y * s - (offset[0] * c + offset[1] * s)
    local_y = -x * s + y * c - (-offset[0] * s + offset[1] * c)
    m00, m01, m10, m11, tx, ty = _state["frame"]  # compose: outer frame o (R, offset)
    frame = (m00 * c + m01 * s, -m00 * s + m01 * c, m10 * c + m11 * s, -m10 * s + m11 * c,
             m00 * offset[0] + m01 * offset[1] + tx, m10 * offset[0] + m11 * offset[1] + ty)
    return _properties(x=local_x, y=local_y, frame=frame)


# ---------------------------------------------------------------------------------------------
# Exactness bookkeeping.
#
# Every SDF carries an _Info: whether its value is the exact distance outside (f > 0) and
# inside (f < 0), whether it is a bound (1-Lipschitz: |f| <= distance to the boundary of
# {f < 0}, with the correct sign), and what is known about its shape that later operations use
# to keep exactness: convexity, a bounding box, mirror symmetries about the coordinate axes.
# Unknown means False / None / empty: the flags are conservative.

@dataclass(frozen=True)
class _Info:
    outside: bool = False       # exact where f > 0
    inside: bool = False        # exact where f < 0
    bound: bool = False         # 1-Lipschitz (implies |f| <= true distance, sign correct)
    convex: bool = False        # the shape {f <= 0} is convex
    bbox: tuple | None = None   # (xmin, ymin, xmax, ymax) containing the shape
    sym: frozenset = frozenset()  # 'x': f(-x, y) = f(x, y); 'y': f(x, -y) = f(x, y)


_NONE = _Info()


def _frame_bbox(bbox, frame=None):
    """World bounding box of a local bounding box under the current (or given) frame."""
    if bbox is None:
        return None
    m00, m01, m10, m11, tx, ty = _state["frame"] if frame is None else frame
    xs, ys = (bbox[0], bbox[2]), (bbox[1], bbox[3])
    cx = [m00 * u + m01 * v + tx for u in xs for v in ys]
    cy = [m10 * u + m11 * v + ty for u in xs for v in ys]
    return (min(cx), min(cy), max(cx), max(cy))


def _grow(bbox, r):
    if bbox is None:
        return None
    return (bbox[0] - r, bbox[1] - r, bbox[2] + r, bbox[3] + r)


def _primitive_info(bbox, sym=(), convex=False, exact=True) -> _Info:
    """Info of a primitive built now, from its local bounding box and symmetries."""
    world_sym = frozenset(sym) if _state["frame"] == _IDENTITY else frozenset()
    return _Info(outside=exact, inside=exact, bound=True, convex=convex,
                 bbox=_frame_bbox(bbox), sym=world_sym)


def _points_bbox(points, r=0.0):
    p = np.asarray(points, dtype=np.float64)
    return (float(p[:, 0].min() - r), float(p[:, 1].min() - r),
            float(p[:, 0].max() + r), float(p[:, 1].max() + r))


def _edges_symmetry(points, closed=True) -> frozenset:
    """Axes about which the polyline through ``points`` is mirror-symmetric (to 1e-12)."""
    p = np.asarray(points, dtype=np.float64)
    tol = 1e-12 * max(1.0, float(np.abs(p).max()))
    q = np.roll(p, -1, axis=0) if closed else p[1:]
    p = p if closed else p[:-1]
    edges = np.concatenate([p, q], axis=1)
    edges = np.concatenate([edges, edges[:, [2, 3, 0, 1]]])  # both directions

    def same(a, b):  # equal as sets of edges, to the tolerance (conservative at its edge)
        a, b = np.round(a / tol), np.round(b / tol)
        return np.array_equal(a[np.lexsort(a.T[::-1])], b[np.lexsort(b.T[::-1])])

    out = set()
    if same(edges, edges * [-1, 1, -1, 1]):
        out.add("x")
    if same(edges, edges * [1, -1, 1, -1]):
        out.add("y")
    return frozenset(out)


def _center_sym(center) -> set:
    return {axis for axis, c in zip("xy", center) if c == 0.0}


# ---------------------------------------------------------------------------------------------
# Blends: the hard operations, the notebook's exponential blends, the polynomial ones.

def _blend_kind(kind) -> str:
    if kind == "exp":
        kind = "exponential"
    if not isinstance(kind, str) or kind not in BLEND_KINDS:
        raise ValueError(f"kind must be one of {BLEND_KINDS}, got kind={kind!r}")
    return kind


def _blend_min(a: Expr, b: Expr, k: float, kind: str) -> Expr:
    if k == 0.0:
        return sym_min(a, b)
    if kind == "exponential":
        return sym_smin(a, b, k)
    return (sym_qmin if kind == "quadratic" else sym_cmin)(a, b, k)


def _blend_max(a: Expr, b: Expr, k: float, kind: str) -> Expr:
    if k == 0.0:
        return sym_max(a, b)
    if kind == "exponential":
        return sym_smax(a, b, k)
    return -(sym_qmin if kind == "quadratic" else sym_cmin)(-a, -b, k)


def _blend_depth(k: float, kind: str) -> float:
    """How far a smooth union can reach beyond the hard one (bounding boxes grow by this)."""
    if k == 0.0:
        return 0.0
    return {"exponential": math.log(2.0) / k, "quadratic": k / 4.0, "cubic": k / 6.0}[kind]


def _bbox_union(a, b, grow=0.0):
    if a is None or b is None:
        return None
    return _grow((min(a[0], b[0]), min(a[1], b[1]), max(a[2], b[2]), max(a[3], b[3])), grow)


def _bbox_meet(a, b):
    if a is None:
        return b
    if b is None:
        return a
    return (max(a[0], b[0]), max(a[1], b[1]), min(a[2], b[2]), min(a[3], b[3]))


def _check_sdf(value, name):
    if not isinstance(value, SDF):
        raise TypeError(f"{name} must be a fastsdf SDF, got {name}={value!r} of type "
                        f"{type(value).__name__}")
    return value


# ---------------------------------------------------------------------------------------------
# Shapes.

class SDF(Function):
    """A signed distance function of the plane: negative inside, positive outside.

    Callable as ``f(x, y, compute_gradient=False)`` (see :class:`fastsdf.graph.Function`);
    ``f.f`` is its expression. Combine with ``|`` (union), ``&`` (intersection), ``-``
    (difference); ``|=`` and friends work too. The operators blend as the :func:`smoothness`
    context says; the methods :meth:`union`, :meth:`intersection`, :meth:`difference` take the
    blend explicitly. :attr:`exactness` says how far the value can be trusted as a distance.
    """

    def __init__(self, expr: Expr, info: _Info | None = None):
        super().__init__(expr, [_X, _Y])
        self._info = _NONE if info is None else info
        if self._info.bound:  # interval bounds may use |f(p) - f(c)| <= |p - c|
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
        flags follow the rules in the README ("Primitives, modifiers, blends") and are
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
    def _other(self, other, op: str):
        if not isinstance(other, SDF):
            raise TypeError(f"cannot {op} an SDF with {other!r} of type {type(other).__name__}; "
                            "both operands must be fastsdf SDF objects")
        return other

    def __or__(self, other):
        k, kind = current_blend()
        return Union(self, self._other(other, "unite"), k=k, kind=kind)

    def __and__(self, other):
        k, kind = current_blend()
        return Intersection(self, self._other(other, "intersect"), k=k, kind=kind)

    def __sub__(self, other):
        return Difference(self, self._other(other, "subtract"))

    def union(self, other, k=0.0, kind="exponential"):
        """``self | other`` with an explicit blend (the :func:`smoothness` context is ignored):
        ``k = 0`` hard; ``kind='exponential'`` (``k`` = sharpness, 1/distance), ``'quadratic'``
        or ``'cubic'`` (``k`` = blend width, distance). See :class:`Union`."""
        return Union(self, self._other(other, "unite"), k=k, kind=kind)

    def intersection(self, other, k=0.0, kind="exponential"):
        """``self & other`` with an explicit blend (see :meth:`union`, :class:`Intersection`)."""
        return Intersection(self, self._other(other, "intersect"), k=k, kind=kind)

    def difference(self, other, k=0.0, kind="exponential"):
        """``self - other``, smooth for ``k > 0`` (see :meth:`union`, :class:`Difference`)."""
        return Difference(self, self._other(other, "subtract"), k=k, kind=kind)

    # -- modifiers -----------------------------------------------------------------------------
    def round(self, r):
        """Offset: ``f - r`` (``r > 0`` grows the shape and rounds its convex corners by
        ``r``; ``r < 0`` erodes it).

        Exactness, for ``r > 0``: exact outside if ``f`` is; exact inside too if ``f`` is exact
        and its shape is convex (a rounded box, a capsule from a segment). For a non-convex
        shape the inside value is only a bound (filled concavities are deeper than ``r - f``).
        For ``r < 0``: exact inside if ``f`` is, a bound outside. Always a bound if ``f`` is.
        """
        r = _real(r, "r")
        i = self._info
        if r == 0:
            return SDF(self.f, i)
        if r > 0:
            info = replace(i, inside=i.inside and i.outside and i.convex, bbox=_grow(i.bbox, r))
        else:
            info = replace(i, outside=False)
        return SDF(self.f - r, info)

    def shell(self, thickness):
        """Annulus of the boundary: ``|f| - thickness / 2``, a band of total width
        ``thickness`` centred on the surface (IQ's onion).

        Exact outside the band if ``f`` is exact (inside and outside); inside the band a
        bound (exact inside the band only where the surface is a circle, see :class:`Ring`:
        near a corner the band's inner edge is farther than the formula says).
        """
        t = _real(thickness, "thickness")
        if t <= 0:
            raise ValueError(f"thickness must be > 0, got thickness={t!r}")
        i = self._info
        info = _Info(outside=i.outside and i.inside, inside=False, bound=i.bound,
                     bbox=_grow(i.bbox, t / 2), sym=i.sym)
        return SDF(sym_abs(self.f) - t / 2, info)

    def scale(self, s):
        """Uniform scale about the origin: ``s * f(p / s)`` with ``s > 0``; keeps the value a
        distance, so exactness is kept."""
        s = _real(s, "s")
        if s <= 0:
            raise ValueError(f"s must be > 0, got s={s!r}")
        inv = 1.0 / s
        i = self._info
        bbox = None if i.bbox is None else tuple(v * s for v in i.bbox)
        return SDF(substitute(self.f, {"x": _X * inv, "y": _Y * inv}) * s, replace(i, bbox=bbox))

    def translate(self, offset):
        """The shape moved by ``offset``: ``f(p - offset)``, in the coordinates of ``f`` (an
        active :func:`transform` context plays no part). Same as building it under
        ``transform(offset=offset)``; keeps exactness."""
        o = _vec2(offset, "offset")
        i = self._info
        bbox = None if i.bbox is None else (i.bbox[0] + o[0], i.bbox[1] + o[1],
                                             i.bbox[2] + o[0], i.bbox[3] + o[1])
        sym = frozenset(a for a, ov in zip("xy", o) if a in i.sym and ov == 0.0)
        expr = substitute(self.f, {"x": _X - float(o[0]), "y": _Y - float(o[1])})
        return SDF(expr, replace(i, bbox=bbox, sym=sym))

    def rotate(self, angle):
        """The shape rotated counter-clockwise by ``angle`` (radians) about the origin:
        ``f(R(-angle) p)``. Same as building it under ``transform(angle=angle)``; keeps
        exactness."""
        angle = _real(angle, "angle")
        c, s = math.cos(angle), math.sin(angle)
        i = self._info
        bbox = _frame_bbox(i.bbox, (c, -s, s, c, 0.0, 0.0))
        sym = i.sym if angle == 0.0 else frozenset()
        expr = substitute(self.f, {"x": _X * c + _Y * s, "y": _Y * c - _X * s})
        return SDF(expr, replace(i, bbox=bbox, sym=sym))

    def mirror(self, axis="x"):
        """Mirror symmetry: ``axis='x'`` evaluates ``f(|x|, y)``, the part of the shape with
        ``x >= 0`` plus its mirror image in the line ``x = 0``; ``'y'`` likewise
        ``f(x, |y|)``; ``'xy'`` both.

        A bound if ``f`` is one. Exact if ``f`` is exact and either already symmetric about
        that axis or known (from its bounding box) to lie strictly on the positive side;
        otherwise the part of the shape on the negative side, now cut away, can make the
        value smaller than the distance.
        """
        if axis not in ("x", "y", "xy"):
            raise ValueError(f"axis must be 'x', 'y' or 'xy', got axis={axis!r}")
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
            info = _Info(outside=i.outside and disjoint, inside=i.inside and disjoint,
                         bound=i.bound, bbox=bbox, sym=i.sym | {ax})
            f = SDF(substitute(f.f, sub), info)
        return f

    def repeat(self, spacing, count):
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
        sp = _pair(spacing, "spacing", _real)
        ct = _pair(count, "count", _count)
        if not all(v > 0 for v in sp):
            raise ValueError(f"spacing must be > 0, got spacing={spacing!r}")
        i = self._info
        sub, symmetric, contained = {}, True, i.bbox is not None
        lo = list(i.bbox[:2]) if i.bbox is not None else None
        hi = list(i.bbox[2:]) if i.bbox is not None else None
        for j, (ax, s, n) in enumerate(zip("xy", sp, ct)):
            if n == 1:
                continue
            coord = _X if ax == "x" else _Y
            cell = sym_min(sym_max(sym_floor(coord * (1.0 / s) + 0.5), 0.0), float(n - 1))
            sub[ax] = coord - cell * s
            symmetric = symmetric and ax in i.sym
            if i.bbox is not None:
                contained = contained and max(-i.bbox[j], i.bbox[2 + j]) < s / 2
                hi[j] += (n - 1) * s
        if not sub:
            return self
        info = _Info(outside=symmetric and i.outside,
                     inside=symmetric and contained and i.inside,
                     bound=symmetric and i.bound,
                     bbox=None if lo is None else (lo[0], lo[1], hi[0], hi[1]))
        return SDF(substitute(self.f, sub), info)

    def __repr__(self):
        return f"{type(self).__name__}({str(self.f)[:200]})"


def _pair(value, name, check):
    if isinstance(value, (tuple, list, np.ndarray)):
        if len(value) != 2:
            raise ValueError(f"{name} must be a number or a pair, got {name}={value!r}")
        return tuple(check(v, name) for v in value)
    v = check(value, name)
    return (v, v)


def _count(value, name) -> int:
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, numbers.Integral):
        raise TypeError(f"{name} must be an integer, got {name}={value!r}")
    if value < 1:
        raise ValueError(f"{name} must be >= 1, got {name}={value!r}")
    return int(value)


# Modifiers as functions (the methods of SDF).

def offset(f, r):
    """``f.round(r)``: the shape offset by ``r`` (see :meth:`SDF.round`)."""
    return _check_sdf(f, "f").round(r)


def shell(f, thickness):
    """``f.shell(thickness)`` (see :meth:`SDF.shell`)."""
    return _check_sdf(f, "f").shell(thickness)


def scale(f, s):
    """``f.scale(s)`` (see :meth:`SDF.scale`)."""
    return _check_sdf(f, "f").scale(s)


def translate(f, offset):  # noqa: F811 - the parameter shadows offset() here only
    """``f.translate(offset)`` (see :meth:`SDF.translate`)."""
    return _check_sdf(f, "f").translate(offset)


def rotate(f, angle):
    """``f.rotate(angle)`` (see :meth:`SDF.rotate`)."""
    return _check_sdf(f, "f").rotate(angle)


def mirror(f, axis="x"):
    """``f.mirror(axis)`` (see :meth:`SDF.mirror`)."""
    return _check_sdf(f, "f").mirror(axis)


def repeat(f, spacing, count):
    """``f.repeat(spacing, count)`` (see :meth:`SDF.repeat`)."""
    return _check_sdf(f, "f").repeat(spacing, count)


# ---------------------------------------------------------------------------------------------
# The notebook's primitives.

class Circle(SDF):
    """Disc of ``radius`` around ``center`` (exact distance).

    At the centre, where every direction is steepest, the gradient is the local +x axis.
    """

    def __init__(self, center=(0.0, 0.0), radius=1.0):
        center = _vec2(center, "center")
        radius = _real(radius, "radius")
        if radius <= 0:
            raise ValueError(f"radius must be > 0, got radius={radius!r}")
        self.center, self.radius = center, radius
        x, y = _state["x"], _state["y"]
        info = _primitive_info(_points_bbox([center], radius), _center_sym(center), convex=True)
        super().__init__(sym_length(x - center[0], y - center[1]) - radius, info)


class Halfspace(SDF):
    """Half-plane ``{p : n . p <= d}`` with outward normal ``normal`` (normalized here) and
    signed offset ``d`` from the origin (Hessian normal form; exact distance)."""

    def __init__(self, normal=(1.0, 0.0), d=0.0):
        normal = _vec2(normal, "normal")
        d = _real(d, "d")
        length = float(np.hypot(normal[0], normal[1]))
        if not length > 0:
            raise ValueError(f"normal must have non-zero length, got normal={normal.tolist()!r}")
        n = normal / length
        self.normal, self.d = n, d
        x, y = _state["x"], _state["y"]
        super().__init__(x * n[0] + y * n[1] - d, _primitive_info(None, convex=True))


class Box(SDF):
    """Axis-aligned rectangle from corner ``minc`` to corner ``maxc`` (in local coordinates).

    The distance is exact everywhere. (The notebook's box, an intersection of four half-spaces,
    agrees inside and along the faces but outside the corners gives only a lower bound, the
    L-infinity distance, with an axis-aligned gradient.)
    """

    def __init__(self, minc=(-1.0, -1.0), maxc=(1.0, 1.0)):
        minc, maxc = _vec2(minc, "minc"), _vec2(maxc, "maxc")
        if not np.all(minc < maxc):
            raise ValueError(f"minc must be below maxc in both coordinates, got "
                             f"minc={minc.tolist()!r}, maxc={maxc.tolist()!r}")
        self.minc, self.maxc = minc, maxc
        center, half = (minc + maxc) / 2, (maxc - minc) / 2
        x, y = _state["x"], _state["y"]
        qx = sym_abs(x - center[0]) - half[0]
        qy = sym_abs(y - center[1]) - half[1]
        outside = sym_length(sym_max(qx, 0.0), sym_max(qy, 0.0))
        # min(0, .) puts the constant first so that on the boundary (a tie) the constant's zero
        # gradient is taken and the gradient stays of unit length.
        inside = sym_min(0.0, sym_max(qx, qy))
        sym = {ax for ax, lo, hi in zip("xy", minc, maxc) if lo == -hi}
        info = _primitive_info(_points_bbox([minc, maxc]), sym, convex=True)
        super().__init__(outside + inside, info)


# ---------------------------------------------------------------------------------------------
# Set operations.

def _k_and_kind(k, kind):
    return _smoothness_value(k), _blend_kind(kind)


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
    """

    def __init__(self, a: SDF, b: SDF, k=0.0, kind="exponential"):
        a, b = _check_sdf(a, "a"), _check_sdf(b, "b")
        k, kind = _k_and_kind(k, kind)
        ia, ib = a._info, b._info
        info = _Info(outside=k == 0 and ia.outside and ib.outside, bound=ia.bound and ib.bound,
                     bbox=_bbox_union(ia.bbox, ib.bbox, _blend_depth(k, kind)),
                     sym=ia.sym & ib.sym)
        super().__init__(_blend_min(a.f, b.f, k, kind), info)


class Intersection(SDF):
    """Intersection of two SDFs: ``max(a, b)``, or a smooth maximum for ``k > 0`` (the blends
    of :class:`Union`, mirrored: ``smax(a, b) = -smin(-a, -b)``).

    Exactness: the hard intersection of exact SDFs is exact inside and a bound outside (near a
    corner the distance to the intersection is larger than either operand). Blends: a bound.
    """

    def __init__(self, a: SDF, b: SDF, k=0.0, kind="exponential"):
        a, b = _check_sdf(a, "a"), _check_sdf(b, "b")
        k, kind = _k_and_kind(k, kind)
        ia, ib = a._info, b._info
        info = _Info(inside=k == 0 and ia.inside and ib.inside, bound=ia.bound and ib.bound,
                     convex=k == 0 and ia.convex and ib.convex, bbox=_bbox_meet(ia.bbox, ib.bbox),
                     sym=ia.sym & ib.sym)
        super().__init__(_blend_max(a.f, b.f, k, kind), info)


class Difference(SDF):
    """``a`` with ``b`` cut away: ``max(a, -b)``. Hard by default, as in the notebook (and ``-``
    is always hard); ``k > 0`` blends like :class:`Intersection` with ``-b``.

    Exactness: exact inside where ``a`` is exact inside and ``b`` exact outside; a bound
    outside. Blends: a bound.
    """

    def __init__(self, a: SDF, b: SDF, k=0.0, kind="exponential"):
        a, b = _check_sdf(a, "a"), _check_sdf(b, "b")
        k, kind = _k_and_kind(k, kind)
        ia, ib = a._info, b._info
        info = _Info(inside=k == 0 and ia.inside and ib.outside, bound=ia.bound and ib.bound,
                     bbox=ia.bbox, sym=ia.sym & ib.sym)
        super().__init__(_blend_max(a.f, -b.f, k, kind), info)


# ---------------------------------------------------------------------------------------------
# Issue 7 primitives. All are built in the local coordinates of the transform context and
# are exact signed distances unless their docstring says otherwise.

def _segment_expr(x: Expr, y: Expr, a, b) -> Expr:
    """Unsigned distance from (x, y) to the segment a-b (a point if a == b)."""
    px, py = x - float(a[0]), y - float(a[1])
    ex, ey = float(b[0] - a[0]), float(b[1] - a[1])
    ee = ex * ex + ey * ey
    if ee == 0.0:
        return sym_length(px, py)
    t = (px * ex + py * ey) * (1.0 / ee)
    h = sym_min(sym_max(t, 0.0), 1.0)
    return sym_length(px - h * ex, py - h * ey)


def _ccw(vertices: np.ndarray) -> np.ndarray:
    """The vertices in counter-clockwise order (by the sign of the shoelace area)."""
    v = vertices
    area2 = float(np.sum(v[:, 0] * np.roll(v[:, 1], -1) - np.roll(v[:, 0], -1) * v[:, 1]))
    return v if area2 > 0 else v[::-1].copy()


def _convex_polygon_expr(x: Expr, y: Expr, vertices: np.ndarray) -> Expr:
    """Exact SDF of a convex polygon (counter-clockwise vertices) from graph operations:
    outside the distance to the nearest edge, inside the largest signed edge-line distance
    (which for a convex polygon is minus the distance to the nearest edge)."""
    n = len(vertices)
    dist = line = None
    for i in range(n):
        a, b = vertices[i], vertices[(i + 1) % n]
        e = b - a
        nx, ny = e[1] / math.hypot(*e), -e[0] / math.hypot(*e)  # outward normal
        seg = _segment_expr(x, y, a, b)
        h = x * nx + y * ny - float(nx * a[0] + ny * a[1])
        dist = seg if dist is None else sym_min(dist, seg)
        line = h if line is None else sym_max(line, h)
    return sym_select(line, dist, line)


def _vertices(value, name, minimum=3) -> np.ndarray:
    try:
        arr = np.asarray(value)
    except Exception:  # noqa: BLE001
        raise TypeError(f"{name} must be a sequence of (x, y) pairs, got {name}={value!r}") \
            from None
    if arr.dtype.kind not in "iuf":
        raise TypeError(f"{name} must be a sequence of (x, y) pairs of real numbers, got "
                        f"{name}={value!r}")
    if arr.ndim != 2 or arr.shape[1] != 2:
        raise ValueError(f"{name} must have shape (n, 2), got shape {arr.shape} for "
                         f"{name}={value!r}")
    arr = arr.astype(np.float64)
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} must be finite, got {name}={value!r}")
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
        raise ValueError(f"{name} must enclose a non-zero area (got collinear or coincident "
                         f"vertices: {v.tolist()!r})")

    def orient(p, q, r):
        return (q[..., 0] - p[..., 0]) * (r[..., 1] - p[..., 1]) - \
            (q[..., 1] - p[..., 1]) * (r[..., 0] - p[..., 0])

    tol = 1e-12 * scale * scale
    for i in range(n):
        # adjacent edge i -> i+1: folds back if collinear and pointing backwards
        e1, e2 = b[i] - a[i], b[(i + 1) % n] - a[(i + 1) % n]
        if abs(e1[0] * e2[1] - e1[1] * e2[0]) <= tol and e1 @ e2 < 0:
            raise ValueError(f"{name} is not simple: edges {i} and {(i + 1) % n} overlap "
                             f"(the polygon folds back at vertex {(i + 1) % n})")
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

        touch = on_seg(p1, p2, q1, o1) | on_seg(p1, p2, q2, o2) | \
            on_seg(q1, q2, np.broadcast_to(p1, q1.shape), o3) | \
            on_seg(q1, q2, np.broadcast_to(p2, q1.shape), o4)
        bad = proper | touch
        if np.any(bad):
            k = int(j[np.argmax(bad)])
            raise ValueError(f"{name} is not simple: edge {i} ({a[i].tolist()} -> "
                             f"{b[i].tolist()}) meets edge {k} ({a[k].tolist()} -> "
                             f"{b[k].tolist()})")
    area2 = float(np.sum(a[:, 0] * b[:, 1] - b[:, 0] * a[:, 1]))
    if abs(area2) <= 1e-12 * scale * scale:
        raise ValueError(f"{name} must enclose a non-zero area (got collinear or coincident "
                         f"vertices: {v.tolist()!r})")


class Segment(SDF):
    """The line segment from ``a`` to ``b`` (``a == b`` gives a point).

    A shape of zero thickness: the value is the exact *unsigned* distance, ``>= 0``
    everywhere and 0 only on the segment (there is no inside). On the segment itself the
    gradient is the local +x axis (a one-sided choice, as at a circle's centre).
    ``Segment(a, b).round(r)`` is the same shape as ``Capsule(a, b, r)``.
    """

    def __init__(self, a=(0.0, 0.0), b=(1.0, 0.0)):
        a, b = _vec2(a, "a"), _vec2(b, "b")
        self.a, self.b = a, b
        info = _primitive_info(_points_bbox([a, b]), _edges_symmetry([a, b], closed=False),
                               convex=True)
        super().__init__(_segment_expr(_state["x"], _state["y"], a, b), info)


class Capsule(SDF):
    """The segment ``a``-``b`` thickened by ``radius`` (a stadium; a disc if ``a == b``)."""

    def __init__(self, a=(0.0, 0.0), b=(1.0, 0.0), radius=0.25):
        a, b = _vec2(a, "a"), _vec2(b, "b")
        radius = _real(radius, "radius")
        if radius <= 0:
            raise ValueError(f"radius must be > 0, got radius={radius!r}")
        self.a, self.b, self.radius = a, b, radius
        info = _primitive_info(_points_bbox([a, b], radius),
                               _edges_symmetry([a, b], closed=False), convex=True)
        super().__init__(_segment_expr(_state["x"], _state["y"], a, b) - radius, info)


class RoundedBox(SDF):
    """Axis-aligned rectangle ``minc``-``maxc`` with rounded corners.

    ``radii``: one radius, or four in the order of the quadrants (counter-clockwise from the
    upper right): ``(upper-right, upper-left, lower-left, lower-right)``; each in
    ``[0, min(width, height) / 2]`` (0 keeps the corner sharp).
    """

    def __init__(self, minc=(-1.0, -1.0), maxc=(1.0, 1.0), radii=0.25):
        minc, maxc = _vec2(minc, "minc"), _vec2(maxc, "maxc")
        if not np.all(minc < maxc):
            raise ValueError(f"minc must be below maxc in both coordinates, got "
                             f"minc={minc.tolist()!r}, maxc={maxc.tolist()!r}")
        if isinstance(radii, (tuple, list, np.ndarray)):
            if len(radii) != 4:
                raise ValueError(f"radii must be one number or four (upper-right, upper-left, "
                                 f"lower-left, lower-right), got radii={radii!r}")
            r = [_real(v, "radii") for v in radii]
        else:
            r = [_real(radii, "radii")] * 4
        center, half = (minc + maxc) / 2, (maxc - minc) / 2
        limit = float(min(half))
        if not all(0.0 <= v <= limit for v in r):
            raise ValueError(f"radii must be in [0, {limit!r}] (half the smaller side), got "
                             f"radii={radii!r}")
        self.minc, self.maxc, self.radii = minc, maxc, tuple(r)
        x, y = _state["x"], _state["y"]
        px, py = x - float(center[0]), y - float(center[1])
        if len(set(r)) == 1:
            rad = r[0]
        else:  # the radius of the quadrant the point is in
            rad = sym_select(px, sym_select(py, r[0], r[3]), sym_select(py, r[1], r[2]))
        qx = sym_abs(px) - float(half[0]) + rad
        qy = sym_abs(py) - float(half[1]) + rad
        expr = sym_length(sym_max(qx, 0.0), sym_max(qy, 0.0)) + sym_min(0.0, sym_max(qx, qy)) - rad
        sym = set()
        if center[0] == 0 and r[0] == r[1] and r[2] == r[3]:
            sym.add("x")
        if center[1] == 0 and r[0] == r[3] and r[1] == r[2]:
            sym.add("y")
        info = _primitive_info(_points_bbox([minc, maxc]), sym, convex=True)
        super().__init__(expr, info)


class OrientedBox(SDF):
    """Rectangle along the segment ``a``-``b``: length ``|b - a|``, total width ``thickness``
    (IQ's oriented box; the ends are flat, at ``a`` and ``b``)."""

    def __init__(self, a=(-1.0, 0.0), b=(1.0, 0.0), thickness=0.5):
        a, b = _vec2(a, "a"), _vec2(b, "b")
        thickness = _real(thickness, "thickness")
        if thickness <= 0:
            raise ValueError(f"thickness must be > 0, got thickness={thickness!r}")
        length = float(np.hypot(*(b - a)))
        if not length > 0:
            raise ValueError(f"a and b must differ, got a={a.tolist()!r}, b={b.tolist()!r}")
        self.a, self.b, self.thickness = a, b, thickness
        d = (b - a) / length
        m = (a + b) / 2
        x, y = _state["x"], _state["y"]
        px, py = x - float(m[0]), y - float(m[1])
        u = px * float(d[0]) + py * float(d[1])
        v = py * float(d[0]) - px * float(d[1])
        qx = sym_abs(u) - length / 2
        qy = sym_abs(v) - thickness / 2
        expr = sym_length(sym_max(qx, 0.0), sym_max(qy, 0.0)) + sym_min(0.0, sym_max(qx, qy))
        n = np.array([-d[1], d[0]]) * thickness / 2
        corners = [a - n, b - n, b + n, a + n]
        info = _primitive_info(_points_bbox(corners), _edges_symmetry(corners), convex=True)
        super().__init__(expr, info)


class Triangle(SDF):
    """The triangle with corners ``p0, p1, p2`` (either orientation; not collinear)."""

    def __init__(self, p0=(-1.0, -0.5), p1=(1.0, -0.5), p2=(0.0, 1.0)):
        v = np.array([_vec2(p0, "p0"), _vec2(p1, "p1"), _vec2(p2, "p2")])
        e1, e2 = v[1] - v[0], v[2] - v[0]
        area2 = e1[0] * e2[1] - e1[1] * e2[0]
        scale = float(max(np.hypot(*e1), np.hypot(*e2), np.hypot(*(v[2] - v[1]))))
        if not abs(area2) > 1e-12 * scale * scale:
            raise ValueError(f"p0, p1, p2 must not be collinear, got p0={v[0].tolist()!r}, "
                             f"p1={v[1].tolist()!r}, p2={v[2].tolist()!r}")
        self.vertices = _ccw(v)
        info = _primitive_info(_points_bbox(v), _edges_symmetry(v), convex=True)
        super().__init__(_convex_polygon_expr(_state["x"], _state["y"], self.vertices), info)


def _regular_vertices(center, radius, n, phase=math.pi / 2):
    t = phase + 2 * math.pi * np.arange(n) / n
    return np.stack([center[0] + radius * np.cos(t), center[1] + radius * np.sin(t)], -1)


def _check_n(n, name="n", minimum=3) -> int:
    if isinstance(n, (bool, np.bool_)) or not isinstance(n, numbers.Integral):
        raise TypeError(f"{name} must be an integer, got {name}={n!r}")
    if n < minimum:
        raise ValueError(f"{name} must be >= {minimum}, got {name}={n!r}")
    return int(n)


def _positive(value, name) -> float:
    value = _real(value, name)
    if value <= 0:
        raise ValueError(f"{name} must be > 0, got {name}={value!r}")
    return value


class RegularPolygon(SDF):
    """Regular ``n``-gon inscribed in the circle of ``radius`` (circumradius) around
    ``center``, one vertex pointing up (+y). Built from graph operations: ``n`` segments (one
    loop over a table in the generated code for ``n >= 4``)."""

    def __init__(self, center=(0.0, 0.0), radius=1.0, n=6):
        center = _vec2(center, "center")
        radius = _positive(radius, "radius")
        n = _check_n(n)
        self.center, self.radius, self.n = center, radius, n
        v = _regular_vertices(center, radius, n)
        self.vertices = v
        sym = {"x"} if center[0] == 0 else set()
        if center[1] == 0 and n % 2 == 0:
            sym.add("y")
        info = _primitive_info(_points_bbox(v), sym, convex=True)
        super().__init__(_convex_polygon_expr(_state["x"], _state["y"], v), info)


class EquilateralTriangle(RegularPolygon):
    """Equilateral triangle inscribed in the circle of ``radius`` around ``center``, one
    corner pointing up (+y)."""

    def __init__(self, center=(0.0, 0.0), radius=1.0):
        super().__init__(center=center, radius=radius, n=3)


class Polygon(SDF):
    """Any simple polygon, given by its vertices (either orientation, not repeated at the end).

    Collinear vertices (extra points on an edge) and consecutive duplicates are fine; the
    polygon must not intersect or touch itself and must enclose a non-zero area (checked, in
    O(n^2)). Evaluated by a compiled loop over the edges (graph op ``prim``, kind
    ``'polygon'``): O(n) per point; the vertices are a table in the generated module.
    """

    def __init__(self, vertices):
        v = _vertices(vertices, "vertices")
        if len(v) > 1 and np.all(v[0] == v[-1]):
            v = v[:-1]  # closed by repeating the first vertex: accepted
        keep = np.any(v != np.roll(v, 1, axis=0), axis=1)  # drop consecutive duplicates
        v = v[keep] if np.any(keep) else v[:1]
        if len(v) < 3:
            raise ValueError(f"vertices needs at least 3 distinct vertices, got "
                             f"{np.asarray(vertices).tolist()!r}")
        _check_simple(v, "vertices")
        v = _ccw(v)
        self.vertices = v
        data = tuple((float(p[0]), float(p[1])) for p in v)
        info = _primitive_info(_points_bbox(v), _edges_symmetry(v), convex=_is_convex(v))
        super().__init__(sym_prim("polygon", _state["x"], _state["y"], data=data), info)


class Star(Polygon):
    """Star with ``n`` points: a polygon alternating between ``radius`` (the tips, one
    pointing up) and ``inner_radius`` (default ``radius / 2``) around ``center``."""

    def __init__(self, center=(0.0, 0.0), radius=1.0, n=5, inner_radius=None):
        center = _vec2(center, "center")
        radius = _positive(radius, "radius")
        n = _check_n(n, minimum=2)
        inner = radius / 2 if inner_radius is None else _positive(inner_radius, "inner_radius")
        if not inner < radius:
            raise ValueError(f"inner_radius must be < radius, got inner_radius={inner!r}, "
                             f"radius={radius!r}")
        t = math.pi / 2 + math.pi * np.arange(2 * n) / n
        rr = np.where(np.arange(2 * n) % 2 == 0, radius, inner)
        v = np.stack([center[0] + rr * np.cos(t), center[1] + rr * np.sin(t)], -1)
        super().__init__(v)
        self.center, self.radius, self.n, self.inner_radius = center, radius, n, inner
        sym = {"x"} if center[0] == 0 else set()
        if center[1] == 0 and n % 2 == 0:
            sym.add("y")
        self._info = replace(self._info, sym=frozenset(sym) if _state["frame"] == _IDENTITY
                             else frozenset())


class Ellipse(SDF):
    """Ellipse around ``center`` with semi-axes ``axes = (a, b)`` along the local x and y axes
    (exact for any axis ratio; equal axes give a circle).

    Evaluated by a compiled closest-point solve (graph op ``prim``, kind ``'ellipse'``): a
    safeguarded Newton iteration, typically 3 to 6 steps (about 10x the cost of a circle).
    """

    def __init__(self, center=(0.0, 0.0), axes=(1.0, 0.5)):
        center = _vec2(center, "center")
        axes = _vec2(axes, "axes")
        if not np.all(axes > 0):
            raise ValueError(f"axes must be > 0, got axes={axes.tolist()!r}")
        self.center, self.axes = center, axes
        x, y = _state["x"], _state["y"]
        expr = sym_prim("ellipse", x - float(center[0]), y - float(center[1]),
                        float(axes[0]), float(axes[1]))
        info = _primitive_info(_points_bbox([center - axes, center + axes]), _center_sym(center),
                               convex=True)
        super().__init__(expr, info)


class Ring(SDF):
    """Annulus: the circle of ``radius`` around ``center`` thickened to total width
    ``thickness`` (``0 < thickness < 2 radius``): ``|length(p - c) - radius| - thickness/2``."""

    def __init__(self, center=(0.0, 0.0), radius=1.0, thickness=0.2):
        center = _vec2(center, "center")
        radius = _positive(radius, "radius")
        thickness = _positive(thickness, "thickness")
        if not thickness < 2 * radius:
            raise ValueError(f"thickness must be < 2 * radius (the hole would close), got "
                             f"thickness={thickness!r}, radius={radius!r}")
        self.center, self.radius, self.thickness = center, radius, thickness
        x, y = _state["x"], _state["y"]
        expr = sym_abs(sym_length(x - float(center[0]), y - float(center[1])) - radius) \
            - thickness / 2
        info = _primitive_info(_points_bbox([center], radius + thickness / 2),
                               _center_sym(center))
        super().__init__(expr, info)


class Arc(SDF):
    """Circular arc of ``radius`` around ``center``, spanning the angle ``aperture`` (radians,
    ``0 < aperture <= 2 pi``) symmetrically about the local +y axis, thickened to total width
    ``thickness`` with round ends (IQ's sdArc; rotate it with ``transform``).

    Exact when ``thickness < 2 radius`` and the two round ends do not overlap (their centres
    are at least ``thickness`` apart, or the arc is a full circle); otherwise exact outside and
    a bound inside (reported as ``'bound'``).
    """

    def __init__(self, center=(0.0, 0.0), radius=1.0, aperture=math.pi, thickness=0.2):
        center = _vec2(center, "center")
        radius = _positive(radius, "radius")
        aperture = _positive(aperture, "aperture")
        if aperture > 2 * math.pi:
            raise ValueError(f"aperture must be <= 2 pi, got aperture={aperture!r}")
        thickness = _positive(thickness, "thickness")
        if not thickness < 2 * radius:
            raise ValueError(f"thickness must be < 2 * radius, got thickness={thickness!r}, "
                             f"radius={radius!r}")
        self.center, self.radius = center, radius
        self.aperture, self.thickness = aperture, thickness
        x, y = _state["x"], _state["y"]
        px, py = x - float(center[0]), y - float(center[1])
        ring = sym_abs(sym_length(px, py) - radius)
        if aperture == 2 * math.pi:
            dist = ring
        else:
            s, c = math.sin(aperture / 2), math.cos(aperture / 2)
            ax = sym_abs(px)
            # beyond the end's ray the end point is nearest, else the circle
            dist = sym_select(ax * c - py * s, sym_length(ax - s * radius, py - c * radius), ring)
        gap = 2 * radius * math.sin(math.pi - aperture / 2)  # distance between the ends
        exact = aperture == 2 * math.pi or gap >= thickness
        info = _primitive_info(_points_bbox([center], radius + thickness / 2),
                               _center_sym(center) & {"x"})
        if not exact:
            info = replace(info, inside=False)
        super().__init__(dist - thickness / 2, info)
