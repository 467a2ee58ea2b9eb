"""NarrowBandGridSDF: fine samples only near the surface, a lower bound everywhere else.

A particle (or any collision test) only needs an accurate distance where it may touch a
surface. A dense :class:`fastsdf.fields.grid.GridSDF` spends almost all its memory far from any
surface; its memory grows with the area while its accuracy is set by the spacing. A
:class:`NarrowBandGridSDF` keeps a coarse level of *tiles* over ``bounds`` (8 x 8 fine
cells each, like the leaves of OpenVDB; Museth 2013) and stores fine nodes (value and gradient,
as ``GridSDF(gradient='stored')``) only in the tiles that can reach the band ``|d| <= band``
(or ``lo <= d <= hi`` for ``band=(lo, hi)``: particles, which only touch surfaces from outside,
need a band that reaches their largest radius on the outside and only a few spacings inside).

Which tiles are fine is decided soundly: with ``L`` a Lipschitz bound of ``f`` (1 for fastsdf
shapes whose ``exactness`` is ``'exact'`` or ``'bound'``), every point ``p`` of a tile with
centre ``c`` and half-diagonal ``rt`` has ``f(c) - L rt <= f(p) <= f(c) + L rt``; a tile is
*far* when that range misses the band. For a function with no known bound the interval bounds of
:mod:`fastsdf.expr.interval` over the tile take its place. A far tile stores one int32: a lower
bound of ``|f|`` over the tile (with ``f``'s sign there, quantized downwards) less half a fine cell
diagonal, and the direction of ``f``'s gradient at the tile centre (in 4096 steps), which it
answers as the gradient (so that a particle that starts deep inside matter is still pushed out).
So every far answer is a correct lower bound of ``|d|`` with the right sign: collision tests and
sphere tracing stay safe; they are only conservative far from surfaces.

Inside fine tiles queries are bilinear in value and in each gradient component, exactly as a
dense grid of the same spacing (the node coordinates are computed the same way, so the values
agree to the last bit). Neighbouring fine tiles share their edge nodes (each tile stores its
9 x 9 nodes), so the interpolant is continuous across tile edges. Between a fine and
a far tile it jumps from the interpolated value to the lower bound (only where ``|d| > band``).

**Tolerance builds.** ``tolerance=t`` makes the build choose the spacing: it builds a trial grid,
estimates every band cell's interpolation error (the error at the cell's midpoint against the
exact SDF, and ``h |grad jump| / 8`` along the cell's edges, which equals the maximum error of a
parabola and catches kinks), and refines assuming second order until at most about 1% of the band
cells exceed ``t / 2``. The remaining cells over ``t / 2`` - those crossed by a kink of the SDF
(a corner of the shape, the medial axis), where bilinear interpolation is only first order - are
marked *exact*: queries there evaluate the exact SDF (the same fallback a dense grid uses outside
its bounds; the particle loop's ``inside=False`` path). The achieved error is measured with
:meth:`NarrowBandGridSDF.measure_error` (random points in the band, see
:func:`measure_band_error`); ``nbytes`` and ``memory`` report the storage.

For numba code: ``d, gx, gy, inside = g.sampler(g.sampler_data, x, y)`` as for the dense grid
(:data:`fastsdf.fields.grid.GridSDF.sampler`); ``inside`` is False outside ``bounds``, in exact
cells and for non-finite points (then the values are NaN), and the caller evaluates
``g.exact.point_fn(x, y)`` there (finite points). :class:`fastsdf.particles.ParticleSimulation`
accepts a NarrowBandGridSDF as its world. For particles choose ``band=(-w, r_max + w)`` with
``r_max`` the largest particle radius and ``w`` a few spacings (or a symmetric ``band`` of at
least ``r_max + w``, twice the memory): a particle in contact then only touches fine tiles, and
one pushed deeper than ``w`` into matter gets a far tile's answer, a lower bound of its depth
with the direction out of matter.
"""

from __future__ import annotations

import math
import numbers
import sys
import time
from typing import Any, Literal, overload

import numba
import numpy as np
from numba import njit, prange, types
from numba.core import cgutils
from numba.extending import intrinsic
from numpy.typing import ArrayLike

from fastsdf.backends.request import Request, make_request
from fastsdf.expr.points import PARALLEL_MIN_POINTS, as_points
from fastsdf.fields.grid import (
    NOGRAD,
    GridError,
    _check_bounds,
    _check_dtype,
    _check_samples,
    _exact_at,
    _fetch_add,
    _n_chunks,
    _stats,
)
from fastsdf.function import Function
from fastsdf.notice import compiling_first

__all__ = ["NarrowBandGridSDF", "sample_band", "measure_band_error"]

