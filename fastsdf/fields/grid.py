"""GridSDF: an SDF sampled on a regular grid and queried by bilinear interpolation.

A :class:`GridSDF` evaluates any fastsdf SDF (a :class:`fastsdf.function.Function`) once at the
nodes of a regular grid over ``bounds``, then answers queries in time independent of the scene:
a handful of loads and multiply-adds per point, in a numba kernel (parallel for large inputs,
serial for small ones). It is the notebook's ``GridSDF`` (cell 22), which used three passes of
``scipy.ndimage.map_coordinates``, rebuilt as one fused gather.

Conventions are those of :class:`fastsdf.function.Function`: distances in the units of the
coordinates, negative inside; ``g(x, y)`` returns float64 values of the shape of ``x``;
``g(x, y, compute_gradient=True)`` returns ``(d, grad)`` with ``grad[..., 0] = dd/dx`` and
``grad[..., 1] = dd/dy``; a point with a NaN or infinite coordinate gets NaN value and gradient.

Grid layout: node ``(i, j)`` sits at ``(x0 + i * hx, y0 + j * hy)`` with ``hx = (x1 - x0) /
(nx - 1)`` (like ``np.mgrid[x0:x1:nx*1j, y0:y1:ny*1j]``, x along the first axis). Storage is one
C-contiguous array: ``(nx, ny, 3)`` holding ``[d, dd/dx, dd/dy]`` per node for
``gradient='stored'``, ``(nx, ny)`` holding ``d`` for ``gradient='fd'``.

Accuracy (``h`` the node spacing; see :func:`measure_error`): bilinear interpolation of the
values is exact at the nodes and for affine functions, and in smooth regions its error is at most
``h**2 / 8 * (|d_xx| + |d_yy|)`` (second order: halving ``h`` divides it by four). Near corners
of the shape and on the medial axis (where the SDF has kinks) the error is first order in ``h``.
The interpolant of an exact (1-Lipschitz) SDF is Lipschitz with constant at most ``sqrt(2)``
(each partial derivative is a blend of node differences of magnitude <= 1): use that bound for
conservative advancement (sphere tracing) against a grid.

For numba code (e.g. a fused particle loop) ``g.sampler`` and ``g.sampler_data`` give the same
interpolation per point: ``d, gx, gy, inside = g.sampler(g.sampler_data, x, y)``.
"""

from __future__ import annotations

import math
import numbers
import sys
from dataclasses import asdict, dataclass
from typing import Any, Literal, overload

import numba
import numpy as np
from llvmlite import ir
from numba import njit, prange, types
from numba.core import cgutils
from numba.extending import intrinsic
from numpy.typing import ArrayLike

from fastsdf.backends.request import Request, make_request
from fastsdf.expr.points import PARALLEL_MIN_POINTS, as_points
from fastsdf.function import Function
from fastsdf.notice import compiling_first

__all__ = ["GridSDF", "GridError", "measure_error", "sample_stored", "sample_fd", "BYTES_PER_NODE"]

#: Bytes stored per grid node, by ``(gradient, dtype name)``.
BYTES_PER_NODE = {
    ("stored", "float64"): 24,
    ("stored", "float32"): 12,
    ("fd", "float64"): 8,
    ("fd", "float32"): 4,
}

_MODES = ("exact", "nearest")
_GRADIENTS = ("stored", "fd")
#: Nodes evaluated per call of the scene kernel while sampling (bounds peak memory).
_BUILD_BLOCK = 1 << 18


# ---------------------------------------------------------------------------------------------
# Per-point samplers (numba). ``data`` is ``GridSDF.sampler_data``: ``(q, x0, x1, y0, y1, ihx,
# ihy, nx, ny)`` where ``q`` is the storage flattened (a C-order view of ``GridSDF.data``),
# ``ihx = 1 / hx`` and ``ihy = 1 / hy``. Node (i, j) starts at ``q[(i * ny + j) * c]`` with c = 3
# channels ``[d, dd/dx, dd/dy]`` for stored gradients, c = 1 for values only. Indices are
# unsigned so numba emits no negative-index wraparound code.

_U1, _U2, _U3, _U4, _U5 = np.uint64(1), np.uint64(2), np.uint64(3), np.uint64(4), np.uint64(5)


@intrinsic
def _prefetch(typingctx, arr, idx):
    """Hint the CPU to fetch ``arr[idx]`` into cache (``llvm.prefetch``; never faults, so any
    index is safe, even one past the end)."""
    if not isinstance(arr, types.Array) or not isinstance(idx, types.Integer):
        return None

    def codegen(context, builder, sig, args):
        ary = context.make_array(sig.args[0])(context, builder, args[0])
        ptr = builder.gep(ary.data, [args[1]])
        i8p, i32 = ir.IntType(8).as_pointer(), ir.IntType(32)
        fnty = ir.FunctionType(ir.VoidType(), [i8p, i32, i32, i32])
        fn = cgutils.get_or_insert_function(builder.module, fnty, "llvm.prefetch.p0")
        builder.call(fn, [builder.bitcast(ptr, i8p), i32(0), i32(3), i32(1)])
        return context.get_dummy_value()

    return types.void(arr, idx), codegen


