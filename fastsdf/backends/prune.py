"""Pruning per tile: evaluate only the operands of a chain that can matter near a point.

The generated kernels evaluate every loop over a constant table ("group": the same-shape
operands of a ``min``/``max``/``smin``/``smax`` chain, see :mod:`fastsdf.backends.lower`)
over a list of rows given as data. A :class:`PrunePlan` covers a rectangle with tiles and, from
sound interval bounds of every operand over every tile (:mod:`fastsdf.expr.interval`), keeps per
tile only the rows that can matter:

* hard ``min``: operand ``i`` is dropped where ``lo_i > min_j hi_j`` (``j`` over every operand of
  the chain); it can never be the minimum (nor tie with it) in the tile, so value and gradient
  are bit-identical. ``max`` mirrors this.
* exponential ``smin`` with sharpness ``k``: every operand contributes, so pruning is
  approximate. Operands with ``lo_i >= H + log(n / expm1(k tol)) / k`` (``H = min_j hi_j``, ``n``
  operands) are dropped; their total weight changes the result by at most
  ``log1p(sum exp(-k (lo_i - H))) / k <= tol``. ``smax`` mirrors this. ``tol=None`` (default)
  is half an ulp of ``H``: identical in practice, and little is pruned unless ``k`` is large.

* polynomial blends of width ``k`` (quadratic, cubic; chains of the same ``k`` are left folds,
  never reordered): member ``i`` is dropped where ``lo_i > k + min_{j<i} hi_j`` (``j`` over
  the operands before it in the chain). The running value is then below ``a_i - k``, where the
  blend is exactly the running value, value and gradient: bit-identical.

Points are sorted by tile (a counting sort) and run through the scene's SIMD block functions
(:mod:`fastsdf.backends.kernel.simd`, driven by :func:`fastsdf.backends.kernel.drive.tiles_par`)
with each tile's row lists as data: pruning never recompiles anything. A tile's points fill whole
blocks of 512; the last few points of consecutive tiles share blocks, which run the union of those
tiles' lists (a superset of the rows that can matter visits them in the same order: the same bits).
"""

from __future__ import annotations

import math
import sys
import time
from typing import Any

import numpy as np
from llvmlite import ir
from numba import njit, types
from numba.core import cgutils
from numba.extending import intrinsic

from fastsdf.backends.kernel.cache import hashed_import
from fastsdf.expr.graph import gc_paused
from fastsdf.expr.interval import LIPSCHITZ_RULES, node_bounds
from fastsdf.expr.ops import OPS

__all__ = ["PrunePlan", "make_plan", "bin_points", "plan_header", "HEADER_SIZE", "call_vg_plan"]


class PrunePlan:
    """Row lists per tile for the loop groups of one compiled expression over one rectangle.

    ``act`` (int64) holds the kept rows; ``offs[t, g]:offs[t, g + 1]`` is group ``g``'s slice for
    tile ``t`` (row-major tiles: ``t = ty * nx + tx``). ``kept[g]`` is the number of rows kept per
    tile, ``sizes[g]`` the group's size, ``build_s`` the time to build the plan.
    """

    def __init__(
        self,
        bounds: tuple,
        nx: int,
        ny: int,
        act: np.ndarray,
        offs: np.ndarray,
        kept: list,
        sizes: list,
        build_s: float,
        tol: float | None,
    ):
        self.bounds, self.nx, self.ny = bounds, nx, ny
        self.act, self.offs, self.kept, self.sizes = act, offs, kept, sizes
        self.build_s, self.tol = build_s, tol

    @property
    def fraction(self) -> float:
        """Evaluated rows over all rows, averaged over tiles (1 = nothing pruned)."""
        total = sum(self.sizes)
        if not total:
            return 1.0
        return float(sum(k.sum() for k in self.kept) / (total * self.nx * self.ny))

    def report(self) -> dict:
        """A summary: tiles, bounds, operands, survivors per tile (mean, max), the fraction
        kept, build time (s) and tolerance."""
        per_tile = np.sum(self.kept, axis=0) if self.kept else np.zeros(self.nx * self.ny)
        return {
            "tiles": (self.nx, self.ny),
            "bounds": self.bounds,
            "operands": int(sum(self.sizes)),
            "survivors_mean": float(per_tile.mean()),
            "survivors_max": int(per_tile.max()),
            "fraction": self.fraction,
            "build_s": self.build_s,
            "tol": self.tol,
        }


