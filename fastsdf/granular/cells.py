"""Neighbour search on the CPU without atomics: a cell list built by a parallel counting sort
(per-thread counts and a prefix sum), the grains reordered by cell (so neighbours in space are
neighbours in memory), and a Verlet list with a skin (compressed rows). The force pass runs over
contiguous chunks of grains in parallel; a pair inside a chunk is listed once and its force
applied to both grains by that chunk, a pair across chunks is listed at both grains, each side
computing it (bit for bit the same, with opposite signs) for its own grain: no two chunks write
the same grain, without atomics.

A list entry is a uint32: the neighbour's index in the low 30 bits (:data:`INDEX_MASK`) and, in
the top two, the periodic image it is seen through (0: none, 1: ``x_j + period``, 2: ``x_j -
period``), fixed at the build (positions are wrapped into the period then, and the period is at
least three cells wide), so the force pass needs no rounding per pair.

A pair is listed when its centres are closer than ``R_i + R_j + skin``; the list stays valid
(every pair in contact is listed) while no grain has moved farther than ``skin / 2`` since it
was built. The cells are at least ``2 max(R) + skin`` wide, so listed pairs lie in adjacent cells.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from numba import njit, prange

from fastsdf.introspect import show_field_types

#: The bits of a list entry that hold the neighbour's index (at most 2**30 grains).
INDEX_MASK = (1 << 30) - 1

__all__ = [
    "INDEX_MASK",
    "CellGrid",
    "SortedGrains",
    "brute_force_pairs",
    "build_verlet",
    "carry_springs",
    "cell_keys",
    "counting_sort",
    "list_pairs",
    "make_grid",
    "permute",
]


@show_field_types
class CellGrid(NamedTuple):
    """Square-ish cells over a rectangle: cell ``(cx, cy)`` covers ``[x0 + cx w, x0 + (cx+1) w)
    x [y0 + cy h, ...)`` with ``w = 1 / inv_w``, ``h = 1 / inv_h``, ``ncx`` by ``ncy`` cells;
    key ``cy * ncx + cx``.
    ``period > 0``: x is periodic with that period (``ncx * w == period``, ``ncx >= 3``)."""

    x0: float
    y0: float
    inv_w: float
    inv_h: float
    ncx: int
    ncy: int
    period: float


def make_grid(
    x: np.ndarray,
    y: np.ndarray,
    cutoff: float,
    period_x0: float = 0.0,
    period: float = 0.0,
    max_cells: int | None = None,
) -> CellGrid:
    """The cell grid over the bounding box of the grains at ``x``, ``y`` with cells at least
    ``cutoff`` wide (wider when the box would need more than ``max_cells`` cells; default
    ``2 n + 64``, which bounds the memory of the cell arrays per grain); with ``period > 0``,
    x is periodic over ``[period_x0, period_x0 + period)``."""
    n = x.shape[0]
    max_cells = 2 * n + 64 if max_cells is None else max_cells
    ylo, yhi = float(y.min()), float(y.max())
    if period > 0:
        xlo, xhi = period_x0, period_x0 + period
    else:
        xlo, xhi = float(x.min()), float(x.max())
    if not all(math.isfinite(v) for v in (xlo, xhi, ylo, yhi)):
        raise FloatingPointError(
            "grain positions are not finite (the simulation blew up: "
            "is the substep short enough for the stiffness?)"
        )
    cell = cutoff
    while True:
        if period > 0:
            ncx = max(int(period // cell), 1)
            w = period / ncx
        else:
            ncx = int((xhi - xlo) // cell) + 1
            w = cell
        ncy = int((yhi - ylo) // cell) + 1
        if ncx * ncy <= max_cells or (period > 0 and ncx < 3):
            break
        cell *= math.sqrt(ncx * ncy / max_cells) * 1.01
    if period > 0 and ncx < 3:
        raise ValueError(
            f"the period must be at least 3 cells ({3 * cutoff}) wide for the "
            f"neighbour search, got period={period!r}"
        )
    return CellGrid(xlo, ylo, 1.0 / w, 1.0 / cell, ncx, ncy, float(period))


@njit(cache=True, parallel=True, error_model="numpy")
def cell_keys(x: np.ndarray, y: np.ndarray, grid: CellGrid, keys: np.ndarray) -> None:
    """Each grain's cell key into ``keys`` (int32); with x periodic, x is first wrapped into
    the period (in place)."""
    for i in prange(x.shape[0]):
        xi = x[i]
        if grid.period > 0.0:
            xi = grid.x0 + (xi - grid.x0) % grid.period
            x[i] = xi
        cx = min(max(int((xi - grid.x0) * grid.inv_w), 0), grid.ncx - 1)
        cy = min(max(int((y[i] - grid.y0) * grid.inv_h), 0), grid.ncy - 1)
        keys[i] = cy * grid.ncx + cx


@njit(cache=True, parallel=True, error_model="numpy")
def counting_sort(
    keys: np.ndarray, ncells: int, counts: np.ndarray, perm: np.ndarray, cell_start: np.ndarray
) -> None:
    """Stable sort of the grains by cell key, in parallel without atomics: chunk ``t`` of the
    grains (``counts.shape[0]`` chunks) counts its keys into its own row ``counts[t]``; a
    prefix sum over (cell, chunk) turns the counts into each chunk's write offsets; each chunk
    then scatters its grains. ``perm[p]`` is the grain at sorted position ``p``; cell ``c``
    holds positions ``cell_start[c]:cell_start[c + 1]``."""
    n = keys.shape[0]
    chunks = counts.shape[0]
    for t in prange(chunks):
        row = counts[t]
        for c in range(ncells):
            row[c] = 0
        for i in range(t * n // chunks, (t + 1) * n // chunks):
            row[keys[i]] += 1
    run = 0
    for c in range(ncells):
        cell_start[c] = run
        for t in range(chunks):
            k = counts[t, c]
            counts[t, c] = run
            run += k
    cell_start[ncells] = run
    for t in prange(chunks):
        row = counts[t]
        for i in range(t * n // chunks, (t + 1) * n // chunks):
            k = keys[i]
            perm[row[k]] = i
            row[k] += 1


@njit(cache=True, parallel=True, error_model="numpy")
def _gather(a, perm, scratch):
    for p in prange(perm.shape[0]):
        scratch[p] = a[perm[p]]
    for p in prange(perm.shape[0]):
        a[p] = scratch[p]


def permute(arrays: tuple, perm: np.ndarray, scratch: np.ndarray) -> None:
    """Reorder every array in place, ``a[:] = a[perm]``, through one scratch array of
    ``perm``'s length and each array's dtype kind (float64 scratch serves int64 arrays through
    a view)."""
    for a in arrays:
        _gather(a, perm, scratch.view(a.dtype) if a.dtype.itemsize == 8 else scratch)


@show_field_types
class SortedGrains(NamedTuple):
    """Grains sorted by cell as the neighbour search reads them: centres ``x, y`` and radii
    ``radius`` (float64), each grain's cell ``keys`` (int32), the cells' ``cell_start``
    (int64; cell ``c`` holds grains ``cell_start[c]:cell_start[c + 1]``) and the list's
    ``skin``. (The grid travels beside it: numba's parallel loops take no tuple nested in a
    tuple.)"""

    x: np.ndarray
    y: np.ndarray
    radius: np.ndarray
    keys: np.ndarray
    cell_start: np.ndarray
    skin: float


@njit(cache=True, inline="always", error_model="numpy")
def _scan(i, lo, hi, cells, grid, out, at, fill):
    """Neighbours of grain ``i`` of ``cells`` (a :class:`SortedGrains` in the cells of
    ``grid``) in its chunk ``lo:hi`` with a larger index, and all those outside its chunk:
    their count, written from ``out[at]`` when ``fill``."""
    x = cells.x
    y = cells.y
    radius = cells.radius
    cell_start = cells.cell_start
    c = cells.keys[i]
    cx = c % grid.ncx
    cy = c // grid.ncx
    xi = x[i]
    yi = y[i]
    ri = radius[i] + cells.skin
    count = 0
    for oy in range(-1, 2):
        ky = cy + oy
        if ky < 0 or ky >= grid.ncy:
            continue
        for ox in range(-1, 2):
            kx = cx + ox
            if grid.period > 0.0:
                kx = (kx + grid.ncx) % grid.ncx
            elif kx < 0 or kx >= grid.ncx:
                continue
            cell = ky * grid.ncx + kx
            for j in range(cell_start[cell], cell_start[cell + 1]):
                if j <= i and j >= lo:  # (j < hi: cells ahead of i may hold later chunks)
                    continue
                dx = xi - x[j]
                image = 0
                if grid.period > 0.0:
                    s = np.rint(dx / grid.period)
                    dx -= grid.period * s
                    image = 1 if s > 0 else (2 if s < 0 else 0)  # 1: seen at x_j + period
                dy = yi - y[j]
                cut = ri + radius[j]
                if dx * dx + dy * dy < cut * cut:
                    if fill:
                        out[at + count] = np.uint32(j | (image << 30))
                    count += 1
    return count


@njit(cache=True, parallel=True, error_model="numpy")
def _count_neighbours(cells, grid, chunks, counts):
    n = cells.x.shape[0]
    for c in prange(chunks):
        lo = c * n // chunks
        hi = (c + 1) * n // chunks
        for i in range(lo, hi):
            counts[i] = _scan(i, lo, hi, cells, grid, counts, 0, False)


@njit(cache=True, parallel=True, error_model="numpy")
def _fill_neighbours(cells, grid, chunks, nbr_start, nbr):
    n = cells.x.shape[0]
    for c in prange(chunks):
        lo = c * n // chunks
        hi = (c + 1) * n // chunks
        for i in range(lo, hi):
            _scan(i, lo, hi, cells, grid, nbr, nbr_start[i], True)


def build_verlet(
    cells: SortedGrains, grid: CellGrid, chunks: int, nbr_start: np.ndarray, nbr: np.ndarray | None
) -> np.ndarray:
    """The Verlet list of grains sorted by the cells of ``grid`` (``cells``), for a force
    pass split into ``chunks`` contiguous chunks of grains (chunk ``c`` holds ``c n // chunks``
    to ``(c + 1) n // chunks - 1``): a pair inside one chunk is listed once, at its lower index
    (the chunk's pass applies the force to both grains: Newton's third law, half the work), a
    pair across two chunks at both grains (each chunk writes only its own grains: no races).
    ``nbr_start`` (int64, n + 1; filled here) and the entries (uint32, see the module docs),
    reusing ``nbr`` when it is large enough (grown by a quarter otherwise). Two passes (count,
    prefix sum, fill), both parallel over chunks."""
    n = cells.x.shape[0]
    counts = nbr_start[1:]
    _count_neighbours(cells, grid, chunks, counts)
    nbr_start[0] = 0
    np.cumsum(counts, out=counts)
    total = int(nbr_start[n])
    if nbr is None or nbr.shape[0] < total:
        nbr = np.empty(total + total // 4 + 16, np.uint32)
    _fill_neighbours(cells, grid, chunks, nbr_start, nbr)
    return nbr


def list_pairs(nbr_start: np.ndarray, nbr: np.ndarray) -> np.ndarray:
    """The pairs ``(i, j)``, ``i < j``, of a Verlet list (grain ``i``'s neighbours are
    ``nbr[nbr_start[i]:nbr_start[i + 1]]``), as an (m, 2) array sorted by rows."""
    n = nbr_start.shape[0] - 1
    i = np.repeat(np.arange(n), np.diff(nbr_start))
    j = (nbr[: nbr_start[n]] & INDEX_MASK).astype(np.int64)
    keep = i < j
    pairs = np.stack([i[keep], j[keep]], axis=1)
    return pairs[np.lexsort((pairs[:, 1], pairs[:, 0]))] if len(pairs) else pairs.reshape(0, 2)


def brute_force_pairs(
    x: np.ndarray, y: np.ndarray, radius: np.ndarray, skin: float, period: float = 0.0
) -> np.ndarray:
    """Every pair ``(i, j)``, ``i < j``, of grains at ``x``, ``y`` with radii ``radius``
    closer than ``R_i + R_j + skin`` (x periodic with ``period`` if > 0; all pairs tested: a
    reference for small n), sorted by rows."""
    dx = x[:, None] - x[None, :]
    if period > 0:
        dx -= period * np.rint(dx / period)
    dy = y[:, None] - y[None, :]
    cut = radius[:, None] + radius[None, :] + skin
    close = np.triu(dx * dx + dy * dy < cut * cut, 1)
    return np.argwhere(close)


@njit(cache=True, inline="always", error_model="numpy")
def _find(start, nbr, row, want):
    for k in range(start[row], start[row + 1]):
        if (nbr[k] & INDEX_MASK) == want:
            return k
    return -1


@njit(cache=True, parallel=True, error_model="numpy")
def carry_springs(
    perm: np.ndarray,
    old_start: np.ndarray,
    old_nbr: np.ndarray,
    old_memory: np.ndarray,
    nbr_start: np.ndarray,
    nbr: np.ndarray,
    memory: np.ndarray,
) -> None:
    """Carry the per-pair memory of an old Verlet list into a new one (the contacts' springs
    across a rebuild): the grain now in slot ``p`` was in slot ``perm[p]`` when the old list
    was built (the reorder by cell of the rebuild); for each new entry ``(p, q)`` the old pair
    ``(perm[p], perm[q])`` is searched in the old row of ``perm[p]``, then (a pair inside one
    chunk is listed at one grain only) in that of ``perm[q]``; a pair not found (new) starts
    at 0. ``memory`` has one row per entry: column 0 is the same from either grain (the
    tangential stretch), column 1 (when present: the rolling torque) changes sign with the
    grain it is seen from. Rows of the list hold a few entries in a packing, so the search is
    short; parallel over grains, each writing its own rows."""
    n = perm.shape[0]
    cols = memory.shape[1]
    for p in prange(n):
        op = perm[p]
        for k in range(nbr_start[p], nbr_start[p + 1]):
            oq = perm[nbr[k] & INDEX_MASK]
            sign = 1.0
            at = _find(old_start, old_nbr, op, oq)
            if at < 0:
                at = _find(old_start, old_nbr, oq, op)
                sign = -1.0
            if at < 0:
                for c in range(cols):
                    memory[k, c] = 0.0
            else:
                memory[k, 0] = old_memory[at, 0]
                for c in range(1, cols):
                    memory[k, c] = sign * old_memory[at, c]
