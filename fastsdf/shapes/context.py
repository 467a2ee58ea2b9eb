"""The modelling context: the coordinates, frame and blend that new shapes are built with.

The state lives in a :class:`contextvars.ContextVar`, so each thread (and each asyncio task)
has its own: scenes built concurrently never see each other's :func:`smoothness` or
:func:`transform`. A new thread starts from the defaults (identity transform, hard blends).
"""

from __future__ import annotations

import contextvars
import math
import numbers
from collections.abc import Iterator
from contextlib import AbstractContextManager, contextmanager
from typing import Any, NamedTuple

import numpy as np

from fastsdf.expr.graph import Expr, Symbol, sym_cos, sym_sin
from fastsdf.expr.validate import (
    FloatOrParam,
    PairOrParam,
    coord2_or_param,
    is_param,
    real_or_param,
    shown,
)
from fastsdf.expr.validate import check_length as _check_length

__all__ = ["smoothness", "transform", "current_smoothness", "current_blend", "BLEND_KINDS"]

_X, _Y = Symbol("x"), Symbol("y")

#: The blends of ``|``, ``&`` and the set-operation methods: ``k`` is the sharpness
#: (1/distance) for ``'exponential'`` and the blend width (distance) for the polynomial ones.
BLEND_KINDS = ("exponential", "quadratic", "cubic")

# The frame of new primitives: local -> world is ``world = M local + t`` with
# ``frame = (m00, m01, m10, m11, tx, ty)``; used only for the exactness bookkeeping (bounding
# boxes and symmetries), the coordinates themselves live in ``x`` and ``y``.
_IDENTITY = (1.0, 0.0, 0.0, 1.0, 0.0, 0.0)


class _State(NamedTuple):
    """The modelling state: the coordinate expressions new primitives are built in, their
    frame, and the smoothness (and blend kind) of ``|`` and ``&``. (Immutable; a named tuple:
    entering a context costs a ``_replace``, cheaper than a frozen dataclass's.)"""

    x: Expr = _X
    y: Expr = _Y
    smoothness: FloatOrParam = 0.0
    blend: str = "exponential"
    frame: tuple | None = _IDENTITY


# Immutable states in a context variable: context managers set a new one and reset on exit (the
# default is a NamedTuple, immutable).
_context: contextvars.ContextVar[_State] = contextvars.ContextVar(
    "fastsdf_modelling_state",
    default=_State(),  # noqa: B039 - an immutable NamedTuple
)


def _coords() -> tuple[Expr, Expr]:
    """``(x, y)``: the expressions of the local coordinates new primitives are built in."""
    s = _context.get()
    return s.x, s.y


def _frame() -> tuple | None:
    """The local -> world frame of new primitives."""
    return _context.get().frame


# ---------------------------------------------------------------------------------------------
# Parameter validation: errors name the parameter and the value.


def _smoothness_value(k: object) -> FloatOrParam:
    if k is None:
        return 0.0
    if type(k) is float and k == 0.0:  # hard: the common case
        return k
    if is_param(k):  # a runtime parameter: checked > 0 at the parameters' defaults
        _, number = real_or_param(k, "k")
        if not number > 0:
            raise ValueError(
                f"a blend k given by parameters must be > 0 (at their defaults), "
                f"got k={k} = {shown(number)}"
            )
        return k
    if isinstance(k, (bool, np.bool_)) or not isinstance(k, numbers.Real):
        raise TypeError(f"smoothness k must be a real number, got k={shown(k)}")
    number = float(k)
    if not math.isfinite(number) or number < 0:
        raise ValueError(
            f"smoothness k must be finite and >= 0 (0 means a hard min/max), got k={shown(number)}"
        )
    if number > 0:
        # a blend width (or, for the exponential blend, its inverse) is a length
        _check_length(number, "smoothness k")
    return number


def _blend_kind(kind: object) -> str:
    if kind == "exp":
        kind = "exponential"
    if not isinstance(kind, str) or kind not in BLEND_KINDS:
        raise ValueError(f"kind must be one of {BLEND_KINDS}, got kind={shown(kind)}")
    return kind


# ---------------------------------------------------------------------------------------------
# The modelling context.


@contextmanager
def _properties(**props: Any) -> Iterator[None]:
    token = _context.set(_context.get()._replace(**props))
    try:
        yield
    finally:
        _context.reset(token)


def smoothness(k: FloatOrParam | None, kind: str = "exponential") -> AbstractContextManager[None]:
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


def current_smoothness() -> FloatOrParam:
    """The smoothness that ``|`` and ``&`` use right now."""
    return _context.get().smoothness


def current_blend() -> tuple:
    """``(k, kind)``: the blend that ``|`` and ``&`` use right now."""
    s = _context.get()
    return s.smoothness, s.blend


def transform(
    angle: FloatOrParam = 0.0, offset: PairOrParam = (0.0, 0.0)
) -> AbstractContextManager[None]:
    """Context manager: primitives created inside are rotated by ``angle`` (radians,
    counter-clockwise) about their own origin, then translated by ``offset``.

    Nested transforms compose, the outer one applied last. Rotations and translations keep
    distances exact.
    """
    a, a0 = real_or_param(angle, "angle")  # (a0 = a unless a is a parameter expression)
    shift, _ = coord2_or_param(offset, "offset")
    if isinstance(shift, np.ndarray):  # numbers: Python floats (the same values, and faster
        shift = tuple(shift.tolist())  # than NumPy scalars in the frame's arithmetic)
    if is_param(a):  # a runtime parameter: the rotation is computed in the kernel
        return _transformed(sym_cos(a), sym_sin(a), shift)
    return _transformed(math.cos(a0), math.sin(a0), shift)


@contextmanager
def _transformed(c: FloatOrParam, s: FloatOrParam, offset: tuple) -> Iterator[None]:
    # Composed on entry, not on the call to transform(), so that the outer context is the one
    # in force where the block runs.
    x, y = _coords()
    # Primitives are built in local coordinates: the inverse transform of the current ones.
    local_x = x * c + y * s - (offset[0] * c + offset[1] * s)
    local_y = -x * s + y * c - (-offset[0] * s + offset[1] * c)
    outer = _frame()
    if outer is None or any(is_param(v) for v in (c, s, offset[0], offset[1])):
        frame = None  # moved by runtime parameters: unknown to the exactness bookkeeping
    else:
        m00, m01, m10, m11, tx, ty = outer  # compose: outer frame o (R, offset)
        frame = (
            m00 * c + m01 * s,
            -m00 * s + m01 * c,
            m10 * c + m11 * s,
            -m10 * s + m11 * c,
            m00 * offset[0] + m01 * offset[1] + tx,
            m10 * offset[0] + m11 * offset[1] + ty,
        )
    with _properties(x=local_x, y=local_y, frame=frame):
        yield