_TILE = 8  # cells per tile side: 64 cells, one 64-bit mask of exact cells
_SHIFT = 3  # log2(_TILE); the samplers use these as compile-time constants
_N1 = _TILE + 1  # nodes per tile side (edge nodes are shared with the neighbours)
_TRIAL_CELLS = 256  # cells along the longer side of a tolerance build's trial grid
_EXACT_FRACTION = 0.01  # tolerance builds refine until about this share of cells is exact
_SAFETY = 0.5  # cells whose estimated error exceeds safety * tolerance are exact
_DIR_BITS = 12  # far tiles: gradient direction in 4096 steps (0.09 degrees)
_NDIR = 1 << _DIR_BITS
_M_MAX = 1 << (30 - _DIR_BITS)  # far tiles: lower bound in at most this many quanta
_DIRS = np.stack(
    [np.cos(2 * np.pi * np.arange(_NDIR) / _NDIR), np.sin(2 * np.pi * np.arange(_NDIR) / _NDIR)],
    axis=1,
).reshape(-1)


# ---------------------------------------------------------------------------------------------
# Per-point samplers (numba). ``data`` is ``NarrowBandGridSDF.sampler_data``:
# ``(table, q, masks, dirs, x0, x1, y0, y1, ihx, ihy, nx, ny, nty, quantum)``.
# ``table[ti * nty + tj]`` (int32) is ``2 k + x`` for fine tile k (x = 1 if any of its cells is
# exact, so that the other tiles skip the mask load), or for a far tile
# ``-(1 + s + 2 (a + _NDIR m))``: lower bound ``m * quantum`` of |d|, ``s = 1`` where d < 0, and
# the direction of the exact gradient at the tile's centre, ``dirs[a] = (cos, sin)`` of the angle
# ``2 pi a / _NDIR`` (so a particle deep inside matter is still pushed out). Fine tile k stores
# its (T+1) x (T+1) nodes from ``q[k * (T+1)**2 * 3]``, each ``[d, dd/dx, dd/dy]``, x-major.
# ``masks[k]`` has bit ``a * T + b`` set where cell (a, b) of the tile answers with the exact SDF.
# nx, ny count cells inside bounds; T = 8 cells per tile side.


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _band_locate(data, x, y):
    """(k, a, b, tx, ty, far, status): status 0 = fine cell, 1 = far tile (far holds the
    signed lower bound, k the direction index), 2 = exact fallback (outside bounds, exact cell,
    non-finite)."""
    table, q, masks, dirs, x0, x1, y0, y1, ihx, ihy, nx, ny, nty, quantum = data
    if not ((x >= x0) & (x <= x1) & (y >= y0) & (y <= y1)):
        return 0, 0, 0, 0.0, 0.0, 0.0, 2
    u = (x - x0) * ihx
    v = (y - y0) * ihy
    i = min(int(u), nx - 1)  # u >= 0: int() is floor; the last node belongs to the last cell
    j = min(int(v), ny - 1)
    ti = i >> _SHIFT
    tj = j >> _SHIFT
    e = np.int64(table[np.uint64(ti * nty + tj)])
    if e < 0:
        c = -1 - e
        val = (c >> (1 + _DIR_BITS)) * quantum
        if c & 1:
            val = -val
        return ((c >> 1) & (_NDIR - 1)), 0, 0, 0.0, 0.0, val, 1
    a = i - (ti << _SHIFT)
    b = j - (tj << _SHIFT)
    k = e >> 1
    # the tile has exact cells: look at its mask
    if e & 1 and (masks[np.uint64(k)] >> np.uint64((a << _SHIFT) + b)) & np.uint64(1):
        return 0, 0, 0, 0.0, 0.0, 0.0, 2
    return k, a, b, u - i, v - j, 0.0, 0


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _lerp2(tx, ty, a, b, c, e):
    lo = a + ty * (b - a)
    hi = c + ty * (e - c)
    return lo + tx * (hi - lo)


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _lerp_channel(q, base, c, k, tx, ty):
    """Channel ``k`` (value, x or y gradient) of a fine cell's nodes (``base`` its lower left,
    ``c`` the node one column on; 3 channels per node), blended bilinearly."""
    u3 = np.uint64(3)
    a, b = np.float64(q[base + k]), np.float64(q[base + k + u3])
    return _lerp2(tx, ty, a, b, np.float64(q[c + k]), np.float64(q[c + k + u3]))


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def sample_band(data: tuple, x: float, y: float) -> tuple[float, float, float, bool]:
    """Value and gradient at one point of a :class:`NarrowBandGridSDF`.

    ``data`` is ``g.sampler_data``. Returns ``(d, dd/dx, dd/dy, inside)`` (float64 x3, bool):
    bilinear in a fine cell; in a far tile the stored signed lower bound of the distance and the
    unit direction of the exact gradient at the tile's centre; ``inside = False`` with NaN
    values outside ``bounds``, in cells marked exact and for non-finite coordinates (evaluate
    the exact SDF there).
    """
    k, a, b, tx, ty, far, status = _band_locate(data, x, y)
    if status == 1:
        dirs = data[3]
        return far, dirs[np.uint64(2 * k)], dirs[np.uint64(2 * k + 1)], True
    if status == 2:
        return math.nan, math.nan, math.nan, False
    q = data[1]
    base = np.uint64(3 * ((k * _N1 + a) * _N1 + b))
    c = base + np.uint64(3 * _N1)
    d = _lerp_channel(q, base, c, np.uint64(0), tx, ty)
    gx = _lerp_channel(q, base, c, np.uint64(1), tx, ty)
    gy = _lerp_channel(q, base, c, np.uint64(2), tx, ty)
    return d, gx, gy, True


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _sample_band_value(data, x, y):
    k, a, b, tx, ty, far, status = _band_locate(data, x, y)
    if status == 1:
        return far
    if status == 2:
        return math.nan
    q = data[1]
    base = np.uint64(3 * ((k * _N1 + a) * _N1 + b))
    c = base + np.uint64(3 * _N1)
    u3 = np.uint64(3)
    return _lerp2(
        tx,
        ty,
        np.float64(q[base]),
        np.float64(q[base + u3]),
        np.float64(q[c]),
        np.float64(q[c + u3]),
    )