@njit(cache=True, nogil=True, error_model="numpy")
def _ld(q, k):
    """``q[k]`` as float64 (numba's ``float()`` keeps float32 as float32)."""
    return np.float64(q[k])


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _locate(x, y, x0, x1, y0, y1, ihx, ihy, nx, ny):
    """Cell ``(i, j)`` and fractions ``(tx, ty)`` of a point, clamped into the grid, whether
    it was inside ``bounds``, and whether it was finite (``ok``)."""
    inside = (x >= x0) & (x <= x1) & (y >= y0) & (y <= y1)
    ok = True
    if not inside:
        ok = math.isfinite(x) and math.isfinite(y)
        if not ok:
            x, y = x0, y0
        x = min(max(x, x0), x1)
        y = min(max(y, y0), y1)
    u = (x - x0) * ihx
    v = (y - y0) * ihy
    i = min(int(u), nx - 2)  # u >= 0, so int() is floor; the last node belongs to the last cell
    j = min(int(v), ny - 2)
    return i, j, u - i, v - j, inside, ok


@njit(cache=True, nogil=True, error_model="numpy")
def _lerp2(tx, ty, a, b, c, e):
    """Bilinear blend of nodes a = (i, j), b = (i, j+1), c = (i+1, j), e = (i+1, j+1)."""
    lo = a + ty * (b - a)
    hi = c + ty * (e - c)
    return lo + tx * (hi - lo)


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def sample_stored(data: tuple, x: float, y: float) -> tuple[float, float, float, bool]:
    """Bilinear value and gradient at one point of a ``gradient='stored'`` grid.

    ``data`` is ``GridSDF.sampler_data``. Returns ``(d, dd/dx, dd/dy, inside)`` as
    ``(float64, float64, float64, bool)``: value and gradient interpolated from the four nodes
    around ``(x, y)`` (each channel bilinearly). ``inside`` is False for points outside
    ``bounds``; their values are those at the nearest point of the grid (coordinates clamped).
    Non-finite coordinates give NaN values and ``inside = False``.
    """
    q, x0, x1, y0, y1, ihx, ihy, nx, ny = data
    i, j, tx, ty, inside, ok = _locate(x, y, x0, x1, y0, y1, ihx, ihy, nx, ny)
    if not ok:
        return math.nan, math.nan, math.nan, False
    # Two contiguous runs of 6 numbers: nodes (i, j), (i, j+1) and (i+1, j), (i+1, j+1).
    a = np.uint64(3 * (i * ny + j))
    c = a + np.uint64(3 * ny)
    d = _lerp2(tx, ty, _ld(q, a), _ld(q, a + _U3), _ld(q, c), _ld(q, c + _U3))
    gx = _lerp2(tx, ty, _ld(q, a + _U1), _ld(q, a + _U4), _ld(q, c + _U1), _ld(q, c + _U4))
    gy = _lerp2(tx, ty, _ld(q, a + _U2), _ld(q, a + _U5), _ld(q, c + _U2), _ld(q, c + _U5))
    return d, gx, gy, inside


@njit(cache=True, nogil=True, error_model="numpy")
def _dnode(q, k, n, at, step, ih):
    """Derivative of the values along one axis at a node: ``k`` is the node's index along that
    axis (of ``n`` nodes), ``at`` its flat index, ``step`` the flat distance between neighbours
    along the axis. Central differences in the interior; second-order one-sided differences on
    the grid's edges (first order when n == 2)."""
    if k > 0 and k < n - 1:
        return (_ld(q, at + step) - _ld(q, at - step)) * (0.5 * ih)
    if n == 2:
        return (
            (_ld(q, at + step) - _ld(q, at)) * ih
            if k == 0
            else (_ld(q, at) - _ld(q, at - step)) * ih
        )
    if k == 0:
        return (-3.0 * _ld(q, at) + 4.0 * _ld(q, at + step) - _ld(q, at + step + step)) * (0.5 * ih)
    return (3.0 * _ld(q, at) - 4.0 * _ld(q, at - step) + _ld(q, at - step - step)) * (0.5 * ih)


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def sample_fd(data: tuple, x: float, y: float) -> tuple[float, float, float, bool]:
    """Bilinear value and finite-difference gradient at one point of a ``gradient='fd'`` grid.

    ``data`` is ``GridSDF.sampler_data``. Returns ``(d, dd/dx, dd/dy, inside)``: the value is
    bilinear in the four nodes around ``(x, y)``; the gradient is the bilinear interpolation of
    node gradients taken by central differences of the stored values (second-order one-sided
    differences on the grid's edges), which reads the 12 nodes of the 4x4 stencil less its
    corners. ``inside`` and out-of-bounds/non-finite handling are as in :func:`sample_stored`.
    """
    q, x0, x1, y0, y1, ihx, ihy, nx, ny = data
    i, j, tx, ty, inside, ok = _locate(x, y, x0, x1, y0, y1, ihx, ihy, nx, ny)
    if not ok:
        return math.nan, math.nan, math.nan, False
    row = np.uint64(ny)
    a = np.uint64(i * ny + j)
    c = a + row
    d = _lerp2(tx, ty, _ld(q, a), _ld(q, a + _U1), _ld(q, c), _ld(q, c + _U1))
    gx = _lerp2(
        tx,
        ty,
        _dnode(q, i, nx, a, row, ihx),
        _dnode(q, i, nx, a + _U1, row, ihx),
        _dnode(q, i + 1, nx, c, row, ihx),
        _dnode(q, i + 1, nx, c + _U1, row, ihx),
    )
    gy = _lerp2(
        tx,
        ty,
        _dnode(q, j, ny, a, _U1, ihy),
        _dnode(q, j + 1, ny, a + _U1, _U1, ihy),
        _dnode(q, j, ny, c, _U1, ihy),
        _dnode(q, j + 1, ny, c + _U1, _U1, ihy),
    )
    return d, gx, gy, inside


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _sample_value(data, ch, x, y):
    """Bilinear value only, for storage with ``ch`` channels per node. Returns (d, inside)."""
    q, x0, x1, y0, y1, ihx, ihy, nx, ny = data
    i, j, tx, ty, inside, ok = _locate(x, y, x0, x1, y0, y1, ihx, ihy, nx, ny)
    if not ok:
        return math.nan, False
    a = np.uint64(ch * (i * ny + j))
    c = a + np.uint64(ch * ny)
    s = np.uint64(ch)
    return _lerp2(tx, ty, _ld(q, a), _ld(q, a + s), _ld(q, c), _ld(q, c + s)), inside


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _prefetch_cell(data, ch, wide, x, y):
    """Prefetch the rows of the cell of (x, y): the two rows a bilinear query reads, plus the
    rows above and below for finite-difference gradients (``wide``). Any input is safe."""
    q, x0, x1, y0, y1, ihx, ihy, nx, ny = data
    u = min(max((x - x0) * ihx, 0.0), nx - 2.0)
    v = min(max((y - y0) * ihy, 0.0), ny - 2.0)
    if not (u == u and v == v):
        return
    a = ch * (int(u) * ny + int(v))
    row = ch * ny
    _prefetch(q, a)
    _prefetch(q, a + 2 * ch - 1)
    _prefetch(q, a + row)
    _prefetch(q, a + row + 2 * ch - 1)
    if wide:
        _prefetch(q, a - row)
        _prefetch(q, a + 2 * row)