def _tile_ranges(bounds, nx, ny):
    (x0, x1), (y0, y1) = bounds
    wx, wy = (x1 - x0) / nx, (y1 - y0) / ny
    ix, iy = np.meshgrid(np.arange(nx), np.arange(ny))  # row-major: t = iy * nx + ix
    ix, iy = ix.ravel().astype(np.float64), iy.ravel().astype(np.float64)
    # Tiles overlap by a sliver so that a point binned across a rounding edge is still inside.
    ex, ey = 1e-9 * (wx + abs(x0) + abs(x1)), 1e-9 * (wy + abs(y0) + abs(y1))
    return {
        "x": (x0 + ix * wx - ex, x0 + (ix + 1) * wx + ex),
        "y": (y0 + iy * wy - ey, y0 + (iy + 1) * wy + ey),
    }


#: Members bounded together (memory: about 100 arrays of members x tiles floats at once).
_MEMBER_CHUNK = 128


def _steps_bounds(group, ranges):
    """Bounds of every member of a group over every tile, in chunks of members."""
    M = len(group.members)
    parts = [
        _steps_bounds_chunk(
            group.steps,
            group.members[i : i + _MEMBER_CHUNK],
            group.rows[i : i + _MEMBER_CHUNK],
            ranges,
        )
        for i in range(0, M, _MEMBER_CHUNK)
    ]
    if len(parts) == 1:
        return parts[0]
    return np.concatenate([p[0] for p in parts]), np.concatenate([p[1] for p in parts])


def _per_member(steps: list) -> bool:
    """Whether a group's members must be bounded one by one: a compiled primitive with numeric
    arguments (an ellipse's axes), which its interval rule reads from the node itself. A
    polygon's only arguments are its coordinates (its vertices are the node's structure, the
    same in every member), so a group of them is bounded over the table like any template."""
    return any(node.op == "prim" and len(node.args) > 2 for node, _ in steps)


def _steps_bounds_chunk(steps, members, rows, ranges):
    """Bounds ``(lo, hi)`` of shape (members, tiles) of members of a group: the shared
    template is evaluated once on (members x tiles) arrays, the constants as columns."""
    if _per_member(steps):  # per-member constants in the reference
        out = [node_bounds(m, ranges) for m in members]
        return (
            np.stack([o[id(m)][0] for o, m in zip(out, members)]),
            np.stack([o[id(m)][1] for o, m in zip(out, members)]),
        )
    T = len(next(iter(ranges.values()))[0])
    hints = [LIPSCHITZ_RULES.get(m) for m in members]
    hint = max(hints) if all(h is not None for h in hints) else None
    lo, hi = _template_bounds(
        steps,
        [rows[:, j][:, None] for j in range(rows.shape[1])],
        {k: (lo[None, :], hi[None, :]) for k, (lo, hi) in ranges.items()},
        (1, T),
        hint,
    )
    M = len(members)
    return (np.broadcast_to(lo, (M, T)), np.broadcast_to(hi, (M, T)))


def _template_bounds(steps, cols, ranges, shape, hint):
    """Bounds ``(lo, hi)`` of a group's template with constants ``cols[j]`` over boxes
    ``ranges`` (arrays broadcasting together: (members, 1) columns against (1, tiles) boxes, or
    one entry per (member, tile) pair), intersected with the Lipschitz bound around each box's
    centre; ``hint``: a Lipschitz constant of the result known from the modelling layer (an
    array per entry, or a number, or None)."""
    centres = {k: 0.5 * (lo + hi) for k, (lo, hi) in ranges.items()}
    with np.errstate(all="ignore"):  # huge tiles: an infinite half-diagonal is sound
        half = np.sqrt(sum((0.5 * (hi - lo)) ** 2 for lo, hi in ranges.values()))
        scale = sum(np.abs(c) for c in centres.values()) + half
    lo_s, hi_s, c_s, L_s = [], [], [], []
    with np.errstate(all="ignore"):
        for i, (node, refs) in enumerate(steps):
            if node.op == "sym":
                lo, hi = ranges[node.attr]
                c, L = centres[node.attr], np.ones(shape)
            else:
                alo, ahi, ac, aL = [], [], [], []
                for kind, j in refs:
                    if kind == "c":
                        alo.append(cols[j]), ahi.append(cols[j]), ac.append(cols[j])
                        aL.append(np.zeros_like(cols[j]))
                    else:
                        alo.append(lo_s[j]), ahi.append(hi_s[j]), ac.append(c_s[j])
                        aL.append(L_s[j])
                spec = OPS[node.op]
                lo, hi = spec.interval(node, alo, ahi)
                lo = np.where(np.isnan(lo), -np.inf, lo)
                hi = np.where(np.isnan(hi), np.inf, hi)
                c = spec.np(node, ac, False)[0]
                L = (
                    spec.lipschitz(node, aL, alo, ahi)
                    if spec.lipschitz is not None
                    else np.full(np.broadcast(lo, hi).shape, np.inf)
                )
                L = np.where(np.isnan(L), np.inf, L)
                if i == len(steps) - 1 and hint is not None:
                    L = np.minimum(L, hint)
                r = L * half
                m = 1e-10 * (np.abs(c) + r + scale) + 1e-290
                ok = np.isfinite(c) & np.isfinite(r)
                lo = np.where(ok, np.maximum(lo, c - r - m), lo)
                hi = np.where(ok, np.minimum(hi, c + r + m), hi)
            lo_s.append(lo), hi_s.append(hi), c_s.append(c), L_s.append(L)
    return lo_s[-1], hi_s[-1]


