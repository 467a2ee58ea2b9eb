"""Level sets of an SDF as polylines: marching squares with each crossing refined on the SDF.

Marching squares on a grid of samples finds which cell edges the level set crosses and how the
crossings connect; each crossing is then moved onto the level set of the function itself by a
bracketing root finder along its edge (Illinois: regula falsi with the stale end's value
halved, and a step of at least a tolerance from the ends), so a vertex lies within ``tol`` of
the true level set wherever the function is exact, not at the linear interpolation's accuracy
(``scikit-image``'s ``find_contours``; compared in bench/RESULTS.md).

Orientation: every polyline keeps the region below the level (the inside, for ``level=0``) on
its left, so closed loops around solid regions run counter-clockwise and loops around holes
clockwise. Saddle cells are resolved by the function's value at the cell's centre.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any, NamedTuple

import numpy as np
from numpy.typing import ArrayLike

from fastsdf.expr.validate import check_bounds, shown
from fastsdf.introspect import show_field_types

__all__ = ["Contour", "contours", "refine_crossings"]


@show_field_types
class Contour(NamedTuple):
    """One polyline of a level set: ``points`` (k, 2) in the function's coordinates and
    whether it is ``closed`` (then the last point connects back to the first, which is not
    repeated)."""

    points: np.ndarray
    closed: bool


def _evaluate(f: Callable, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    return np.asarray(f(x, y), dtype=np.float64).reshape(x.shape)


def refine_crossings(
    f: Callable,
    fixed: np.ndarray,
    lo: np.ndarray,
    hi: np.ndarray,
    glo: np.ndarray,
    ghi: np.ndarray,
    axis: np.ndarray,
    level: float = 0.0,
    tol: float = 1e-12,
    max_iter: int = 200,
) -> np.ndarray:
    """Roots of ``f - level`` on axis-aligned edges, all edges at once (vectorised Illinois).

    Edge ``k`` runs along x (``axis[k] == 0``) or y (``1``) from coordinate ``lo[k]`` to
    ``hi[k]`` at the other coordinate ``fixed[k]``; ``glo``, ``ghi`` are ``f - level`` at its
    ends, of opposite signs (one may be 0). Returns the coordinate along the edge of a point
    whose distance to a sign change of ``f - level`` is at most ``tol``: the end of the final
    bracket with the smaller ``|f - level|`` (after at most ``max_iter`` steps).
    """
    a, b = lo.astype(np.float64).copy(), hi.astype(np.float64).copy()
    fa, fb = glo.astype(np.float64).copy(), ghi.astype(np.float64).copy()
    side = np.zeros(a.shape, dtype=np.int8)  # which end was kept last time (Illinois)
    active = (np.abs(b - a) > tol) & (fa != 0) & (fb != 0)
    for _ in range(max_iter):
        idx = np.flatnonzero(active)
        if idx.size == 0:
            break
        A, B, FA, FB = a[idx], b[idx], fa[idx], fb[idx]
        with np.errstate(invalid="ignore", divide="ignore"):
            c = B - FB * (B - A) / (FB - FA)
        w = B - A
        # Keep at least tol/2 from either end (so the bracket shrinks by that much at least),
        # and fall back to bisection if the secant point is not a number.
        step = np.sign(w) * 0.5 * tol
        c = np.where(np.isfinite(c), c, 0.5 * (A + B))
        lo_c, hi_c = np.minimum(A + step, B - step), np.maximum(A + step, B - step)
        c = np.clip(c, lo_c, hi_c)
        ax = axis[idx]
        fx = fixed[idx]
        fc = _evaluate(f, np.where(ax == 0, c, fx), np.where(ax == 0, fx, c)) - level
        bad = ~np.isfinite(fc)
        if bad.any():
            raise ValueError(
                f"the function is not finite at {int(bad.sum())} point(s) on "
                f"cell edges crossing the level set (e.g. at "
                f"{shown(float(c[bad][0]))} along axis {int(ax[bad][0])})"
            )
        same_as_b = np.sign(fc) == np.sign(FB)
        # c replaces b where it has b's sign, else a; halve the other end's value if that end
        # was kept the previous time too (Illinois).
        keep_a = same_as_b
        sd = side[idx]
        FA = np.where(keep_a & (sd == 1), 0.5 * FA, FA)
        FB = np.where(~keep_a & (sd == -1), 0.5 * FB, FB)
        A = np.where(keep_a, A, c)
        FA = np.where(keep_a, FA, fc)
        B = np.where(keep_a, c, B)
        FB = np.where(keep_a, fc, FB)
        side[idx] = np.where(keep_a, 1, -1)
        a[idx], b[idx], fa[idx], fb[idx] = A, B, FA, FB
        active[idx] = (np.abs(B - A) > tol) & (fc != 0)
    # The halved values are not the function's: compare the true ones at both ends.
    ga = _evaluate(f, np.where(axis == 0, a, fixed), np.where(axis == 0, fixed, a)) - level
    gb = _evaluate(f, np.where(axis == 0, b, fixed), np.where(axis == 0, fixed, b)) - level
    return np.where(np.abs(ga) <= np.abs(gb), a, b)


def _check_resolution(resolution: Any) -> tuple:
    if isinstance(resolution, (int, np.integer)) and not isinstance(resolution, bool):
        resolution = (resolution, resolution)
    try:
        nx, ny = (int(abs(complex(r))) if isinstance(r, complex) else int(r) for r in resolution)
    except (TypeError, ValueError):
        raise TypeError(
            f"resolution must be a node count or a pair of them, got resolution={shown(resolution)}"
        ) from None
    if nx < 2 or ny < 2:
        raise ValueError(
            f"resolution needs at least 2 nodes per axis, got resolution={shown(resolution)}"
        )
    return nx, ny


def contours(
    f: Callable,
    level: float = 0.0,
    bounds: ArrayLike = ((-2, 2), (-2, 2)),
    resolution: Any = (256, 256),
    tol: float = 1e-12,
    refine: bool = True,
) -> list[Contour]:
    """The level set ``f = level`` inside ``bounds`` as polylines.

    ``f`` is any fastsdf SDF, a :class:`fastsdf.fields.grid.GridSDF`, or a callable ``f(x, y)`` on
    arrays. It is sampled on ``resolution = (nx, ny)`` nodes spanning ``bounds`` (both ends
    included); marching squares finds the crossings and their connections, and each crossing
    is refined on ``f`` itself to ``tol`` (``refine=False`` keeps the linear interpolation of
    the samples, as scikit-image does). Returns :class:`Contour` s: closed loops for level
    sets inside ``bounds``, open polylines ending on its edges; the region where
    ``f < level`` lies on the left of each. Features smaller than a cell may be missed, as in
    every sampling method.
    """
    (x0, x1), (y0, y1) = check_bounds(bounds)
    nx, ny = _check_resolution(resolution)
    if not (isinstance(level, (int, float, np.integer, np.floating)) and math.isfinite(level)):
        raise ValueError(f"level must be a finite number, got level={shown(level)}")
    if not (isinstance(tol, (int, float)) and tol > 0):
        raise ValueError(f"tol must be a positive number, got tol={shown(tol)}")
    level = float(level)
    xs, ys = np.linspace(x0, x1, nx), np.linspace(y0, y1, ny)
    X, Y = np.meshgrid(xs, ys, indexing="ij")
    v = _evaluate(f, X, Y) - level
    if not np.isfinite(v).all():
        raise ValueError("the function is not finite at every sample of the grid")
    px, py = _crossings(f, xs, ys, v, level, tol, refine)
    return _chains(_successors(f, xs, ys, v < 0, level), px, py)


def _crossings(
    f: Callable,
    xs: np.ndarray,
    ys: np.ndarray,
    v: np.ndarray,
    level: float,
    tol: float,
    refine: bool,
) -> tuple[np.ndarray, np.ndarray]:
    """``(px, py)``: the point where ``f = level`` crosses each edge of the grid of nodes
    ``xs`` x ``ys`` whose values ``v`` (``f - level``) change sign there (NaN at the other
    edges); linearly interpolated (scikit-image's answer), then refined on ``f`` to ``tol``.
    Horizontal edge (i, j), nodes (i, j)-(i+1, j), has id ``i*ny + j``; vertical edge (i, j),
    nodes (i, j)-(i, j+1), id ``H + i*(ny-1) + j`` with ``H = (nx - 1) ny``."""
    nx, ny = v.shape
    inside = v < 0
    H = (nx - 1) * ny
    px = np.full(H + nx * (ny - 1), np.nan)
    py = np.full(px.size, np.nan)
    hi_, hj_ = np.nonzero(inside[:-1, :] != inside[1:, :])
    vi_, vj_ = np.nonzero(inside[:, :-1] != inside[:, 1:])
    h_ids = hi_ * ny + hj_
    v_ids = H + vi_ * (ny - 1) + vj_
    ga, gb = v[hi_, hj_], v[hi_ + 1, hj_]
    px[h_ids] = xs[hi_] + ga / (ga - gb) * (xs[hi_ + 1] - xs[hi_])
    py[h_ids] = ys[hj_]
    ga2, gb2 = v[vi_, vj_], v[vi_, vj_ + 1]
    px[v_ids] = xs[vi_]
    py[v_ids] = ys[vj_] + ga2 / (ga2 - gb2) * (ys[vj_ + 1] - ys[vj_])
    if refine and (h_ids.size or v_ids.size):
        fixed = np.concatenate([ys[hj_], xs[vi_]])
        lo = np.concatenate([xs[hi_], ys[vj_]])
        hi = np.concatenate([xs[hi_ + 1], ys[vj_ + 1]])
        axis = np.concatenate([np.zeros(h_ids.size, np.int8), np.ones(v_ids.size, np.int8)])
        roots = refine_crossings(
            f, fixed, lo, hi, np.concatenate([ga, ga2]), np.concatenate([gb, gb2]), axis, level, tol
        )
        px[h_ids] = roots[: h_ids.size]
        py[v_ids] = roots[h_ids.size :]
    return px, py


def _successors(
    f: Callable, xs: np.ndarray, ys: np.ndarray, inside: np.ndarray, level: float
) -> np.ndarray:
    """For each edge id (see :func:`_crossings`) the id of the next crossing along the level
    set, the region ``f < level`` (``inside``, at the nodes) on its left; -1 for none."""
    nx, ny = inside.shape
    H = (nx - 1) * ny
    # Cells with crossings; their four corners' phases in CCW order (0: (i, j), 1: (i+1, j),
    # 2: (i+1, j+1), 3: (i, j+1)) and the ids of their edges e0..e3 (bottom, right, top,
    # left: edge k runs from corner k to corner k+1 counter-clockwise).
    c = [inside[:-1, :-1], inside[1:, :-1], inside[1:, 1:], inside[:-1, 1:]]
    mixed = ~((c[0] == c[1]) & (c[1] == c[2]) & (c[2] == c[3]))
    ci, cj = np.nonzero(mixed)
    corners = np.stack([cc[ci, cj] for cc in c], axis=1)
    edges = np.stack(
        [ci * ny + cj, H + (ci + 1) * (ny - 1) + cj, ci * ny + cj + 1, H + ci * (ny - 1) + cj],
        axis=1,
    )
    saddle = (corners[:, 0] == corners[:, 2]) & (corners[:, 1] == corners[:, 3])
    centre_inside = np.zeros(ci.size, dtype=bool)
    if saddle.any():
        si = np.flatnonzero(saddle)
        cx = 0.5 * (xs[ci[si]] + xs[ci[si] + 1])
        cy = 0.5 * (ys[cj[si]] + ys[cj[si] + 1])
        centre_inside[si] = _evaluate(f, cx, cy) - level < 0
    # Segments: along the cell's boundary counter-clockwise, an edge from an inside corner to
    # an outside one is an exit, the reverse an entry. Each exit joins the entry before it
    # (cutting off an inside corner), or in a saddle whose centre is inside, the entry after
    # it (cutting off an outside corner); the inside then lies on the segment's left.
    nxt = np.full(H + nx * (ny - 1), -1, dtype=np.int64)
    for k in range(4):
        exit_k = corners[:, k] & ~corners[:, (k + 1) % 4]
        if not exit_k.any():
            continue
        rows = np.flatnonzero(exit_k)
        before = np.full(rows.size, -1)
        after = np.full(rows.size, -1)
        for step in (1, 2, 3):
            e = (k - step) % 4
            is_entry = ~corners[rows, e] & corners[rows, (e + 1) % 4]
            before = np.where((before < 0) & is_entry, e, before)
            e = (k + step) % 4
            is_entry = ~corners[rows, e] & corners[rows, (e + 1) % 4]
            after = np.where((after < 0) & is_entry, e, after)
        partner = np.where(saddle[rows] & centre_inside[rows], after, before)
        nxt[edges[rows, k]] = edges[rows, partner]
    return nxt


def _chains(nxt: np.ndarray, px: np.ndarray, py: np.ndarray) -> list[Contour]:
    """Follow the successor links into open polylines (from ids nobody points to) and closed
    loops (the rest)."""
    has_next = np.flatnonzero(nxt >= 0)
    pointed = np.zeros(nxt.size, dtype=bool)
    pointed[nxt[has_next]] = True
    starts = [int(s) for s in has_next if not pointed[s]]
    seen = np.zeros(nxt.size, dtype=bool)
    out = []
    nxt_l = nxt.tolist()
    for s in starts:
        ids = [s]
        seen[s] = True
        k = nxt_l[s]
        while k >= 0:
            ids.append(k)
            seen[k] = True
            k = nxt_l[k]
        out.append(Contour(np.stack([px[ids], py[ids]], axis=1), False))
    for s in has_next.tolist():
        if seen[s]:
            continue
        ids = [s]
        seen[s] = True
        k = nxt_l[s]
        while k != s:
            ids.append(k)
            seen[k] = True
            k = nxt_l[k]
        out.append(Contour(np.stack([px[ids], py[ids]], axis=1), True))
    return out
