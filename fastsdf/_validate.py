"""Parameter checks shared by the modelling and simulation modules.

Every error names the parameter and the value it got, at construction time.
"""

from __future__ import annotations

import math
import numbers

import numpy as np


def real(value, name: str, finite: bool = True) -> float:
    """``value`` as a float; ``TypeError`` unless it is a real number (bools are not), and
    ``ValueError`` if ``finite`` and it is NaN or infinite."""
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, numbers.Real):
        raise TypeError(f"{name} must be a real number, got {name}={value!r}")
    value = float(value)
    if finite and not math.isfinite(value):
        raise ValueError(f"{name} must be finite, got {name}={value!r}")
    return value


def vec2(value, name: str) -> np.ndarray:
    """``value`` as a finite float64 array of shape (2,), with errors naming ``name``."""
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