@intrinsic
def _borrowed(typingctx, arr):
    """A view of ``arr`` without a reference count (null meminfo); the caller keeps ``arr``
    alive."""
    if not isinstance(arr, types.Array):
        return None

    def codegen(context, builder, signature, args):
        src = context.make_array(signature.args[0])(context, builder, args[0])
        out = context.make_array(signature.return_type)(context, builder)
        for field in ("nitems", "itemsize", "data", "shape", "strides"):
            setattr(out, field, getattr(src, field))
        out.meminfo = cgutils.get_null_value(out.meminfo.type)
        out.parent = cgutils.get_null_value(out.parent.type)
        return out._getvalue()

    return arr(arr), codegen


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _borrow(data):
    """The sampler data with its arrays as views without reference counts: binding an array
    to a variable inside the inlined sampler otherwise costs an atomic increment and decrement
    per point (the caller keeps the arrays alive)."""
    return (_borrowed(data[0]), _borrowed(data[1]), _borrowed(data[2]), _borrowed(data[3])) + data[
        4:
    ]


# Batch kernels. They return the number of points that need the exact SDF (NaN answers).
# Software prefetching, which the dense grid's random queries need, measured no gain here: the
# fine storage is small enough to stay in cache.


@njit(cache=True, nogil=True, error_model="numpy")
def _range(data, gradient, xs, ys, out, grad, start, stop):
    """Points ``start..stop-1``: the value, and with ``gradient`` the gradient."""
    data = _borrow(data)
    miss = 0
    for p in range(start, stop):
        if gradient:
            d, gx, gy, inside = sample_band(data, xs[p], ys[p])
            grad[p, 0] = gx
            grad[p, 1] = gy
        else:
            d = _sample_band_value(data, xs[p], ys[p])
            inside = d == d
        out[p] = d
        miss += not inside
    return miss


@njit(cache=True, parallel=True, error_model="numpy")
def _par(data, gradient, xs, ys, out, grad, chunks, workers):
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
            total += _range(data, gradient, xs, ys, out, grad, a, b)
            c = _fetch_add(counter, 0, 1)
        counts[w] = total
    return counts.sum()


# ---------------------------------------------------------------------------------------------
# Parameter checks.


def _positive(value, name):
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, numbers.Real):
        raise TypeError(f"{name} must be a positive real number, got {name}={value!r}")
    v = float(value)
    if not (v > 0 and math.isfinite(v)):
        raise ValueError(f"{name} must be a positive finite number, got {name}={value!r}")
    return v


def _band_range(band):
    """``(lo, hi)`` from ``band=w`` (the band ``|d| <= w``) or ``band=(lo, hi)``."""
    if isinstance(band, numbers.Real) and not isinstance(band, (bool, np.bool_)):
        w = _positive(band, "band")
        return (-w, w)
    try:
        lo, hi = band
    except (TypeError, ValueError):
        raise TypeError(
            f"band must be a positive number or a pair (lo, hi) of signed "
            f"distances, got band={band!r}"
        ) from None
    for v in (lo, hi):
        if isinstance(v, (bool, np.bool_)) or not isinstance(v, numbers.Real):
            raise TypeError(f"band=(lo, hi) must hold two real numbers, got band={band!r}")
    lo, hi = float(lo), float(hi)
    if not (math.isfinite(lo) and math.isfinite(hi) and lo <= 0.0 <= hi and lo < hi):
        raise ValueError(
            f"band=(lo, hi) needs finite lo <= 0 <= hi with lo < hi (the band "
            f"must contain the surface), got band={band!r}"
        )
    return (lo, hi)


