"""Parameter checks shared by the modelling and simulation modules.

Every error names the parameter and the value it got, at construction time: each check takes
the ``value`` given and the ``name`` of the parameter it was given as.
"""

from __future__ import annotations

import math
import numbers
from collections.abc import Sequence
from typing import TypeAlias, TypeGuard

import numpy as np
from numpy.typing import ArrayLike

from fastsdf.expr.graph import Expr
from fastsdf.expr.quote import shown

__all__ = [
    "shown",
    "count",
    "positive",
    "reals",
    "check_bounds",
    "MAX_COORD",
    "MIN_LENGTH",
    "real",
    "vec2",
    "coord",
    "coord2",
    "length",
    "check_length",
    "is_param",
    "real_or_param",
    "vec2_or_param",
    "coord2_or_param",
]

#: A number, or an expression of runtime parameters (:func:`fastsdf.expr.graph.Param`, time
#: ``t``), wherever a scene takes a number.
FloatOrParam: TypeAlias = "float | Expr"
#: Two numbers (a tuple, list or array), each of which may be an expression of parameters.
PairOrParam: TypeAlias = "ArrayLike | Sequence[float | Expr]"
#: A checked pair: a float64 array of shape (2,), or a tuple holding expressions of parameters.
Pair: TypeAlias = "np.ndarray | tuple[float | Expr, float | Expr]"


def count(value: object, name: str, minimum: int = 1) -> int:
    """``value`` as an int; ``ValueError`` naming ``name`` unless it is an integer (not a
    bool) at least ``minimum``."""
    if (
        isinstance(value, (bool, np.bool_))
        or not isinstance(value, numbers.Integral)
        or value < minimum
    ):
        raise ValueError(f"{name} must be an integer >= {minimum}, got {name}={shown(value)}")
    return int(value)


def positive(value: object, name: str) -> float:
    """``value`` as a float; ``ValueError`` naming ``name`` unless it is a finite number > 0."""
    try:
        number = float(value)  # type: ignore[arg-type]
    except (TypeError, ValueError):
        number = math.nan
    if not (math.isfinite(number) and number > 0.0):
        raise ValueError(f"{name} must be a finite number > 0, got {name}={shown(value)}")
    return number


def reals(value: ArrayLike, name: str) -> np.ndarray:
    """``value`` as a 1-d float64 array (flattened; a 1-d float64 array, strided views
    included, as it is); ``ValueError`` naming ``name`` unless it holds real numbers."""
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError(
            f"{name} must be an array of real numbers, got {name} of type {type(value).__name__}"
        ) from None
    return arr if arr.ndim == 1 else arr.reshape(-1)


def check_bounds(bounds: object, name: str = "bounds") -> tuple:
    """``bounds`` as ``((x0, x1), (y0, y1))`` floats: ``TypeError`` naming ``name`` unless
    it is two pairs of numbers, ``ValueError`` unless they are finite with ``x0 < x1`` and
    ``y0 < y1``."""
    try:
        arr = np.asarray(bounds, dtype=np.float64)
    except (TypeError, ValueError):
        arr = None
    if arr is None or arr.shape != (2, 2):
        raise TypeError(f"{name} must be [(xmin, xmax), (ymin, ymax)], got {name}={shown(bounds)}")
    if not (np.all(np.isfinite(arr)) and arr[0, 0] < arr[0, 1] and arr[1, 0] < arr[1, 1]):
        raise ValueError(
            f"{name} must be finite with xmin < xmax and ymin < ymax, got {name}={shown(bounds)}"
        )
    (x0, x1), (y0, y1) = arr.tolist()
    return (x0, x1), (y0, y1)