# ---------------------------------------------------------------------------------------------
# Batch kernels over flat float64 arrays. Each returns the number of finite points that lay
# outside ``bounds`` (so that mode='exact' knows whether a fix-up pass is needed at all). The
# cell of the point PREFETCH places ahead is prefetched, so that several cache misses into a
# large grid are in flight at once instead of one per point.

PREFETCH = 24


@njit(cache=True, nogil=True, error_model="numpy")
def _range(data, ch, gradient, xs, ys, out, grad, start, stop):
    """Points ``start..stop-1``: the value (``gradient`` 0, storage of ``ch`` channels per
    node), or value and gradient, stored (1) or by finite differences (2)."""
    outside = 0
    ahead = min(stop, start + PREFETCH)
    wide = gradient == 2
    for p in range(start, ahead):
        _prefetch_cell(data, ch, wide, xs[p], ys[p])
    for p in range(start, stop):
        if p + PREFETCH < stop:
            _prefetch_cell(data, ch, wide, xs[p + PREFETCH], ys[p + PREFETCH])
        if gradient == 0:
            d, inside = _sample_value(data, ch, xs[p], ys[p])
        else:
            if gradient == 1:
                d, gx, gy, inside = sample_stored(data, xs[p], ys[p])
            else:
                d, gx, gy, inside = sample_fd(data, xs[p], ys[p])
            grad[p, 0] = gx
            grad[p, 1] = gy
        out[p] = d
        outside += (not inside) and (d == d)
    return outside


# Parallel kernels hand out chunks dynamically: each thread claims the next chunk from an
# atomic counter until none is left. With a static split, a thread that shares its core with
# another process holds the whole call back by scheduler time slices (on the shared 2-core
# machine, with one competing process: 15 ms median per 1e6 points static, 8 ms dynamic, 15 ms
# serial); with dynamic claiming the other thread takes over its share. ``workers`` is the
# number of numba threads (passed in: numba.get_num_threads() inside a kernel defeats caching).


@intrinsic
def _fetch_add(typingctx, arr, idx, val):
    """Atomically ``arr[idx] += val``, returning the old value (int64 arrays)."""
    if not (
        isinstance(arr, types.Array)
        and arr.dtype == types.int64
        and isinstance(idx, types.Integer)
        and isinstance(val, types.Integer)
    ):
        return None

    def codegen(context, builder, sig, args):
        ary = context.make_array(sig.args[0])(context, builder, args[0])
        ptr = builder.gep(ary.data, [args[1]])
        v = context.cast(builder, args[2], sig.args[2], types.int64)
        return builder.atomic_rmw("add", ptr, v, "monotonic")

    return types.int64(arr, idx, val), codegen