def _lipschitz_of(f, lipschitz):
    if lipschitz is not None:
        return _positive(lipschitz, "lipschitz")
    exactness = getattr(f, "exactness", "unknown")
    if exactness in ("exact", "bound"):
        return 1.0
    return None  # unknown: tiles are classified with interval bounds


# ---------------------------------------------------------------------------------------------


class NarrowBandGridSDF:
    """An SDF sampled finely only in the band ``|d| <= band``, bilinear there, a lower bound
    elsewhere. See the module docstring for the layout and the guarantees.

    ``NarrowBandGridSDF(f, bounds=[(-2, 2), (-2, 2)], band=0.05, samples=[3193j, 3193j])`` or
    ``NarrowBandGridSDF(f, bounds, band=0.05, tolerance=1e-5)``

    Parameters
    ----------
    f : fastsdf.function.Function
        The exact SDF (negative inside). Evaluated only at the tile centres, at the nodes of the
        fine tiles and (tolerance builds) at the midpoints of their cells.
    bounds : [(x0, x1), (y0, y1)]
        The gridded rectangle; finite, ``x0 < x1``, ``y0 < y1``. Outside it the exact SDF answers.
    band : float or (lo, hi)
        The band (coordinate units): every point with ``|f| <= band`` (a number) or with
        ``lo <= f <= hi`` (a pair, ``lo <= 0 <= hi``, ``lo < hi``) lies in a fine tile. For
        particles: ``(-w, r_max + w)``, see the module docstring.
    samples : [nx, ny], optional
        Fine node counts over ``bounds`` as for :class:`fastsdf.fields.grid.GridSDF` (``400j`` or
        400): spacing ``h = (x1 - x0) / (nx - 1)``; the fine nodes are exactly those of the dense
        grid with these samples. Give ``samples`` or ``tolerance`` (or both).
    tolerance : float, optional
        Target for the band's value error (coordinate units). Without ``samples`` the spacing is
        chosen from a measured error estimate (see the module docstring); cells whose estimated
        error exceeds ``tolerance / 2`` answer with the exact SDF. Check the result with
        :func:`measure_band_error`.
    dtype : np.float64 or np.float32
        Storage of the fine nodes (arithmetic is float64). float32 adds a rounding error of at
        most ``2**-24 max|d|`` to values and ``2**-24`` to gradient components.
    lipschitz : float, optional
        A bound on ``|grad f|``; default 1 for shapes whose ``exactness`` is ``'exact'`` or
        ``'bound'``. For other functions (``exactness == 'none'``, a bare
        :class:`fastsdf.function.Function`) without ``lipschitz``, tiles are classified with the
        interval bounds of :mod:`fastsdf.expr.interval` over each tile (sound, but slower to build),
        and ``lipschitz`` is None.

    Attributes
    ----------
    exact, bounds, band (as given), tolerance, tile, dtype, lipschitz, mode (always ``'exact'``)
    band_range : (lo, hi), the band as a range of signed distances
    shape : fine node counts (nx, ny) over bounds; spacing : (hx, hy)
    tile : fine cells per tile side (8); tiles : (ntx, nty) tile counts
    n_fine : number of fine tiles; n_exact_cells : cells answered by the exact SDF
    nbytes : bytes stored (table, fine nodes, cell masks); memory : the same, itemised (dict)
    build_seconds : wall time of the build (including trial grids of a tolerance build)
    sampler, sampler_data : per-point query for numba code (see :func:`sample_band`).
    """

    mode = "exact"

    def __init__(
        self,
        f: Any,
        bounds: ArrayLike = ((-2, 2), (-2, 2)),
        band: float = 0.05,
        samples: Any = None,
        tolerance: float | None = None,
        dtype: Any = np.float64,
        lipschitz: float | None = None,
    ):
        t0 = time.perf_counter()
        if not isinstance(f, Function):
            raise TypeError(
                f"f must be a fastsdf SDF (a fastsdf.function.Function such as "
                f"sdf.Circle(...)), got f={f!r} of type {type(f).__name__}"
            )
        if f.time_dependent:  # as GridSDF: a sampled scene does not move
            raise ValueError(
                "f depends on time (sdf.t): a narrow band samples a scene that "
                "does not move; give a moving scene to the simulation as it is, "
                "or sample a snapshot f.frozen(t=...)"
            )
        if f.params:
            f = f.frozen()  # a snapshot at the current parameter values
        self.exact = f
        self.bounds = _check_bounds(bounds)
        self.band_range = _band_range(band)
        self.band = band if isinstance(band, numbers.Real) else self.band_range
        self.tile = _TILE
        self.dtype = _check_dtype(dtype)
        self.lipschitz = _lipschitz_of(f, lipschitz)
        self.tolerance = None if tolerance is None else _positive(tolerance, "tolerance")
        if samples is None and tolerance is None:
            raise ValueError(
                "give samples= (the fine node counts) or tolerance= (a target error), got neither"
            )
        if samples is not None:
            self._build(_check_samples(samples))
        else:
            self._build_to_tolerance()
        self.build_seconds = time.perf_counter() - t0

    # -- construction -------------------------------------------------------------------------
    def _build(self, shape):
        (x0, x1), (y0, y1) = self.bounds
        nx, ny = shape[0] - 1, shape[1] - 1  # cells inside bounds
        T = self.tile
        ntx, nty = -(-nx // T), -(-ny // T)
        if ntx * nty >= 2**31 - 1:
            raise ValueError(f"samples={list(shape)!r} gives too many tiles ({ntx} x {nty})")
        hx, hy = (x1 - x0) / nx, (y1 - y0) / ny
        self.shape = tuple(shape)
        self.spacing = (hx, hy)
        self.tiles = (ntx, nty)
        lip = self.lipschitz
        # Tile centres: one value per tile decides fine or far.
        cx = (np.arange(ntx) * T + T / 2) * hx + x0
        cy = (np.arange(nty) * T + T / 2) * hy + y0
        CX, CY = np.meshgrid(cx, cy, indexing="ij")
        dc, gc = self.exact(CX.ravel(), CY.ravel(), compute_gradient=True)
        rt = 0.5 * T * math.hypot(hx, hy)
        with np.errstate(invalid="ignore"):
            if lip is not None:  # dlo <= f <= dhi over the tile
                dlo, dhi = dc - lip * rt, dc + lip * rt
            else:
                dlo, dhi = self._interval_range(cx, cy, T * hx, T * hy)
            low = np.where(dlo > 0, dlo, np.where(dhi < 0, -dhi, 0.0))  # |f| >= low
            blo, bhi = self.band_range
            fine = ~((dlo > bhi) | (dhi < blo))  # NaN centres are fine (checked below)
        fidx = np.flatnonzero(fine)
        nf = fidx.size
        # Far tiles: a lower bound of |f| over the tile, less half a cell diagonal (so that the
        # interpolated values of neighbouring fine tiles stay above it, which the particle
        # loop's free-flight budget relies on), quantized downwards (capped: still a bound),
        # and the direction of the gradient at the centre.
        slack = 0.5 * math.hypot(hx, hy)
        span = math.hypot(x1 - x0, y1 - y0) + T * max(hx, hy)
        self._quantum = quantum = max(min(hx, hy) / 64.0, span / _M_MAX)
        with np.errstate(invalid="ignore"):
            lb = np.maximum(low - slack, 0.0)
            m = np.minimum(np.maximum(np.floor(lb / quantum) - 1.0, 0.0), _M_MAX - 1)
            ang = np.arctan2(gc[:, 1], gc[:, 0])
        ang = np.where(np.isfinite(ang), ang, 0.0)
        a_idx = np.rint(ang * (_NDIR / (2 * math.pi))).astype(np.int64) % _NDIR
        table = (-(1 + (dc < 0) + 2 * (a_idx + _NDIR * m.astype(np.int64)))).astype(np.int32)
        table[fidx] = 2 * np.arange(nf, dtype=np.int32)
        # Fine nodes: the node (I, J) of the whole grid sits at (I * hx + x0, J * hy + y0), as in
        # np.linspace, the last node of bounds exactly at x1, y1.
        n1 = T + 1
        ti, tj = fidx // nty, fidx % nty
        a = np.arange(n1)
        I = ti[:, None] * T + a[None, :]  # (nf, n1)
        J = tj[:, None] * T + a[None, :]
        xs_t = np.where(nx == I, x1, I * hx + x0)
        ys_t = np.where(ny == J, y1, J * hy + y0)
        X = np.broadcast_to(xs_t[:, :, None], (nf, n1, n1)).ravel()
        Y = np.broadcast_to(ys_t[:, None, :], (nf, n1, n1)).ravel()
        q = np.empty((nf, n1, n1, 3), dtype=self.dtype)
        if nf:
            d, g = self.exact(X, Y, compute_gradient=True)
            if not (np.all(np.isfinite(d)) and np.all(np.isfinite(g))):
                k = int(np.flatnonzero(~(np.isfinite(d) & np.all(np.isfinite(g), axis=1)))[0])
                raise ValueError(
                    f"f returned a non-finite value or gradient at the fine node "
                    f"({float(X[k])!r}, {float(Y[k])!r}): choose bounds where f "
                    f"is defined, got bounds={[list(b) for b in self.bounds]!r}"
                )
            with np.errstate(over="ignore"):
                q[..., 0] = d.reshape(nf, n1, n1)
                q[..., 1:] = g.reshape(nf, n1, n1, 2)
            if not np.all(np.isfinite(q)):
                raise ValueError(f"node values overflow {self.dtype.name}")
        self._table, self._q = table, q
        self._masks = np.zeros(nf, dtype=np.uint64)
        self._cell_error = None
        if self.tolerance is not None and nf:
            self._mark_exact_cells(X, Y, q)
        self._finish()

    def _interval_range(self, cx, cy, wx, wy):
        """Bounds ``(lo, hi)`` of ``f`` over every tile (x-major), from interval evaluation."""
        from fastsdf.expr.interval import bounds as interval_bounds

        CX, CY = np.meshgrid(cx, cy, indexing="ij")
        sx, sy = (s.attr for s in self.exact.symbols)
        boxes = {
            sx: (CX.ravel() - 0.5 * wx, CX.ravel() + 0.5 * wx),
            sy: (CY.ravel() - 0.5 * wy, CY.ravel() + 0.5 * wy),
        }
        lo, hi = interval_bounds(self.exact.f, boxes)
        return np.broadcast_to(lo, CX.size), np.broadcast_to(hi, CX.size)

    def _cell_estimates(self, X, Y, q):
        """Estimated interpolation error of every cell of the fine tiles, shape (nf, T, T), and
        whether each cell can reach the band."""
        nf, n1 = q.shape[0], q.shape[1]
        hx, hy = self.spacing
        v = q[..., 0].astype(np.float64)
        g = q[..., 1:].astype(np.float64)
        X = X.reshape(nf, n1, n1)
        Y = Y.reshape(nf, n1, n1)
        mx = 0.5 * (X[:, :-1, :-1] + X[:, 1:, :-1])
        my = 0.5 * (Y[:, :-1, :-1] + Y[:, :-1, 1:])
        dm = self.exact(mx.ravel(), my.ravel()).reshape(mx.shape)
        bil = 0.25 * (v[:, :-1, :-1] + v[:, 1:, :-1] + v[:, :-1, 1:] + v[:, 1:, 1:])
        e_mid = np.abs(bil - dm)
        jx = np.maximum(
            np.linalg.norm(g[:, 1:, :-1] - g[:, :-1, :-1], axis=-1),
            np.linalg.norm(g[:, 1:, 1:] - g[:, :-1, 1:], axis=-1),
        )
        jy = np.maximum(
            np.linalg.norm(g[:, :-1, 1:] - g[:, :-1, :-1], axis=-1),
            np.linalg.norm(g[:, 1:, 1:] - g[:, 1:, :-1], axis=-1),
        )
        est = np.maximum(e_mid, (hx * jx + hy * jy) / 8.0)
        corner_min = np.minimum(
            np.minimum(v[:, :-1, :-1], v[:, 1:, :-1]), np.minimum(v[:, :-1, 1:], v[:, 1:, 1:])
        )
        corner_max = np.maximum(
            np.maximum(v[:, :-1, :-1], v[:, 1:, :-1]), np.maximum(v[:, :-1, 1:], v[:, 1:, 1:])
        )
        lip = self.lipschitz if self.lipschitz is not None else math.inf
        reach = lip * 0.5 * math.hypot(hx, hy)
        blo, bhi = self.band_range
        with np.errstate(invalid="ignore"):
            in_band = (corner_max + reach >= blo) & (corner_min - reach <= bhi)
        return est, in_band

    def _mark_exact_cells(self, X, Y, q):
        est, in_band = self._cell_estimates(X, Y, q)
        T = self.tile
        over = (est > _SAFETY * self.tolerance) & in_band
        bits = np.left_shift(
            np.uint64(1), (np.arange(T)[:, None] * T + np.arange(T)[None, :]).astype(np.uint64)
        )
        self._masks = np.bitwise_or.reduce(
            np.where(over, bits[None], np.uint64(0)).reshape(over.shape[0], -1), axis=1
        ).astype(np.uint64)
        self._cell_error = (est, in_band)
        fine = self._table >= 0
        self._table[fine] |= (self._masks != 0).astype(np.int32)

    def _build_to_tolerance(self):
        (x0, x1), (y0, y1) = self.bounds
        W, H = x1 - x0, y1 - y0
        h = max(W, H) / _TRIAL_CELLS
        target = _SAFETY * self.tolerance
        self.trials = []
        for _ in range(6):
            shape = (max(2, int(math.ceil(W / h)) + 1), max(2, int(math.ceil(H / h)) + 1))
            self._build(shape)
            est, in_band = self._cell_error if self._cell_error is not None else (None, None)
            if est is None or not in_band.any():
                break
            e = est[in_band]
            frac = float(np.mean(e > target))
            self.trials.append((shape, frac))
            if frac <= 2 * _EXACT_FRACTION:
                break
            eq = float(np.quantile(e, 1.0 - _EXACT_FRACTION))
            # Second order where smooth: the error scales as h**2.
            h *= min(0.9, max(0.2, 0.95 * math.sqrt(target / eq)))

    def _finish(self):
        (x0, x1), (y0, y1) = self.bounds
        hx, hy = self.spacing
        ntx, nty = self.tiles
        self.n_fine = int(self._q.shape[0])
        self.n_exact_cells = int(sum(bin(int(m)).count("1") for m in self._masks))
        self.memory = {
            "table": int(self._table.nbytes),
            "nodes": int(self._q.nbytes),
            "masks": int(self._masks.nbytes),
        }
        self.nbytes = sum(self.memory.values())
        self.sampler_data = (
            self._table,
            self._q.reshape(-1),
            self._masks,
            _DIRS,
            x0,
            x1,
            y0,
            y1,
            1.0 / hx,
            1.0 / hy,
            self.shape[0] - 1,
            self.shape[1] - 1,
            nty,
            self._quantum,
        )

    # -- queries ------------------------------------------------------------------------------
    @overload
    def __call__(
        self, x: ArrayLike, y: ArrayLike | None = None, compute_gradient: Literal[False] = False
    ) -> np.ndarray: ...

    @overload
    def __call__(
        self, x: ArrayLike, y: ArrayLike | None = None, *, compute_gradient: Literal[True]
    ) -> tuple[np.ndarray, np.ndarray]: ...

    @overload
    def __call__(
        self, x: ArrayLike, y: ArrayLike | None = None, compute_gradient: bool = False
    ) -> np.ndarray | tuple[np.ndarray, np.ndarray]: ...

    def __call__(
        self, x: ArrayLike, y: ArrayLike | None = None, compute_gradient: bool = False
    ) -> np.ndarray | tuple[np.ndarray, np.ndarray]:
        """Distance (and gradient) at points: bilinear in fine tiles, the stored lower bound
        (with the centre's gradient direction) in far tiles, the exact SDF outside ``bounds``
        and in exact cells; NaN for non-finite points. Conventions as
        :class:`fastsdf.function.Function`."""
        req = make_request(x, y, "vg" if compute_gradient else "v")
        return req.answer(self.evaluate(req))

    def evaluate(self, req: Request) -> tuple:
        """The flat results ``(value,)`` or ``(value, gradient)`` of a request ``req`` (see
        :mod:`fastsdf.backends.request`)."""
        xs, ys, n = req.xs, req.ys, req.n
        out = np.empty(n)
        grad = np.empty((n, 2)) if req.gradient else None
        if n:
            workers = numba.get_num_threads()
            args = (
                self.sampler_data,
                grad is not None,
                xs,
                ys,
                out,
                NOGRAD if grad is None else grad,
            )
            kern = _par if n >= PARALLEL_MIN_POINTS else _range
            with compiling_first("the band's interpolation", kern):
                if kern is _par:
                    miss = _par(*args, 64 * workers, workers)
                else:
                    miss = _range(*args, 0, n)
            if miss:
                idx = np.flatnonzero(np.isnan(out) & np.isfinite(xs) & np.isfinite(ys))
                _exact_at(self.exact, xs, ys, idx, out, grad)
        return (out,) if grad is None else (out, grad)

    def measure_error(self, n: int = 200_000, seed: int = 0) -> GridError:
        """The achieved error in the band: :func:`measure_band_error` on ``n`` random points
        (drawn by a generator seeded with ``seed``)."""
        return measure_band_error(self, n=n, seed=seed)

    def is_fine(self, x: ArrayLike, y: ArrayLike) -> np.ndarray:
        """Boolean array of the points' shape: True where the point ``(x, y)`` lies inside
        ``bounds`` in a fine tile."""
        xs, ys, shape = as_points(x, y)
        (x0, x1), (y0, y1) = self.bounds
        hx, hy = self.spacing
        with np.errstate(invalid="ignore"):
            ok = (xs >= x0) & (xs <= x1) & (ys >= y0) & (ys <= y1)
        i = np.minimum(((np.where(ok, xs, x0) - x0) / hx).astype(np.int64), self.shape[0] - 2)
        j = np.minimum(((np.where(ok, ys, y0) - y0) / hy).astype(np.int64), self.shape[1] - 2)
        e = self._table[(i // self.tile) * self.tiles[1] + j // self.tile]
        return (ok & (e >= 0)).reshape(shape)

    @property
    def sampler(self) -> Any:
        """The numba per-point query (:func:`sample_band`): ``d, gx, gy, inside =
        sampler(g.sampler_data, x, y)``; evaluate ``g.exact.point_fn`` where ``inside`` is
        False (finite points)."""
        return sample_band

    def __repr__(self) -> str:
        tol = "" if self.tolerance is None else f", tolerance={self.tolerance:g}"
        return (
            f"NarrowBandGridSDF(bounds={[list(b) for b in self.bounds]}, band={self.band!r}, "
            f"samples={list(self.shape)}{tol}, tile={self.tile}, dtype={self.dtype.name}, "
            f"fine tiles={self.n_fine}/{self.tiles[0] * self.tiles[1]}, "
            f"exact cells={self.n_exact_cells}, nbytes={self.nbytes})"
        )


# ---------------------------------------------------------------------------------------------


def measure_band_error(
    g: NarrowBandGridSDF,
    n: int = 200_000,
    seed: int = 0,
    band: float | None = None,
    points: tuple | None = None,
) -> GridError:
    """Errors of a grid against its exact SDF on ``n`` random points in the band (drawn by a
    generator seeded with ``seed``).

    Points are drawn uniformly from the fine tiles of ``g`` (a :class:`NarrowBandGridSDF`;
    they cover the band) and the band statistics keep those with ``|d_exact| < band`` (or
    ``lo < d_exact < hi`` for ``band=(lo, hi)``; default ``g.band``). ``g`` may also be a dense
    :class:`fastsdf.fields.grid.GridSDF`; then ``points`` (an ``(x, y)`` pair, e.g. drawn for a band
    grid) should be given. Returns a
    :class:`fastsdf.fields.grid.GridError` (value errors in coordinate units, gradient angles in
    degrees; far-tile answers are not in the band, where they would not be errors but bounds).
    """
    if points is None:
        if not isinstance(g, NarrowBandGridSDF):
            raise TypeError(f"g must be a NarrowBandGridSDF when points is not given, got {g!r}")
        xs, ys = band_points(g, n, seed)
    else:
        xs, ys, _ = as_points(*points)
    blo, bhi = _band_range(g.band if band is None else band)
    dg, gg = g(xs, ys, compute_gradient=True)
    de, ge = g.exact(xs, ys, compute_gradient=True)
    inb = (de > blo) & (de < bhi)
    dg, gg, de, ge = dg[inb], gg[inb], de[inb], ge[inb]
    verr = np.abs(dg - de)
    cross = gg[:, 0] * ge[:, 1] - gg[:, 1] * ge[:, 0]
    dot = gg[:, 0] * ge[:, 0] + gg[:, 1] * ge[:, 1]
    aerr = np.degrees(np.arctan2(np.abs(cross), dot))
    vmax, vrms = _stats(verr)
    amax, arms = _stats(aerr)
    return GridError(
        n=int(xs.size),
        band=float(max(-blo, bhi)),
        band_n=int(inb.sum()),
        spacing=tuple(g.spacing),
        value_max=vmax,
        value_rms=vrms,
        angle_max_deg=amax,
        angle_rms_deg=arms,
        band_value_max=vmax,
        band_value_rms=vrms,
        band_angle_max_deg=amax,
        band_angle_rms_deg=arms,
    )


def band_points(
    g: NarrowBandGridSDF, n: int = 200_000, seed: int | np.random.Generator | None = 0
) -> tuple[np.ndarray, np.ndarray]:
    """``n`` points drawn uniformly from the fine tiles of ``g`` inside its bounds: (x, y)."""
    if isinstance(n, (bool, np.bool_)) or not isinstance(n, numbers.Integral) or n < 1:
        raise ValueError(f"n must be a positive integer, got n={n!r}")
    rng = np.random.default_rng(seed)
    (x0, x1), (y0, y1) = g.bounds
    fine = np.flatnonzero(g._table >= 0)
    if fine.size == 0:
        return rng.uniform(x0, x1, n), rng.uniform(y0, y1, n)
    T = g.tile
    hx, hy = g.spacing
    k = fine[rng.integers(0, fine.size, n)]
    xs = ((k // g.tiles[1]) * T + rng.uniform(0, T, n)) * hx + x0
    ys = ((k % g.tiles[1]) * T + rng.uniform(0, T, n)) * hy + y0
    keep = (xs <= x1) & (ys <= y1)
    return xs[keep], ys[keep]


def _guard() -> None:
    # Generated modules call these dispatchers: every process reads and writes their numba
    # cache files sealed (see fastsdf.backends.kernel.cache.guard_module).
    from fastsdf.backends.kernel.cache import guard_module

    guard_module(sys.modules[__name__])


_guard()
