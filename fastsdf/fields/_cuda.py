"""A :class:`~fastsdf.fields.grid.GridSDF` queried on the GPU: the grid's own per-point sampler
(``grid.sampler``: the same ``@njit`` function the CPU kernels inline),
compiled by numba-cuda into one kernel over device arrays. The node array is copied to the
device once per grid. Points outside ``bounds`` in ``mode='exact'`` are answered by the exact
SDF's CUDA kernels (:mod:`fastsdf.backends.cuda`), merged on the device."""

from __future__ import annotations

from typing import Any

import numpy as np

from fastsdf.device import cuda as _load_cuda
from fastsdf.device import simulated

__all__ = ["query", "device_data"]

# Imported only once a CUDA path is asked for (fastsdf.device checks numba-cuda first); the
# kernels read ``cuda`` as a module global, which numba-cuda's simulator swaps for its own.
cuda = _load_cuda()

THREADS = 256


def _sampling_kernel(sampler: Any) -> Any:
    """The kernel of one of the grid's samplers: value, gradient and 'outside' per point."""

    @cuda.jit
    def sample(data, xs, ys, out, grad, outside):
        i = cuda.grid(1)
        stride = cuda.gridsize(1)
        while i < xs.shape[0]:
            d, gx, gy, inside = sampler(data, xs[i], ys[i])
            out[i] = d
            grad[i, 0] = gx
            grad[i, 1] = gy
            outside[i] = not inside
            i += stride

    return sample


@cuda.jit
def _merge(out, grad, outside, d2, g2, with_grad):
    # outside[i] also marks non-finite points, which both answers leave NaN
    i = cuda.grid(1)
    stride = cuda.gridsize(1)
    while i < out.shape[0]:
        if outside[i]:
            out[i] = d2[i]
            if with_grad:
                grad[i, 0] = g2[i, 0]
                grad[i, 1] = g2[i, 1]
        i += stride


@cuda.jit
def _count(flags, total):
    i = cuda.grid(1)
    stride = cuda.gridsize(1)
    c = 0
    while i < flags.shape[0]:
        c += flags[i]
        i += stride
    cuda.atomic.add(total, 0, c)


_SAMPLE: dict = {}  # a grid's sampler -> its kernel


def device_data(grid: Any) -> tuple:
    """The grid's ``sampler_data`` with its node array on the device (copied once)."""
    got = getattr(grid, "_device_data", None)
    if got is None:
        q, *rest = grid.sampler_data
        # (the simulator runs the @njit sampler on the CPU, which takes the NumPy array)
        got = (q if simulated() else cuda.to_device(np.ascontiguousarray(q)), *rest)
        grid._device_data = got
    return got


def query(grid: Any, xs: Any, ys: Any, compute_gradient: bool) -> tuple:
    """Value and gradient device arrays ``(out, grad)`` of ``grid`` at flat float64 device
    points ``xs, ys`` (``grad`` None without ``compute_gradient``)."""
    n = xs.shape[0]
    out = cuda.device_array(n)
    grad = cuda.device_array((n, 2))
    outside = cuda.device_array(n, dtype=np.uint8)
    blocks = max(1, min(-(-n // THREADS), 65536))
    if n:
        with np.errstate(all="ignore"):
            kernel = _SAMPLE.get(grid.sampler)
            if kernel is None:
                kernel = _SAMPLE[grid.sampler] = _sampling_kernel(grid.sampler)
            kernel[blocks, THREADS](device_data(grid), xs, ys, out, grad, outside)
        if grid.mode == "exact" and grid.exact is not None:
            total = cuda.to_device(np.zeros(1, dtype=np.int64))
            _count[blocks, THREADS](outside, total)
            if total.copy_to_host()[0]:
                d2, g2 = grid.exact(xs, ys, compute_gradient=True, backend="cuda")
                _merge[blocks, THREADS](out, grad, outside, d2, g2, compute_gradient)
    return out, (grad if compute_gradient else None)
