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
"""

from __future__ import annotations

import math
import numbers
from contextlib import contextmanager

import numpy as np

from .graph import Expr, Function, Symbol, sym_abs, sym_length, sym_max, sym_min, sym_smax, sym_smin

__all__ = ["SDF", "Circle", "Halfspace", "Box", "Union", "Intersection", "Difference",
           "smoothness", "transform", "current_smoothness"]

_X, _Y = Symbol("x"), Symbol("y")

# The modelling state: the coordinate expressions new primitives are built in, and the
# smoothness of | and &. Context managers replace it and restore it on exit.
_state = {"x": _X, "y": _Y, "smoothness": 0.0}


# ---------------------------------------------------------------------------------------------
# Parameter validation: errors name the parameter and the value.

def _real(value, name: str) -> float:
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, numbers.Real):
        raise TypeError(f"{name} must be a real number, got {name}={value!r}")
    value = float(value)
    if not math.isfinite(value):
        raise ValueError(f"{name} must be finite, got {name}={value!r}")
    return value


def _vec2(value, name: str) -> np.ndarray:
    try:
        arr = np.asarray(value)
    except Exception:  # noqa: BLE001 - any conversion failure is a type error for the user
        raise TypeError(f"{name} must be a pair of real numbers, got {name}={value!r}") from None
    if arr.dtype.kind not in "iuf":
        raise TypeError(f"{name} must be a pair of real numbers, got {name}={value!r}")
    if arr.shape != (2,):
        raise ValueError(f"{name} must have exactly 2 components, got {name}={value!r}")
    arr = arr.astype(np.float64)
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} must be finite, got {name}={value!r}")
    return arr


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


def smoothness(k):
    """Context manager: ``|`` and ``&`` created inside blend with sharpness ``k`` (1/distance).

    ``k = 0`` (or None) gives the hard ``min``/``max``; larger ``k`` gives a sharper blend that
    rounds the result by at most ``log(2) / k``. ``k`` must be finite and ``>= 0``.
    """
    return _properties(smoothness=_smoothness_value(k))


def current_smoothness() -> float:
    """The smoothness that ``|`` and ``&`` use right now."""
    return _state["smoothness"]


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
    return _properties(x=local_x, y=local_y)


# ---------------------------------------------------------------------------------------------
# Shapes.

class SDF(Function):
    """A signed distance function of the plane: negative inside, positive outside.

    Callable as ``f(x, y, compute_gradient=False)`` (see :class:`fastsdf.graph.Function`);
    ``f.f`` is its expression. Combine with ``|`` (union), ``&`` (intersection), ``-``
    (difference); ``|=`` and friends work too.
    """

    def __init__(self, expr: Expr):
        super().__init__(expr, [_X, _Y])

    @property
    def sdf(self) -> Expr:
        """The expression (the name cgraph's SDF nodes used)."""
        return self.f

    def _other(self, other, op: str):
        if not isinstance(other, SDF):
            raise TypeError(f"cannot {op} an SDF with {other!r} of type {type(other).__name__}; "
                            "both operands must be fastsdf SDF objects")
        return other

    def __or__(self, other):
        return Union(self, self._other(other, "unite"), k=current_smoothness())

    def __and__(self, other):
        return Intersection(self, self._other(other, "intersect"), k=current_smoothness())

    def __sub__(self, other):
        return Difference(self, self._other(other, "subtract"))

    def __repr__(self):
        return f"{type(self).__name__}({str(self.f)[:200]})"


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
        super().__init__(sym_length(x - center[0], y - center[1]) - radius)


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
        super().__init__(x * n[0] + y * n[1] - d)


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
        super().__init__(outside + inside)


class Union(SDF):
    """Union of two SDFs: ``min(a, b)``, or the exponential smooth minimum for ``k > 0``."""

    def __init__(self, a: SDF, b: SDF, k=0.0):
        k = _smoothness_value(k)
        super().__init__(sym_smin(a.f, b.f, k) if k > 0 else sym_min(a.f, b.f))


class Intersection(SDF):
    """Intersection of two SDFs: ``max(a, b)``, or the exponential smooth maximum for ``k > 0``."""

    def __init__(self, a: SDF, b: SDF, k=0.0):
        k = _smoothness_value(k)
        super().__init__(sym_smax(a.f, b.f, k) if k > 0 else sym_max(a.f, b.f))


class Difference(SDF):
    """``a`` with ``b`` cut away: ``max(a, -b)`` (always hard, as in the notebook)."""

    def __init__(self, a: SDF, b: SDF):
        super().__init__(sym_max(a.f, -b.f))
