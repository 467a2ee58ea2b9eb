"""Coordinates as every evaluator takes them: validated, flat, contiguous float64."""

import numpy as np
from numpy.typing import ArrayLike

PARALLEL_MIN_POINTS = 4096


def as_points(x: ArrayLike, y: ArrayLike) -> tuple:
    """Validate coordinates; returns ``(xs, ys, shape)`` with flat contiguous float64 arrays.

    Raises ``TypeError`` for non-real data and ``ValueError`` if x and y differ in shape.
    """
    xa, ya = np.asarray(x), np.asarray(y)
    for name, arr in (("x", xa), ("y", ya)):
        if arr.dtype.kind not in "iuf":
            raise TypeError(f"{name} must hold real numbers, got dtype {arr.dtype} "
                            f"(value {_preview(arr)})")
    if xa.shape != ya.shape:
        raise ValueError(f"x and y must have the same shape, got x.shape={xa.shape} and "
                         f"y.shape={ya.shape}")
    shape = xa.shape if xa.ndim else (1,)
    xs = np.ascontiguousarray(xa, dtype=np.float64).reshape(-1)
    ys = np.ascontiguousarray(ya, dtype=np.float64).reshape(-1)
    return xs, ys, shape


def _preview(arr: np.ndarray) -> str:
    text = repr(arr.reshape(-1)[:3].tolist()) if arr.size else "[]"
    return text if len(text) < 80 else text[:77] + "..."
