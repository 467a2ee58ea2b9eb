"""Exact Euclidean distance transforms of binary masks, parallel in numba.

The algorithm is Felzenszwalb and Huttenlocher's ("Distance Transforms of Sampled Functions",
2012): a squared distance transform is separable, so a pass along each row (distance to the
nearest feature in the same row) is followed by a pass along each column that takes the lower
envelope of the parabolas ``(q - p)**2 + f(p)``. Both passes are exact: every distance is the
square root of the same sum of squares a brute-force search finds (for unit spacing, the square
root of an integer). The cheap pass runs down tiles of columns (each row's piece of a tile is
contiguous), the envelope pass along rows (contiguous), both in parallel (``prange``), each
thread writing only its own columns or rows: no slot is written by two threads.

Conventions: ``mask[i, j]`` is pixel ``(i, j)``; spacing ``(hi, hj)`` along the two axes.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from numba import njit, prange
from numpy.typing import ArrayLike

from fastsdf.expr.validate import shown
from fastsdf.introspect import show_field_types
from fastsdf.notice import compiling_first

__all__ = ["distance_transform", "signed_distance_transform", "EdtSpacing", "edt_kernel"]

#: Columns per tile in the column pass (one tile row is two cache lines of float64).
_TILE = 16
_INF = np.inf


@show_field_types
class EdtSpacing(NamedTuple):
    """Pixel spacing along the first (``hi``) and second (``hj``) axis of the mask."""

    hi: float
    hj: float


@njit(cache=True, nogil=True, error_model="numpy")
def _column_tile(mask, j0, w, h, signed, g, near, want_near):
    """First pass over the columns ``j0 .. j0 + w``: squared distance along the column to the
    nearest pixel of the target set into ``g`` (``inf`` if none), that pixel's row into
    ``near``. The target of a pixel is the other phase when ``signed``, else the False pixels
    (False pixels get 0). Two sweeps, walking the rows so that each row's tile is contiguous."""
    n = mask.shape[0]
    last_t = np.full(w, -1, dtype=np.int64)  # last True pixel seen, per column
    last_f = np.full(w, -1, dtype=np.int64)  # last False pixel seen
    for i in range(n):
        for b in range(w):
            if mask[i, j0 + b]:
                last_t[b] = i
                k = last_f[b]
            else:
                last_f[b] = i
                k = last_t[b] if signed else i
            g[i, j0 + b] = _INF if k < 0 else ((i - k) * h) ** 2
            if want_near:
                near[i, j0 + b] = k
    last_t[:] = -1
    last_f[:] = -1
    for i in range(n - 1, -1, -1):
        for b in range(w):
            if mask[i, j0 + b]:
                last_t[b] = i
                k = last_f[b]
            else:
                last_f[b] = i
                k = last_t[b] if signed else i
            if k >= 0:
                d = ((k - i) * h) ** 2
                if d < g[i, j0 + b]:
                    g[i, j0 + b] = d
                    if want_near:
                        near[i, j0 + b] = k


@njit(cache=True, nogil=True, error_model="numpy")
def _envelope_pass(f, h, phase, want, vp, vx, va, z, out, arg, want_arg):
    """Second pass along one row: ``out[q] = min_p ((q - p) h)**2 + f[p]`` for the pixels with
    ``phase[q] == want`` (others untouched), the minimising ``p`` into ``arg``. The lower
    envelope of the parabolas over finite ``f[p]`` is built first (indices into ``vp``,
    positions into ``vx``, ``f + x**2`` into ``va``, breakpoints into ``z``), then read left to
    right; values are ``dx**2 + f[p]`` as a brute-force search computes them."""
    n = f.shape[0]
    k = -1
    for q in range(n):
        fq = f[q]
        if fq == _INF:
            continue
        xq = q * h
        aq = fq + xq * xq
        s = -_INF
        while k >= 0:
            s = (aq - va[k]) / (2.0 * (xq - vx[k]))
            if s <= z[k]:
                k -= 1
                s = -_INF
            else:
                break
        k += 1
        vp[k] = q
        vx[k] = xq
        va[k] = aq
        z[k] = s
    count = k + 1
    j = 0
    for q in range(n):
        if phase[q] != want:
            continue
        if count == 0:
            out[q] = _INF
            if want_arg:
                arg[q] = -1
            continue
        x = q * h
        while j + 1 < count and z[j + 1] < x:
            j += 1
        p = vp[j]
        dx = (q - p) * h
        out[q] = dx * dx + f[p]
        if want_arg:
            arg[q] = p