#: Fewest points per chunk handed to a thread (the prefetch needs a run to pay off).
MIN_CHUNK = 512


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _n_chunks(n, chunks):
    return max(1, min(chunks, n // MIN_CHUNK))


@njit(cache=True, parallel=True, error_model="numpy")
def _par(data, ch, gradient, xs, ys, out, grad, chunks, workers):
    """:func:`_range` over all points, chunks claimed by ``workers`` threads."""
    n = xs.shape[0]
    chunks = _n_chunks(n, chunks)
    counter = np.zeros(1, dtype=np.int64)
    counts = np.zeros(workers, dtype=np.int64)
    for w in prange(workers):
        total = 0
        c = _fetch_add(counter, 0, 1)
        while c < chunks:
            a, b = c * n // chunks, (c + 1) * n // chunks
            total += _range(data, ch, gradient, xs, ys, out, grad, a, b)
            c = _fetch_add(counter, 0, 1)
        counts[w] = total
    return counts.sum()


#: The gradient array of a value-only call (never written).
NOGRAD = np.empty((0, 2))


# ---------------------------------------------------------------------------------------------
# Parameter validation: errors name the parameter and the value.


def _check_bounds(bounds):
    try:
        pairs = [tuple(b) for b in bounds]
    except TypeError:
        raise TypeError(f"bounds must be two (min, max) pairs, got bounds={bounds!r}") from None
    if len(pairs) != 2 or any(len(p) != 2 for p in pairs):
        raise ValueError(
            f"bounds must be two (min, max) pairs, e.g. [(-2, 2), (-2, 2)], got bounds={bounds!r}"
        )
    out = []
    for axis, (lo, hi) in zip("xy", pairs):
        for v in (lo, hi):
            if isinstance(v, (bool, np.bool_)) or not isinstance(v, numbers.Real):
                raise TypeError(f"bounds must hold real numbers, got bounds={bounds!r}")
        lo, hi = float(lo), float(hi)
        if not (math.isfinite(lo) and math.isfinite(hi)):
            raise ValueError(
                f"bounds must be finite, got {axis} range ({lo!r}, {hi!r}) in bounds={bounds!r}"
            )
        if not lo < hi:
            raise ValueError(
                f"bounds must have min < max on each axis (non-empty, not "
                f"reversed), got {axis} range ({lo!r}, {hi!r}) in bounds={bounds!r}"
            )
        if not math.isfinite(hi - lo):
            raise ValueError(f"bounds {axis} range ({lo!r}, {hi!r}) is too wide to grid")
        out.append((lo, hi))
    return tuple(out)


def _check_samples(samples):
    if isinstance(samples, (str, bytes)):
        raise TypeError(
            f"samples must be a pair of node counts such as [400j, 400j] or "
            f"[400, 400], got samples={samples!r}"
        )
    try:
        items = list(samples)
    except TypeError:
        raise TypeError(
            f"samples must be a pair of node counts such as [400j, 400j] or "
            f"[400, 400], got samples={samples!r}"
        ) from None
    if len(items) != 2:
        raise ValueError(
            f"samples must give a node count per axis (2 entries), got samples={samples!r}"
        )
    counts = []
    for s in items:
        if isinstance(s, (bool, np.bool_)):
            raise TypeError(
                f"samples entries must be ints or complex counts like 400j, got samples={samples!r}"
            )
        if isinstance(s, numbers.Integral):
            n = int(s)
        elif isinstance(s, numbers.Complex) and not isinstance(s, numbers.Real):
            c = complex(s)
            if c.real != 0 or not math.isfinite(c.imag) or c.imag != int(c.imag):
                raise ValueError(
                    f"complex samples must be a whole node count like 400j (as in "
                    f"np.mgrid), got samples={samples!r}"
                )
            n = int(c.imag)
        else:
            raise TypeError(
                f"samples entries must be ints or complex counts like 400j (a real "
                f"number would be a step in np.mgrid), got samples={samples!r}"
            )
        if n < 2:
            raise ValueError(f"samples must be at least 2 nodes per axis, got samples={samples!r}")
        counts.append(n)
    return tuple(counts)


def _check_choice(value, name, choices):
    if not isinstance(value, str) or value not in choices:
        raise ValueError(
            f"{name} must be one of {', '.join(repr(c) for c in choices)}, got {name}={value!r}"
        )
    return value


def _check_dtype(dtype):
    try:
        dt = np.dtype(dtype)
    except TypeError:
        dt = None
    if dt is None or dt not in (np.dtype(np.float64), np.dtype(np.float32)):
        raise ValueError(f"dtype must be np.float64 or np.float32, got dtype={dtype!r}")
    return dt


# ---------------------------------------------------------------------------------------------


class GridSDF:
    """An SDF sampled on a regular grid, queried by bilinear interpolation.

    ``GridSDF(f, bounds=[(-2, 2), (-2, 2)], samples=[400j, 400j], mode='exact',
    dtype=np.float64, gradient='stored')``

    Parameters
    ----------
    f : fastsdf.function.Function
        The exact SDF (any fastsdf shape or composition). A scene with runtime parameters is
        sampled at their current values (``f.frozen()``); a scene that moves (uses ``sdf.t``)
        is refused: simulations use moving scenes exactly. It is evaluated once, at every node,
        by its compiled parallel kernel (value and analytic gradient); every node must give a
        finite value (and, for stored gradients, a finite gradient).
    bounds : [(x0, x1), (y0, y1)]
        The gridded rectangle, in the units of the coordinates; finite, ``x0 < x1``, ``y0 < y1``.
    samples : [nx, ny]
        Node counts per axis (at least 2): the notebook's ``400j`` (as in ``np.mgrid``) or a
        plain int. Nodes include both ends: spacing ``h = (x1 - x0) / (nx - 1)``.
    mode : 'exact' or 'nearest'
        How points outside ``bounds`` are answered. ``'exact'`` (default) evaluates the exact
        SDF ``f`` there (a few such points cost a second, small pass), so distances far from the
        grid stay correct: the safe choice for collisions. ``'nearest'`` clamps the point onto
        the grid's edge and interpolates there, like the notebook (cheap, but the distance of a
        far point is the edge's, not its own).
    dtype : np.float64 or np.float32
        Storage precision. Arithmetic is always float64. float32 halves memory and adds a
        rounding error of at most ``2**-24 * max|d|`` (``max|d|`` over the nodes) to values, and
        ``2**-24 * max|grad|`` to stored gradients; with ``gradient='fd'`` the gradient gains up
        to ``2**-24 * max|d| / h`` per component (4 times that in the cells along the grid's
        edge), which grows as the grid is refined.
    gradient : 'stored' or 'fd'
        ``'stored'`` (default) keeps the analytic gradient beside each value, interleaved as
        ``(nx, ny, 3)``: **24 bytes per node in float64, 12 in float32**; the query gradient is
        the bilinear interpolation of exact gradients, second order in ``h`` (continuous, and
        equal to the exact gradient at nodes). ``'fd'`` keeps values only, ``(nx, ny)``:
        **8 bytes per node in float64, 4 in float32** (a third of the memory); the gradient is
        the bilinear interpolation of central differences of the values (one-sided second-order
        differences on the edges), also second order and continuous, but with a larger constant
        (measured on a circle: about 2.5 times the stored-gradient angle error), smeared over
        two cells around kinks, and 1.5 to 2 times slower to query (12 nodes read, not 4).
        The derivative of the bilinear interpolant itself was not chosen: it is discontinuous
        across cell edges and only first order.

    Calling ``g(x, y, compute_gradient=False)`` follows :class:`fastsdf.function.Function`: any
    real array shapes (equal), float64 results of the input's shape, ``grad[..., 0] = dd/dx``,
    NaN for points with a non-finite coordinate. Large inputs run in a parallel numba kernel,
    small ones (below ``fastsdf.backends.kernel.codegen.PARALLEL_MIN_POINTS``) serially.

    Attributes
    ----------
    exact : the ``f`` given (fall back to ``g.exact.point_fn`` outside the grid).
    mode, gradient, dtype, bounds, shape (nx, ny), spacing (hx, hy)
    data : the storage array, (nx, ny, 3) or (nx, ny), C-contiguous.
    nbytes : bytes of storage (``nx * ny * bytes_per_node``); bytes_per_node: 24, 12, 8 or 4.
    sampler, sampler_data : per-point interpolation for numba code, see :attr:`sampler`.
    """

    #: Set by :meth:`from_samples` only (a grid built from an SDF reads ``exact.exactness``).
    exactness: str

    def __init__(
        self,
        f: Function,
        bounds: ArrayLike = ((-2, 2), (-2, 2)),
        samples: ArrayLike = (400j, 400j),
        mode: str = "exact",
        dtype: Any = np.float64,
        gradient: str = "stored",
    ):
        if not isinstance(f, Function):
            raise TypeError(
                f"f must be a fastsdf SDF (a fastsdf.function.Function such as "
                f"sdf.Circle(...)), got f={f!r} of type {type(f).__name__}"
            )
        if f.time_dependent:
            raise ValueError(
                "f depends on time (sdf.t): a grid samples a scene that does not "
                "move. Give a moving scene to the simulation as it is (the exact "
                "SDF is evaluated at the simulation's time), or grid a snapshot "
                "f.frozen(t=...)"
            )
        if f.params:
            f = f.frozen()  # a snapshot at the current parameter values (its own kernel)
        self.bounds = _check_bounds(bounds)
        self.shape = _check_samples(samples)
        self.mode = _check_choice(mode, "mode", _MODES)
        self.gradient = _check_choice(gradient, "gradient", _GRADIENTS)
        self.dtype = _check_dtype(dtype)
        self.exact: Function | None = f
        (x0, x1), (y0, y1) = self.bounds
        nx, ny = self.shape
        self.spacing = ((x1 - x0) / (nx - 1), (y1 - y0) / (ny - 1))
        self.bytes_per_node = BYTES_PER_NODE[(self.gradient, self.dtype.name)]
        self.data = self._sample()
        self.nbytes = int(self.data.nbytes)
        self._set_sampler_data()
        self._channels = 3 if self.gradient == "stored" else 1

    @classmethod
    def from_samples(
        cls,
        values: ArrayLike,
        bounds: ArrayLike,
        exact: Function | None = None,
        mode: str = "nearest",
        dtype: Any = np.float64,
        exactness: str = "none",
    ) -> GridSDF:
        """A grid from node values already computed (e.g. a distance transform of an image).

        ``values[i, j]`` is the signed distance at ``(x0 + i * hx, y0 + j * hy)`` (x along the
        first axis, both ends of ``bounds`` included, at least 2 nodes per axis); gradients are
        taken by finite differences (``gradient='fd'``). ``exact`` is the SDF answering points
        outside ``bounds`` in ``mode='exact'``; without one the mode must be ``'nearest'``.
        ``exactness`` ('exact', 'bound' or 'none', as :attr:`fastsdf.SDF.exactness`) says
        whether the values are samples of a 1-Lipschitz distance (neighbouring nodes differ by
        at most their spacing), which lets simulations skip queries safely.
        """
        v = np.asarray(values)
        if v.ndim != 2 or v.shape[0] < 2 or v.shape[1] < 2 or v.dtype.kind not in "iuf":
            raise ValueError(
                f"values must be a real 2-d array with at least 2 nodes per axis, "
                f"got shape {v.shape} and dtype {v.dtype}"
            )
        if not np.isfinite(v).all():
            raise ValueError("values must be finite at every node")
        if exact is not None and not isinstance(exact, Function):
            raise TypeError(f"exact must be a fastsdf SDF or None, got exact={exact!r}")
        g = cls.__new__(cls)
        g.bounds = _check_bounds(bounds)
        g.mode = _check_choice(mode, "mode", _MODES)
        if g.mode == "exact" and exact is None:
            raise ValueError(
                "mode='exact' needs the exact SDF (exact=...) to answer points "
                "outside bounds; pass one or use mode='nearest'"
            )
        g.exactness = _check_choice(exactness, "exactness", ("exact", "bound", "none"))
        g.gradient = "fd"
        g.dtype = _check_dtype(dtype)
        g.exact = exact
        g.shape = (int(v.shape[0]), int(v.shape[1]))
        (x0, x1), (y0, y1) = g.bounds
        nx, ny = g.shape
        g.spacing = ((x1 - x0) / (nx - 1), (y1 - y0) / (ny - 1))
        g.bytes_per_node = BYTES_PER_NODE[(g.gradient, g.dtype.name)]
        g.data = np.ascontiguousarray(v, dtype=g.dtype)
        g.nbytes = int(g.data.nbytes)
        g._set_sampler_data()
        g._channels = 1
        return g

    # -- construction -------------------------------------------------------------------------
    @property
    def axes(self) -> tuple:
        """Node coordinates along x and y: two 1-d float64 arrays of lengths nx and ny."""
        (x0, x1), (y0, y1) = self.bounds
        return np.linspace(x0, x1, self.shape[0]), np.linspace(y0, y1, self.shape[1])

    def _sample(self) -> np.ndarray:
        """Evaluate the exact SDF at every node, a block of rows at a time (bounded memory)."""
        nx, ny = self.shape
        ax, ay = self.axes
        stored = self.gradient == "stored"
        grid = np.empty((nx, ny, 3) if stored else (nx, ny), dtype=self.dtype)
        assert self.exact is not None  # sampled from an SDF (from_samples grids are not)
        comp = self.exact.compiled
        rows = max(1, _BUILD_BLOCK // ny)
        # Pruning: one plan over the whole grid, used by every block (None where it does not pay).
        grid_bounds = ((float(ax[0]), float(ax[-1])), (float(ay[0]), float(ay[-1])))
        plan = comp.pruned_plan(ax, ay, count=nx * ny, bounds=grid_bounds)
        for r0 in range(0, nx, rows):
            r1 = min(nx, r0 + rows)
            xs = np.repeat(ax[r0:r1], ny)
            ys = np.tile(ay, r1 - r0)
            block = grid[r0:r1]
            res = comp.run(xs, ys, "vg" if stored else "v", plan)
            out = res[0]
            with np.errstate(over="ignore"):  # float32 overflow is reported below
                if stored:
                    block[:, :, 0] = out.reshape(r1 - r0, ny)
                    block[:, :, 1:] = res[1].reshape(r1 - r0, ny, 2)
                else:
                    block[...] = out.reshape(r1 - r0, ny)
            if not np.all(np.isfinite(block)):
                self._raise_non_finite(block, r0, ax, ay, out)
        return grid

    def _raise_non_finite(self, block, r0, ax, ay, out):
        bad = ~np.isfinite(block)
        if bad.ndim == 3:
            channel = int(np.argmax(bad.reshape(-1, 3).any(axis=0)))
            bad = bad.any(axis=2)
        else:
            channel = 0
        i, j = np.argwhere(bad)[0]
        what = ("value", "gradient dd/dx", "gradient dd/dy")[channel]
        raw = out.reshape(block.shape[:2])[i, j]
        note = (
            f" (the float64 value {raw!r} overflows {self.dtype.name})"
            if channel == 0 and math.isfinite(raw)
            else ""
        )
        raise ValueError(
            f"f returned a non-finite {what} at grid node ({r0 + i}, {j}) = "
            f"({float(ax[r0 + i])!r}, {float(ay[j])!r}){note}; {int(bad.sum())} node(s) of this "
            f"block are affected. A GridSDF needs finite values at every node: choose bounds "
            f"where f is defined, got bounds={[list(b) for b in self.bounds]!r}"
        )

    # -- queries ------------------------------------------------------------------------------
    @overload
    def __call__(
        self,
        x: ArrayLike,
        y: ArrayLike | None = None,
        compute_gradient: Literal[False] = False,
        backend: str | None = None,
    ) -> np.ndarray: ...

    @overload
    def __call__(
        self,
        x: ArrayLike,
        y: ArrayLike | None = None,
        *,
        compute_gradient: Literal[True],
        backend: str | None = None,
    ) -> tuple[np.ndarray, np.ndarray]: ...

    @overload
    def __call__(
        self,
        x: ArrayLike,
        y: ArrayLike | None = None,
        compute_gradient: bool = False,
        backend: str | None = None,
    ) -> np.ndarray | tuple[np.ndarray, np.ndarray]: ...

    def __call__(
        self,
        x: ArrayLike,
        y: ArrayLike | None = None,
        compute_gradient: bool = False,
        backend: str | None = None,
    ) -> np.ndarray | tuple[np.ndarray, np.ndarray]:
        """Interpolated distance (and gradient) at points; see the class docstring.
        ``backend='cuda'`` queries on the GPU (:mod:`fastsdf.fields._cuda`): device arrays in
        (CuPy, PyTorch, JAX, numba; NumPy is copied there and back), the caller's kind out."""
        if backend not in (None, "cpu", "cuda"):
            raise ValueError(f"backend must be None, 'cpu' or 'cuda', got backend={backend!r}")
        device = "cuda" if backend == "cuda" else "cpu"
        req = make_request(x, y, "vg" if compute_gradient else "v", device=device)
        return req.answer(self.evaluate(req))

    def evaluate(self, req: Request) -> tuple:
        """The flat results ``(value,)`` or ``(value, gradient)`` of a request ``req`` (see
        :mod:`fastsdf.backends.request`), on the CPU or the GPU as it says."""
        if req.device == "cuda":
            return self._evaluate_cuda(req)
        xs, ys, n = req.xs, req.ys, req.n
        out = np.empty(n)
        grad = np.empty((n, 2)) if req.gradient else None
        if n:
            workers = numba.get_num_threads()
            mode = 0 if grad is None else 1 if self.gradient == "stored" else 2
            args = (
                self.sampler_data,
                self._channels,
                mode,
                xs,
                ys,
                out,
                NOGRAD if grad is None else grad,
            )
            kern = _par if n >= PARALLEL_MIN_POINTS else _range
            with compiling_first("the grid's interpolation", kern):
                if kern is _par:
                    outside = _par(*args, 64 * workers, workers)
                else:
                    outside = _range(*args, 0, n)
            if outside and self.mode == "exact":
                self._exact_outside(xs, ys, out, grad)
        return (out,) if grad is None else (out, grad)

    def device_sampler_data(self) -> tuple:
        """:attr:`sampler_data` with the node array on the GPU (copied once per grid), for
        CUDA kernels that call :attr:`sampler` (numba-cuda compiles the ``@njit`` sampler for
        the device)."""
        from fastsdf.device import cuda

        cuda()
        from fastsdf.fields._cuda import device_data

        return device_data(self)

    def _evaluate_cuda(self, req: Request) -> tuple:
        from fastsdf.device import cuda

        cuda()  # a clear error naming the extra before the kernels' module imports numba-cuda
        from fastsdf.fields._cuda import query

        out, grad = query(self, req.xs, req.ys, req.gradient)
        return (out,) if grad is None else (out, grad)

    def _exact_outside(self, xs, ys, out, grad):
        """mode='exact': replace the clamped answers of finite points outside ``bounds``."""
        (x0, x1), (y0, y1) = self.bounds
        with np.errstate(invalid="ignore"):
            inside = (xs >= x0) & (xs <= x1) & (ys >= y0) & (ys <= y1)
        idx = np.flatnonzero(~inside & np.isfinite(xs) & np.isfinite(ys))
        _exact_at(self.exact, xs, ys, idx, out, grad)

    def contains(self, x: ArrayLike, y: ArrayLike) -> np.ndarray:
        """Boolean array of the points' shape: True where the point ``(x, y)`` lies inside
        ``bounds`` (edges included)."""
        xs, ys, shape = as_points(x, y)
        (x0, x1), (y0, y1) = self.bounds
        with np.errstate(invalid="ignore"):
            return ((xs >= x0) & (xs <= x1) & (ys >= y0) & (ys <= y1)).reshape(shape)

    @property
    def values(self) -> np.ndarray:
        """The stored node values ``d[i, j]`` at ``(axes[0][i], axes[1][j])`` (a view)."""
        return self.data[:, :, 0] if self.gradient == "stored" else self.data

    @property
    def sampler(self) -> Any:
        """The numba ``@njit`` per-point interpolation for this grid's storage.

        Inside numba code, ``d, gx, gy, inside = sampler(data, x, y)`` with ``data =
        g.sampler_data`` (a tuple ``(grid, x0, x1, y0, y1, 1/hx, 1/hy)``; pass it in as an
        argument) returns float64 value and gradient and a bool: ``inside`` is False when
        ``(x, y)`` lies outside ``bounds`` (then the values are the clamped, nearest-edge
        answer, whatever ``mode`` is) or has a non-finite coordinate (then they are NaN). To
        honour ``mode='exact'``, fall back to ``g.exact.point_fn(x, y)`` when not inside. The
        functions are fixed module functions (:func:`sample_stored` for ``gradient='stored'``,
        :func:`sample_fd` for ``'fd'``) compiled with ``cache=True``, so they compile once per
        machine and dtype, and marked ``inline='always'``: referenced as a global in your njit
        code they are inlined into your loop; passed in as an argument (a dispatcher value)
        numba calls them instead (measured about 30% slower in a tight loop).
        """
        return sample_stored if self.gradient == "stored" else sample_fd

    def __getstate__(self) -> dict:
        # A pickle holds the exact SDF's graph (no compiled code: the receiver rebuilds its
        # kernels from its own cache) and the node array once; ``sampler_data`` is a view of
        # that array and is rebuilt, so the samples arrive bit for bit.
        state = self.__dict__.copy()
        state.pop("sampler_data", None)
        state.pop("_device_data", None)  # device memory belongs to this process
        return state

    def __setstate__(self, state: dict) -> None:
        self.__dict__.update(state)
        self._set_sampler_data()

    def _set_sampler_data(self) -> None:
        """The tuple the samplers read: the flat nodes, the bounds, the inverse spacings and
        the node counts."""
        (x0, x1), (y0, y1) = self.bounds
        nx, ny = self.shape
        ihx, ihy = 1.0 / self.spacing[0], 1.0 / self.spacing[1]
        self.sampler_data = (self.data.reshape(-1), x0, x1, y0, y1, ihx, ihy, nx, ny)

    def __repr__(self) -> str:
        return (
            f"GridSDF(bounds={[list(b) for b in self.bounds]}, samples={list(self.shape)}, "
            f"mode={self.mode!r}, dtype={self.dtype.name}, gradient={self.gradient!r}, "
            f"nbytes={self.nbytes})"
        )


# ---------------------------------------------------------------------------------------------
# Accuracy.


def _exact_at(
    exact: Function,
    xs: np.ndarray,
    ys: np.ndarray,
    idx: np.ndarray,
    out: np.ndarray,
    grad: np.ndarray | None,
) -> None:
    """``out[idx]`` (and ``grad[idx]``) from the exact SDF at the points ``idx`` (checked
    already: no second validation)."""
    if not idx.size:
        return
    kind = "v" if grad is None else "vg"
    res = exact.evaluate(Request(xs[idx], ys[idx], (idx.size,), kind))
    out[idx] = res[0]
    if grad is not None:
        grad[idx] = res[1]


@dataclass(frozen=True)
class GridError:
    """Errors of a grid against its exact SDF on random points inside ``bounds``.

    ``n`` points were compared, ``band_n`` of them in the band ``|d_exact| < band`` (near the
    surface, where collisions happen). ``value_max`` and ``value_rms``: the value's absolute
    error, in the units of the coordinates; ``angle_max_deg`` and ``angle_rms_deg``: the angle
    between interpolated and exact gradient, in degrees; ``band_value_max``,
    ``band_value_rms``, ``band_angle_max_deg`` and ``band_angle_rms_deg`` the same in the band
    (NaN when no point fell in it). ``spacing`` is the grid's (hx, hy).
    """

    n: int
    band: float
    band_n: int
    spacing: tuple
    value_max: float
    value_rms: float
    angle_max_deg: float
    angle_rms_deg: float
    band_value_max: float
    band_value_rms: float
    band_angle_max_deg: float
    band_angle_rms_deg: float

    def as_dict(self) -> dict:
        """The fields as a plain dict."""
        return asdict(self)


def _stats(a):
    if a.size == 0:
        return math.nan, math.nan
    return float(np.max(a)), float(np.sqrt(np.mean(a * a)))


def measure_error(
    g: GridSDF, n: int = 200_000, band: float = 0.1, seed: int = 0, points: tuple | None = None
) -> Any:
    """Measure ``g`` against ``g.exact`` on ``n`` uniform random points inside ``g.bounds``.

    Returns a :class:`GridError`: max and RMS of the value error ``|d_grid - d_exact|``, and of
    the gradient direction error (angle between the two gradients, degrees), over all points and
    over the band ``|d_exact| < band``. ``seed`` seeds ``numpy.random.default_rng``; ``points``
    may instead give an explicit ``(x, y)`` pair of arrays. Points where the exact SDF is not
    finite are skipped.
    """
    if not isinstance(g, GridSDF):
        raise TypeError(f"g must be a GridSDF, got g={g!r}")
    if not (isinstance(band, numbers.Real) and band > 0 and math.isfinite(band)):
        raise ValueError(f"band must be a positive finite number, got band={band!r}")
    if points is None:
        if isinstance(n, (bool, np.bool_)) or not isinstance(n, numbers.Integral) or n < 1:
            raise ValueError(f"n must be a positive integer, got n={n!r}")
        rng = np.random.default_rng(seed)
        (x0, x1), (y0, y1) = g.bounds
        xs, ys = rng.uniform(x0, x1, int(n)), rng.uniform(y0, y1, int(n))
    else:
        xs, ys, _ = as_points(*points)
    dg, gg = g(xs, ys, compute_gradient=True)
    de, ge = g.exact(xs, ys, compute_gradient=True)
    ok = np.isfinite(de) & np.all(np.isfinite(ge), axis=1) & np.isfinite(dg)
    dg, gg, de, ge = dg[ok], gg[ok], de[ok], ge[ok]
    verr = np.abs(dg - de)
    cross = gg[:, 0] * ge[:, 1] - gg[:, 1] * ge[:, 0]
    dot = gg[:, 0] * ge[:, 0] + gg[:, 1] * ge[:, 1]
    aerr = np.degrees(np.arctan2(np.abs(cross), dot))
    inb = np.abs(de) < band
    vmax, vrms = _stats(verr)
    amax, arms = _stats(aerr)
    bvmax, bvrms = _stats(verr[inb])
    bamax, barms = _stats(aerr[inb])
    return GridError(
        n=int(dg.size),
        band=float(band),
        band_n=int(inb.sum()),
        spacing=tuple(g.spacing),
        value_max=vmax,
        value_rms=vrms,
        angle_max_deg=amax,
        angle_rms_deg=arms,
        band_value_max=bvmax,
        band_value_rms=bvrms,
        band_angle_max_deg=bamax,
        band_angle_rms_deg=barms,
    )


def _guard() -> None:
    # Generated modules call these dispatchers: every process reads and writes their numba
    # cache files sealed (see fastsdf.backends.kernel.cache.guard_module).
    from fastsdf.backends.kernel.cache import guard_module

    guard_module(sys.modules[__name__])


_guard()