def real(value: object, name: str, finite: bool = True) -> float:
    """``value`` as a float; ``TypeError`` unless it is a real number (bools are not), and
    ``ValueError`` if ``finite`` and it is NaN or infinite."""
    if isinstance(value, float):  # float and np.float64: the common case
        value = float(value)
        if not finite or math.isfinite(value):
            return value
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, numbers.Real):
        raise TypeError(f"{name} must be a real number, got {name}={shown(value)}")
    value = float(value)
    if finite and not math.isfinite(value):
        raise ValueError(f"{name} must be finite, got {name}={shown(value)}")
    return value


def _pair_fast(value: object) -> tuple[float, float] | None:
    """``(a, b)`` as Python floats for the common input, a tuple, list or 1-d array of two real
    numbers (not bools), else None (then the general checks run and name the problem)."""
    t = type(value)
    if isinstance(value, np.ndarray) and t is np.ndarray:
        if value.shape != (2,) or value.dtype.kind not in "iuf":
            return None
        a, b = value.tolist()
    elif isinstance(value, (tuple, list)) and (t is tuple or t is list) and len(value) == 2:
        a, b = value
        if type(a) not in _SCALARS or type(b) not in _SCALARS:
            return None
    else:
        return None
    try:
        return float(a), float(b)
    except OverflowError:  # a huge integer: the general checks say so
        return None


# Scalar types taken as they are by the fast path (bool, a subclass of int, is not among them).
_SCALARS = frozenset((float, int, np.float64, np.float32, np.int64, np.int32))


def vec2(value: object, name: str) -> np.ndarray:
    """``value`` as a finite float64 array of shape (2,), with errors naming ``name``."""
    fast = _pair_fast(value)
    if fast is not None and math.isfinite(fast[0]) and math.isfinite(fast[1]):
        return np.array(fast)
    try:
        arr = np.asarray(value)
    except Exception:  # any conversion failure is a type error for the user
        raise TypeError(
            f"{name} must be a pair of real numbers, got {name}={shown(value)}"
        ) from None
    if arr.dtype.kind not in "iuf":
        raise TypeError(f"{name} must be a pair of real numbers, got {name}={shown(value)}")
    if arr.shape != (2,):
        raise ValueError(f"{name} must have exactly 2 components, got {name}={shown(value)}")
    arr = arr.astype(np.float64)
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} must be finite, got {name}={shown(value)}")
    return arr


# The supported range of geometry: coordinates up to MAX_COORD in magnitude, lengths (sizes,
# radii, thicknesses, blend widths, scale factors) between MIN_LENGTH and MAX_COORD. Inside it
# every primitive, modifier and blend is evaluated to rounding (their formulas are
# scale-invariant or rescale by powers of two); outside it construction raises.
MAX_COORD = 1e150
MIN_LENGTH = 1e-150
_RANGE = "the supported range of fastsdf geometry is 1e-150 to 1e150"


def coord(value: object, name: str) -> float:
    """A real coordinate (or signed offset) with ``|value| <= MAX_COORD``."""
    number = real(value, name)
    if abs(number) > MAX_COORD:
        raise ValueError(
            f"{name} must be at most {MAX_COORD:g} in magnitude ({_RANGE}), got "
            f"{name}={shown(number)}"
        )
    return number


def coord2(value: object, name: str) -> np.ndarray:
    """A finite point (shape (2,)) with both coordinates at most ``MAX_COORD`` in magnitude."""
    fast = _pair_fast(value)
    if fast is not None and abs(fast[0]) <= MAX_COORD and abs(fast[1]) <= MAX_COORD:
        return np.array(fast)  # (NaN fails the comparisons: the general checks report it)
    arr = vec2(value, name)
    if np.any(np.abs(arr) > MAX_COORD):
        raise ValueError(
            f"{name} must have coordinates at most {MAX_COORD:g} in magnitude "
            f"({_RANGE}), got {name}={shown(arr.tolist())}"
        )
    return arr