@njit(cache=True, nogil=True, error_model="numpy", parallel=True)
def edt_kernel(mask, spacing, signed, out, feat_i, feat_j):  # noqa: ANN201 (numba kernel)
    """Squared Euclidean distances of a boolean ``mask`` (n, m) into ``out`` (n, m).

    ``signed=False``: the distance of every True pixel to the nearest False pixel (0 on False
    pixels), as ``scipy.ndimage.distance_transform_edt(mask)`` squared. ``signed=True``: every
    pixel's distance to the nearest pixel of the other phase. When ``feat_i, feat_j`` are
    (n, m) int32 arrays (pass (0, 0) ones otherwise) they receive the nearest such pixel (the
    pixel itself where the distance is 0; -1 where none exists). ``spacing``: an
    :class:`EdtSpacing`.
    """
    n, m = mask.shape
    want = feat_i.shape[0] == n
    g = np.empty((n, m))
    near = np.empty((n, m) if want else (0, 0), dtype=np.int64)
    tiles = (m + _TILE - 1) // _TILE
    for t in prange(tiles):
        j0 = t * _TILE
        _column_tile(mask, j0, min(_TILE, m - j0), spacing.hi, signed, g, near, want)
    for i in prange(n):
        row = mask[i]
        f = np.empty(m)
        vp = np.empty(m, dtype=np.int64)
        vx = np.empty(m)
        va = np.empty(m)
        z = np.empty(m + 1)
        arg = np.empty(m if want else 0, dtype=np.int64)
        hj = spacing.hj
        if signed:
            # Envelope of the distances to the True pixels (0 on them), read at False ones;
            # then to the False pixels, read at True ones.
            for j in range(m):
                f[j] = 0.0 if row[j] else g[i, j]
            _envelope_pass(f, hj, row, False, vp, vx, va, z, out[i], arg, want)
            for j in range(m):
                f[j] = g[i, j] if row[j] else 0.0
            _envelope_pass(f, hj, row, True, vp, vx, va, z, out[i], arg, want)
        else:
            for j in range(m):
                if row[j]:
                    f[j] = g[i, j]
                else:
                    f[j] = 0.0
                    out[i, j] = 0.0
                    if want:
                        arg[j] = j
            _envelope_pass(f, hj, row, True, vp, vx, va, z, out[i], arg, want)
        if want:
            for j in range(m):
                p = arg[j]
                feat_j[i, j] = p
                if p < 0:
                    feat_i[i, j] = -1
                elif row[p] != row[j] or not (signed or row[j]):
                    feat_i[i, j] = i  # the envelope's own pixel is the feature
                else:
                    feat_i[i, j] = near[i, p]  # reached along column p
    return out


def _check_mask(mask: ArrayLike, name: str = "mask") -> np.ndarray:
    a = np.asarray(mask)
    if a.ndim != 2:
        raise ValueError(f"{name} must be a 2-d array, got shape {a.shape}")
    if a.dtype != np.bool_:
        if a.dtype.kind not in "iuf":
            raise TypeError(f"{name} must be boolean or real, got dtype {a.dtype}")
        a = a != 0
    return np.ascontiguousarray(a)


def _check_spacing(sampling: ArrayLike | None) -> EdtSpacing:
    if sampling is None:
        return EdtSpacing(1.0, 1.0)
    s = np.broadcast_to(np.asarray(sampling, dtype=np.float64), (2,))
    if not (np.isfinite(s).all() and (s > 0).all()):
        raise ValueError(f"sampling must be positive and finite, got sampling={shown(sampling)}")
    return EdtSpacing(float(s[0]), float(s[1]))


def distance_transform(
    mask: ArrayLike, sampling: ArrayLike | None = None, return_indices: bool = False
) -> np.ndarray | tuple:
    """Distance of each True (non-zero) pixel to the nearest False pixel; 0 on False pixels.

    The same numbers as ``scipy.ndimage.distance_transform_edt(mask, sampling)`` (exact
    Euclidean distances between pixel centres; ``inf`` where the mask has no False pixel), in
    parallel. ``return_indices=True`` also returns the nearest False pixel's indices as an
    int32 array (2, n, m), like scipy's ``return_indices``.
    """
    return _transform(mask, sampling, return_indices, signed=False)


def signed_distance_transform(
    mask: ArrayLike, sampling: ArrayLike | None = None, return_indices: bool = False
) -> np.ndarray | tuple:
    """Signed distance of each pixel centre to the boundary of the True pixels of ``mask`` (a
    2-d boolean array), in the units of ``sampling`` (the pixel's height and width; default
    1: pixels).

    Half-pixel convention: the boundary lies halfway between the centres of two neighbouring
    pixels of different phase, so a pixel's value is its distance to the nearest pixel of the
    other phase less half a pixel (``min(sampling) / 2``), negative on True pixels. Two
    neighbouring pixels across the boundary get ``+h/2`` and ``-h/2``; neighbouring values
    differ by at most their spacing. ``inf``/``-inf`` where the other phase is absent.
    ``return_indices=True`` also returns the nearest other-phase pixel, (2, n, m) int32.
    """
    return _transform(mask, sampling, return_indices, signed=True)


def _transform(
    mask: ArrayLike, sampling: ArrayLike | None, return_indices: bool, signed: bool
) -> np.ndarray | tuple:
    """:func:`distance_transform` or, ``signed``, :func:`signed_distance_transform`."""
    a = _check_mask(mask)
    sp = _check_spacing(sampling)
    out = np.empty(a.shape)
    shape = a.shape if return_indices else (0, 0)
    fi, fj = np.empty(shape, dtype=np.int32), np.empty(shape, dtype=np.int32)
    if a.size:
        with compiling_first("the distance transform", edt_kernel, _finish_signed):
            edt_kernel(a, sp, signed, out, fi, fj)
            if signed:
                _finish_signed(out, a, 0.5 * min(sp.hi, sp.hj))
            else:
                np.sqrt(out, out=out)
    if return_indices:
        return out, np.stack([fi, fj])
    return out


@njit(cache=True, nogil=True, error_model="numpy", parallel=True)
def _finish_signed(sq, inside, half):
    """In place: squared distances to signed distances with the half-pixel shift."""
    n, m = sq.shape
    for i in prange(n):
        for j in range(m):
            d = math.sqrt(sq[i, j]) - half
            sq[i, j] = -d if inside[i, j] else d