def make_plan(groups: list, bounds: tuple, nx: int, ny: int, tol: float | None = None) -> PrunePlan:
    """The :class:`PrunePlan` of ``groups`` (a Program's,
    :attr:`fastsdf.backends.lower.Program.groups`) over ``bounds = ((x0, x1), (y0, y1))``
    cut into ``nx x ny`` tiles."""
    with gc_paused():  # a bulk pass (see fastsdf.expr.graph._GCPaused)
        return _make_plan(groups, bounds, nx, ny, tol)


def _make_plan(groups: list, bounds: tuple, nx: int, ny: int, tol: float | None) -> PrunePlan:
    t0 = time.perf_counter()
    ranges = _tile_ranges(bounds, nx, ny)
    T = nx * ny
    cache: dict = {}  # bounds of a left fold's members over every tile, found where needed

    def member_bounds(gi: int) -> tuple:
        if gi not in cache:
            cache[gi] = _steps_bounds(groups[gi], ranges)
        return cache[gi]

    chains: dict = {}
    for gi, g in enumerate(groups):
        chains.setdefault(id(g.chain), []).append(gi)
    keep: list[Any] = [None] * len(groups)  # (every slot is set below: an array per group)
    for gis in chains.values():
        if groups[gis[0]].op in ("qmin", "cmin"):
            for gi in gis:
                keep[gi] = _keep_ordered(groups, gi, member_bounds, ranges, T)
            continue
        for gi, kk in zip(gis, _keep_coarse_to_fine(groups, gis, ranges, nx, ny, tol)):
            keep[gi] = kk
    return _plan_of(keep, groups, bounds, nx, ny, time.perf_counter() - t0, tol)


def _plan_of(
    keep: list, groups: list, bounds: tuple, nx: int, ny: int, build_s: float, tol: float | None
) -> PrunePlan:
    """The row lists of the kept rows (``keep[g]``: (members, tiles) booleans)."""
    T = nx * ny
    sizes = [len(g.members) for g in groups]
    kept = [kk.sum(axis=0).astype(np.int64) for kk in keep]
    G = len(groups)
    offs = np.zeros((T, G + 1), dtype=np.int64)
    counts = np.stack(kept, axis=1) if G else np.zeros((T, 0), dtype=np.int64)  # (T, G)
    flat = np.cumsum(counts.ravel())
    offs[:, 1:] = flat.reshape(T, G)
    offs[1:, 0] = offs[:-1, G]
    act = np.empty(int(flat[-1]) if len(flat) else 0, dtype=np.int64)
    for gi, kk in enumerate(keep):
        for t in range(T):
            rows = np.flatnonzero(kk[:, t])
            act[offs[t, gi] : offs[t, gi + 1]] = rows
    return PrunePlan(bounds, nx, ny, act, offs, kept, sizes, build_s, tol)


#: Chains find their survivors coarse to fine, starting from the level of at most this many
#: tiles.
_COARSE_TOP_TILES = 16


