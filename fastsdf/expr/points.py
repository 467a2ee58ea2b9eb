"""Coordinates as every evaluator takes them: validated, flat, contiguous float64."""

import contextlib
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

__all__ = ["PARALLEL_MIN_POINTS", "as_points", "point_arrays", "device_points"]

PARALLEL_MIN_POINTS = 4096


def as_points(x: ArrayLike, y: ArrayLike | None = None) -> tuple[np.ndarray, np.ndarray, tuple]:
    """Validate coordinates; returns ``(xs, ys, shape)`` with flat contiguous float64 arrays.

    ``x`` and ``y`` broadcast against each other (``f(x, 0.0)`` is a horizontal line); with
    ``y`` omitted, ``x`` holds points along its last axis of length 2 (``f(points)`` for an
    ``(n, 2)`` array). ``shape`` is the shape of the result (``()`` for scalar coordinates).
    Raises ``TypeError`` for non-real data and ``ValueError`` for shapes that do not fit.
    """
    xa = np.asarray(x)
    if y is None:
        if xa.ndim == 0 or xa.shape[-1] != 2:
            raise ValueError(
                f"points given without y must have a last axis of length 2 (x, y), "
                f"got an array of shape {xa.shape}"
            )
        xa, ya = xa[..., 0], xa[..., 1]
    else:
        ya = np.asarray(y)
    for name, arr in (("x", xa), ("y", ya)):
        if arr.dtype.kind not in "iuf":
            raise TypeError(
                f"{name} must hold real numbers, got dtype {arr.dtype} (value {_preview(arr)})"
            )
    if xa.shape != ya.shape:
        try:
            xa, ya = np.broadcast_arrays(xa, ya)
        except ValueError:
            raise ValueError(
                f"x and y must have the same shape (or shapes that broadcast), got "
                f"x.shape={xa.shape} and y.shape={ya.shape}"
            ) from None
    shape = xa.shape
    xs = np.ascontiguousarray(xa, dtype=np.float64).reshape(-1)
    ys = np.ascontiguousarray(ya, dtype=np.float64).reshape(-1)
    return xs, ys, shape


def point_arrays(x: ArrayLike, y: ArrayLike | None = None) -> tuple[np.ndarray, np.ndarray]:
    """``(x, y)`` as two arrays of one shape, by the rules of :func:`as_points` (``y`` omitted:
    ``x`` holds points along its last axis), for entry points that keep the caller's shape."""
    if y is None:
        xa = np.asarray(x)
        if xa.ndim == 0 or xa.shape[-1] != 2:
            raise ValueError(
                f"points given without y must have a last axis of length 2 (x, y), "
                f"got an array of shape {xa.shape}"
            )
        return xa[..., 0], xa[..., 1]
    xa, ya = np.asarray(x), np.asarray(y)
    if xa.shape != ya.shape and xa.dtype.kind in "iuf" and ya.dtype.kind in "iuf":
        with contextlib.suppress(ValueError):  # as_points reports the shapes
            xa, ya = np.broadcast_arrays(xa, ya)
    return xa, ya


def _preview(arr: np.ndarray) -> str:
    text = repr(arr.reshape(-1)[:3].tolist()) if arr.size else "[]"
    return text if len(text) < 80 else text[:77] + "..."


def device_points(x: Any, y: Any = None) -> tuple[Any, Any, tuple]:
    """:func:`as_points` for the CUDA target: ``(xs, ys, shape)`` with ``xs, ys`` flat float64
    numba device arrays. Device arrays (CuPy, PyTorch, JAX, numba) are used where they are,
    without a copy (a float64 ``(..., 2)`` array's columns are read strided); anything else is
    checked by :func:`as_points` and copied to the device."""
    from fastsdf.device import as_device, cuda, is_device_array

    if not (is_device_array(x) or (y is not None and is_device_array(y))):
        xs, ys, shape = as_points(x, y)
        cu = cuda()
        return cu.to_device(xs), cu.to_device(ys), shape
    if y is None:
        d = as_device(x, "x")
        dshape = tuple(d.shape)
        if not dshape or dshape[-1] != 2:
            raise ValueError(
                f"points given without y must have a last axis of length 2 (x, y), "
                f"got a device array of shape {dshape}"
            )
        shape = dshape[:-1] or (1,)
        flat = d.reshape(-1, 2)
        return flat[:, 0], flat[:, 1], shape
    xd, yd = as_device(x, "x"), as_device(y, "y")
    if tuple(xd.shape) != tuple(yd.shape):
        raise ValueError(
            f"x and y on the device must have the same shape, got x.shape={tuple(xd.shape)} "
            f"and y.shape={tuple(yd.shape)}"
        )
    shape = tuple(xd.shape) or (1,)
    return xd.reshape(-1), yd.reshape(-1), shape