def length(value: object, name: str, zero: bool = False) -> float:
    """A length: ``MIN_LENGTH <= |value| <= MAX_COORD`` (``0`` too if ``zero``); the sign is
    not checked here."""
    number = real(value, name)
    if number == 0.0 and zero:
        return number
    check_length(abs(number), name, number)
    return number


def check_length(size: float, name: str, given: object = None) -> None:
    """Raise unless ``MIN_LENGTH <= size <= MAX_COORD`` (``size`` derived from ``name``, the
    value ``given``)."""
    if not (MIN_LENGTH <= size <= MAX_COORD):
        given = size if given is None else given
        raise ValueError(
            f"{name} must be between {MIN_LENGTH:g} and {MAX_COORD:g} in "
            f"magnitude ({_RANGE}), got {name}={shown(given)}"
        )


# Runtime parameters (fastsdf.expr.graph.Param) are accepted wherever a scene takes a number: the
# checks run on the value the expression has at the parameters' defaults (values set later are
# the caller's responsibility), and the shape bookkeeping treats such a number as unknown.


def _param_value(expr: Expr, name: str) -> float:
    """The value of a parameter expression at its parameters' defaults (it must not depend on
    the coordinates)."""
    from fastsdf.expr.graph import evaluate_numpy

    if expr.syms:
        raise ValueError(
            f"{name} must be a number or an expression of parameters, got one of "
            f"the coordinates {sorted(expr.syms)}: {name}={expr}"
        )
    return float(evaluate_numpy(expr, {"_": np.zeros(1)})[0])


def is_param(value: object) -> TypeGuard[Expr]:
    """Whether ``value`` is an expression (of parameters) rather than a number."""
    return isinstance(value, Expr) and value.op != "const"


def real_or_param(value: object, name: str) -> tuple[float | Expr, float]:
    """``(value, number)``: ``value`` as a float (checked like :func:`real`) or an expression of
    parameters, and the number to check ranges on (the expression at the defaults)."""
    if type(value) is float and math.isfinite(value):  # the common case, checked at once
        return value, value
    if isinstance(value, Expr):
        if value.op == "const":
            v = real(value.attr, name)
            return v, v
        number = _param_value(value, name)
        if not math.isfinite(number):
            raise ValueError(
                f"{name} must be finite, got {name}={value} = {shown(number)} at the "
                f"parameters' defaults"
            )
        return value, number
    v = real(value, name)
    return v, v


def vec2_or_param(value: object, name: str) -> tuple[Pair, np.ndarray]:
    """``(pair, numbers)``: a pair whose components may be expressions of parameters (else the
    float64 array of :func:`vec2`), and the float64 array of its values at the defaults."""
    fast = _pair_fast(value)
    if fast is not None and math.isfinite(fast[0]) and math.isfinite(fast[1]):
        arr = np.array(fast)
        return arr, arr
    if isinstance(value, (tuple, list)) and any(isinstance(v, Expr) for v in value):
        if len(value) != 2:
            raise ValueError(f"{name} must have exactly 2 components, got {name}={shown(value)}")
        (a, na), (b, nb) = (real_or_param(v, name) for v in value)
        return (a, b), np.array([na, nb])
    arr = vec2(value, name)
    return arr, arr


def coord2_or_param(value: object, name: str) -> tuple[Pair, np.ndarray]:
    """:func:`vec2_or_param` with the coordinate range of :func:`coord2` checked on the numbers
    (for expressions of parameters: their values at the defaults)."""
    fast = _pair_fast(value)
    if fast is not None and abs(fast[0]) <= MAX_COORD and abs(fast[1]) <= MAX_COORD:
        arr = np.array(fast)
        return arr, arr
    pair, numbers_ = vec2_or_param(value, name)
    if np.any(np.abs(numbers_) > MAX_COORD):
        raise ValueError(
            f"{name} must have coordinates at most {MAX_COORD:g} in magnitude "
            f"({_RANGE}), got {name}={shown(numbers_.tolist())}"
        )
    return pair, numbers_