def _levels(ranges, nx, ny):
    """Tile levels from the fine tiles (``s = 1``) up, each tile of level ``s`` covering
    ``s x s`` fine tiles (fewer at the far edges): ``[(s, lnx, lny, ranges)]``, coarsest first.
    A level tile's box is the smallest holding its fine tiles' boxes."""
    fx = (ranges["x"][0][:nx], ranges["x"][1][:nx])  # per column of fine tiles
    fy = (ranges["y"][0][::nx], ranges["y"][1][::nx])  # per row
    out = [(1, nx, ny, ranges)]
    s = 1
    while out[-1][1] * out[-1][2] > _COARSE_TOP_TILES:
        s *= 2
        lnx, lny = -(-nx // s), -(-ny // s)
        cx, cy = np.arange(0, nx, s), np.arange(0, ny, s)
        xlo, xhi = np.minimum.reduceat(fx[0], cx), np.maximum.reduceat(fx[1], cx)
        ylo, yhi = np.minimum.reduceat(fy[0], cy), np.maximum.reduceat(fy[1], cy)
        out.append(
            (
                s,
                lnx,
                lny,
                {
                    "x": (np.tile(xlo, lny), np.tile(xhi, lny)),
                    "y": (np.repeat(ylo, lnx), np.repeat(yhi, lnx)),
                },
            )
        )
    return out[::-1]


def _member_hints(members):
    """Per member, the Lipschitz hint that the dense bounds (chunks of ``_MEMBER_CHUNK``
    members) apply: the chunk's largest if every member of the chunk has one, else inf."""
    out = np.full(len(members), np.inf)
    for i in range(0, len(members), _MEMBER_CHUNK):
        hints = [LIPSCHITZ_RULES.get(m) for m in members[i : i + _MEMBER_CHUNK]]
        if all(h is not None for h in hints):
            out[i : i + _MEMBER_CHUNK] = max(hints)
    return out


def _pair_bounds(group, hints, mem, til, lranges):
    """Bounds ``(lo, hi)`` of member ``mem[p]`` over tile ``til[p]`` of a level, per pair p
    (pairs ordered by member): the same numbers as the dense (members x tiles) bounds."""
    steps, members = group.steps, group.members
    if not len(mem):
        return np.empty(0), np.empty(0)
    if _per_member(steps):
        lo, hi = np.empty(len(mem)), np.empty(len(mem))
        cuts = np.flatnonzero(np.diff(mem)) + 1
        for a, b in zip(np.r_[0, cuts], np.r_[cuts, len(mem)]):
            m = members[mem[a]]
            t = til[a:b]
            out = node_bounds(m, {k: (v[0][t], v[1][t]) for k, v in lranges.items()})[id(m)]
            lo[a:b], hi[a:b] = out
        return lo, hi
    rows = group.rows
    cols = [rows[mem, j] for j in range(rows.shape[1])]
    boxes = {k: (v[0][til], v[1][til]) for k, v in lranges.items()}
    lo, hi = _template_bounds(steps, cols, boxes, (len(mem),), hints[mem])
    return np.broadcast_to(lo, mem.shape), np.broadcast_to(hi, mem.shape)


def _keep_coarse_to_fine(groups, gis, ranges, nx, ny, tol):
    """Rows kept per tile, (members, tiles) per group, for a chain of ``min``, ``max``,
    ``smin`` or ``smax``. At the fine tiles the rule is: for ``min``, member ``i`` is dropped
    where its lower bound exceeds the smallest upper bound ``H`` of all operands over the tile
    (it can never be the minimum, nor tie with it); ``max`` mirrors this; the exponential blends
    drop members whose weights together change the value by at most ``tol`` (see the module
    docstring). The rule is applied coarse to fine: a member dropped over a level tile is
    dropped in every fine tile under it, and only the surviving (member, tile) pairs are
    bounded at the next level (bounds shrink with the box, so the kept rows are those of the
    rule applied at the fine tiles alone). For the exponential blends with the default
    tolerance (half an ulp of the chain's value), coarse levels use the smallest magnitude the
    fine tiles' value can have."""
    g0 = groups[gis[0]]
    n_ops = len(g0.others) + sum(len(groups[gi].members) for gi in gis)
    levels = _levels(ranges, nx, ny)
    hints = [_member_hints(groups[gi].members) for gi in gis]
    T0 = levels[0][1] * levels[0][2]
    pairs = [
        (
            np.repeat(np.arange(len(groups[gi].members)), T0),
            np.tile(np.arange(T0), len(groups[gi].members)),
        )
        for gi in gis
    ]
    for li, (_s, lnx, lny, lranges) in enumerate(levels):
        bounds = [
            _pair_bounds(groups[gi], h, mem, til, lranges)
            for gi, h, (mem, til) in zip(gis, hints, pairs)
        ]
        fine = li == len(levels) - 1
        pairs = _survivors(g0, n_ops, tol, fine, lnx * lny, lranges, bounds, pairs)
        if fine:
            break
        pairs = [_children(mem, til, lnx, levels[li + 1]) for mem, til in pairs]
    out = []
    for gi, (mem, til) in zip(gis, pairs):
        kk = np.zeros((len(groups[gi].members), nx * ny), dtype=bool)
        kk[mem, til] = True
        out.append(kk)
    return out


def _survivors(g0, n_ops, tol, fine, Tl, lranges, bounds, pairs):
    """The (member, tile) pairs of one level that the chain's rule keeps."""
    op, k = g0.op, g0.k
    lower = op in ("min", "smin")  # the chain's value is below every upper bound
    # H: the smallest upper bound (min, smin), or the largest lower bound (max, smax); F:
    # the other end over all operands (for the magnitude of the fine tiles' H)
    H = np.full(Tl, np.inf if lower else -np.inf)
    F = np.full(Tl, np.inf if lower else -np.inf)
    red = np.minimum if lower else np.maximum
    for (lo, hi), (_mem, til) in zip(bounds, pairs):
        red.at(H, til, hi if lower else lo)
        red.at(F, til, lo if lower else hi)
    for o in g0.others:
        olo, ohi = (o.attr, o.attr) if o.op == "const" else node_bounds(o, lranges)[id(o)]
        H = red(H, ohi if lower else olo)
        F = red(F, olo if lower else ohi)
    with np.errstate(all="ignore"):
        margin = _smooth_margin(op, k, tol, fine, n_ops, H, F, lower) if k else 0.0
        unknown = ~np.isfinite(H)
        out = []
        for (lo, hi), (mem, til) in zip(bounds, pairs):
            if op == "min":
                kp = lo <= H[til]
            elif op == "max":
                kp = hi >= H[til]
            elif op == "smin":
                kp = ~(lo >= (H + margin)[til])
            else:
                kp = ~(hi <= (H - margin)[til])
            kp |= unknown[til]
            out.append((mem[kp], til[kp]))
    return out


def _smooth_margin(op, k, tol, fine, n_ops, H, F, lower):
    """How far above ``H`` (below, for ``smax``) an exponential chain's member may be dropped:
    ``log(n / expm1(k tol)) / k``, its total weight then changes the value by at most ``tol``
    (default: half an ulp of the value, whose magnitude is bounded by ``H`` and ``F``)."""
    if tol is not None:
        t = np.full(H.shape, float(tol))
    elif fine:
        t = 0.5 * np.spacing(np.abs(H))
    else:  # the fine tiles' H lies between F and H: its smallest magnitude
        mag = (
            np.where(F > 0, F, np.where(H < 0, -H, 0.0))
            if lower
            else np.where(F < 0, -F, np.where(H > 0, H, 0.0))
        )
        t = 0.5 * np.spacing(mag)
    budget = np.expm1(k * t)
    return np.where(budget > 0, np.log(n_ops / budget) / k, np.inf)


def _children(mem, til, lnx, level):
    """The (member, tile) pairs' children at the next level, still ordered by member."""
    cnx, cny = level[1], level[2]
    tx, ty = til % lnx, til // lnx
    cm, ct = [], []
    for dy in (0, 1):
        for dx in (0, 1):
            cx, cy = 2 * tx + dx, 2 * ty + dy
            ok = (cx < cnx) & (cy < cny)
            cm.append(mem[ok])
            ct.append((cy * cnx + cx)[ok])
    cm, ct = np.concatenate(cm), np.concatenate(ct)
    order = np.argsort(cm, kind="stable")
    return cm[order], ct[order]


def _keep_ordered(groups, gi, member_bounds, ranges, T):
    """Rows kept per tile, shape (members, tiles), for a loop of a left fold of polynomial
    blends of width ``k``: the running value after any operands is at most the smallest of
    them, and the blend of ``r`` and ``a`` is exactly ``r`` (value and gradient) where
    ``a - r >= k``. So member ``i`` is dropped where its lower bound exceeds ``k`` plus the
    smallest upper bound of the operands before it in the chain (an outward margin covers the
    rounding of that sum): dropping it leaves every later running value unchanged."""
    g = groups[gi]
    k = float(g.k)
    prefix = np.full(T, np.inf)
    for kind, ref in g.before:
        if kind == "node":
            if ref.op == "const":
                hi = np.full(T, float(ref.attr))
            else:
                hi = node_bounds(ref, ranges)[id(ref)][1]
        else:
            hi = member_bounds(ref)[1].min(axis=0)
        prefix = np.minimum(prefix, np.where(np.isnan(hi), np.inf, hi))
    lo, hi = member_bounds(gi)
    hi = np.where(np.isnan(hi), np.inf, hi)
    # the smallest upper bound before each member: the chain's before, then earlier members
    before = np.minimum(
        prefix[None, :],
        np.vstack([np.full((1, T), np.inf), np.minimum.accumulate(hi, axis=0)[:-1]]),
    )
    with np.errstate(all="ignore"):
        limit = before + k
        limit = limit + 1e-12 * (np.abs(limit) + k) + 1e-300
        return ~(lo > limit) | ~np.isfinite(limit)


@njit(cache=True, nogil=True)
def _bin(xs, ys, x0, y0, sx, sy, nx, ny):
    n = xs.shape[0]
    tile = np.empty(n, dtype=np.int64)
    starts = np.zeros(nx * ny + 1, dtype=np.int64)
    for i in range(n):
        x, y = xs[i], ys[i]
        t = 0
        if math.isfinite(x) and math.isfinite(y):
            tx = min(max(int((x - x0) * sx), 0), nx - 1)
            ty = min(max(int((y - y0) * sy), 0), ny - 1)
            t = ty * nx + tx
        tile[i] = t
        starts[t + 1] += 1
    for t in range(nx * ny):
        starts[t + 1] += starts[t]
    fill = starts[:-1].copy()
    order = np.empty(n, dtype=np.int64)
    for i in range(n):
        t = tile[i]
        order[fill[t]] = i
        fill[t] += 1
    return order, starts


def bin_points(xs: np.ndarray, ys: np.ndarray, plan: PrunePlan) -> tuple:
    """``(order, starts)``: the points of tile ``t`` are ``order[starts[t]:starts[t + 1]]``
    (non-finite points go to tile 0, where the kernels give them NaN)."""
    (x0, x1), (y0, y1) = plan.bounds
    return _bin(xs, ys, x0, y0, plan.nx / (x1 - x0), plan.ny / (y1 - y0), plan.nx, plan.ny)


def snap_bounds(xs: np.ndarray, ys: np.ndarray) -> tuple[tuple[float, float], ...] | None:
    """A rectangle holding the finite points, snapped outward to a coarse grid so that calls on
    similar point sets share one plan. None if there are no finite points."""
    ok = np.isfinite(xs) & np.isfinite(ys)
    if not ok.any():
        return None
    x, y = xs[ok], ys[ok]
    return snap_rect(float(x.min()), float(x.max()), float(y.min()), float(y.max()))


def snap_rect(x0: float, x1: float, y0: float, y1: float) -> tuple[tuple[float, float], ...]:
    """The rectangle ``[x0, x1] x [y0, y1]`` snapped outward as :func:`snap_bounds` does."""
    out = []
    for lo, hi in ((x0, x1), (y0, y1)):
        span = max(hi - lo, 1e-300, 1e-12 * max(abs(lo), abs(hi)))
        step = 2.0 ** math.ceil(math.log2(span)) / 16
        a, b = math.floor(lo / step) * step, (math.floor(hi / step) + 1) * step
        out.append((a, b))
    return tuple(out)


# -- per-point queries (the particle step) -----------------------------------------------------
# A caller that evaluates one point at a time (the particle step, the exact fallback of a grid)
# calls a scene's C function ``void f(double x, double y, double *out, double *h)`` (see
# ``fastsdf.particles._exact_address``): ``h`` is a plan header, :func:`plan_header`, written in
# place so that its address stays valid while the plan changes. The function finds the point's
# tile and evaluates the scene's ``rows_vg`` over that tile's lists; points outside the plan's
# rectangle (or with no plan: ``h[7] == 0``) get the full lists.

#: Floats in a plan header: x0, x1, y0, y1, nx, ny, loops + 1, address of ``act``, of ``offs``.
HEADER_SIZE = 9


def plan_header(plan: PrunePlan | None, h: np.ndarray) -> None:
    """Write ``plan`` (None: no pruning) into the header ``h`` (float64, :data:`HEADER_SIZE`);
    the caller keeps ``plan`` alive while ``h`` refers to it."""
    h[:] = 0.0
    if plan is None:
        return
    (x0, x1), (y0, y1) = plan.bounds
    h[:7] = (x0, x1, y0, y1, plan.nx, plan.ny, plan.offs.shape[1])
    # h[7] != 0 marks a plan; with nothing kept anywhere no row is read: any address will do
    h[7] = float((plan.act if plan.act.size else plan.offs).ctypes.data)
    h[8] = float(plan.offs.ctypes.data)


@intrinsic
def _iptr(typingctx, address):
    """The int64 pointer at integer ``address``."""
    if not isinstance(address, types.Integer):
        return None
    sig = types.CPointer(types.int64)(address)

    def codegen(context, builder, signature, args):
        return builder.inttoptr(args[0], ir.IntType(64).as_pointer())

    return sig, codegen


@intrinsic
def call_vg_plan(
    typingctx: object,
    address: types.Type,
    x: types.Type,
    y: types.Type,
    header: types.Type,
) -> tuple | None:
    """``(d, dd/dx, dd/dy)`` from the C function ``void f(double x, double y, double *out,
    double *h)`` at ``address`` with the plan header at integer address ``header``."""
    if not (isinstance(address, types.Integer) and isinstance(header, types.Integer)):
        return None
    sig = types.UniTuple(types.float64, 3)(address, types.float64, types.float64, header)

    def codegen(context, builder, signature, args):
        a, xv, yv, hv = args
        dbl = ir.DoubleType()
        fnty = ir.FunctionType(ir.VoidType(), [dbl, dbl, dbl.as_pointer(), dbl.as_pointer()])
        fp = builder.inttoptr(a, fnty.as_pointer())
        out = cgutils.alloca_once(builder, dbl, size=3)
        builder.call(fp, [xv, yv, out, builder.inttoptr(hv, dbl.as_pointer())])
        vals = [builder.load(builder.gep(out, [ir.Constant(ir.IntType(32), k)])) for k in range(3)]
        return context.make_tuple(builder, signature.return_type, vals)

    return sig, codegen


def exact_source(scene: str, rows: bool, version: str) -> str:
    """Source of the module defining ``exact_out``, the C function of the scene module
    ``scene`` for per-point callers (see above); ``rows``: the scene has loops over tables (its
    ``rows_vg`` is used inside the plan)."""
    body = ["    d, gx, gy = _exact(x, y)"]
    imports = [f"from {scene} import point_vg as _exact"]
    if rows:
        imports += [
            f"from {scene} import rows_vg as _rows",
            hashed_import("fastsdf.backends.prune", ["_iptr"]),
        ]
        body = [
            "    if h[7] != 0.0 and h[0] <= x <= h[1] and h[2] <= y <= h[3]:",
            "        nx, ny = int(h[4]), int(h[5])",
            "        tx = min(int((x - h[0]) * (nx / (h[1] - h[0]))), nx - 1)",
            "        ty = min(int((y - h[2]) * (ny / (h[3] - h[2]))), ny - 1)",
            "        t = ty * nx + tx",
            "        d, gx, gy = _rows(x, y, _iptr(int(h[7])), "
            "_iptr(int(h[8]) + 8 * t * int(h[6])))",
            "    else:",
            "        d, gx, gy = _exact(x, y)",
        ]
    return f'''"""Generated by fastsdf {version}: the exact SDF of a scene as a C function for
per-point callers (a grid's exact fallback, the particle step). Dependencies: {scene}."""
from numba import cfunc, types

{chr(10).join(imports)}


@cfunc(types.void(types.float64, types.float64, types.CPointer(types.float64),
                  types.CPointer(types.float64)), cache=True, error_model="numpy")
def exact_out(x, y, out, h):
{chr(10).join(body)}
    out[0] = d
    out[1] = gx
    out[2] = gy
'''


def _guard() -> None:
    # Generated modules call these dispatchers: every process reads and writes their numba
    # cache files sealed (see fastsdf.backends.kernel.cache.guard_module).
    from fastsdf.backends.kernel.cache import guard_module

    guard_module(sys.modules[__name__])


_guard()
