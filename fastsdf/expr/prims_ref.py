"""Independent NumPy references for the compiled primitives of :mod:`fastsdf.backends.kernel.prims`.

They use different methods from the compiled code, so that agreement means something:

* ellipse: a dense search over the parametric angle of the first quadrant followed by a
  golden-section refinement (no secular equation, no Newton);
* polygon: the minimum over the distances to the vertices and to the interiors of the edges
  (perpendicular distance where the foot lies on the edge), with the inside test by winding
  number (a sum of signed angles, not a crossing count);
* outline: the stationary points of the squared distance to each quadratic segment as the
  eigenvalues of the cubic's companion matrix (no closed form, no Newton), the sign by counting
  the roots of ``y(t) = v`` in [0, 1) with the quadratic formula (no monotone split).

``evaluate(kind, data, u, v, constants)`` returns ``(d, dd/du, dd/dv)`` as arrays. These are
slow (O(points x samples)); they exist for testing.
"""

from collections.abc import Sequence
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

__all__ = ["evaluate", "ellipse", "outline", "polygon"]

_GOLDEN = (np.sqrt(5.0) - 1.0) / 2.0


def evaluate(
    kind: str, data: Any, u: ArrayLike, v: ArrayLike, constants: Sequence[float]
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(d, dd/du, dd/dv)`` of the primitive ``kind`` (with its ``data`` and ``constants``, as in
    a ``prim`` node) at local coordinates ``(u, v)``."""
    ub, vb = np.broadcast_arrays(np.asarray(u, dtype=np.float64), np.asarray(v, dtype=np.float64))
    if kind == "ellipse":
        a, b = constants  # the semi-axes
        return ellipse(ub, vb, a, b)
    if kind == "polygon":
        return polygon(ub, vb, np.asarray(data, dtype=np.float64))
    if kind == "outline":
        return outline(ub, vb, np.asarray(data, dtype=np.float64))
    raise NotImplementedError(kind)


def ellipse(
    u: np.ndarray, v: np.ndarray, a: float, b: float, samples: int = 4097, chunk: int = 256
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Signed distance to the ellipse ``(u/a)**2 + (v/b)**2 = 1`` and its gradient (the outward
    unit normal at the closest point) by search over the angle ``t`` of ``(a cos t, b sin t)``."""
    shape = u.shape
    y0, y1 = np.abs(u).ravel(), np.abs(v).ravel()
    d = np.empty(y0.size)
    t_best = np.empty(y0.size)
    grid = np.linspace(0.0, np.pi / 2, samples)
    step = grid[1]
    cg, sg = a * np.cos(grid), b * np.sin(grid)
    for s in range(0, y0.size, chunk):
        p0, p1 = y0[s : s + chunk, None], y1[s : s + chunk, None]
        i = np.argmin((p0 - cg) ** 2 + (p1 - sg) ** 2, axis=1)
        lo = np.clip(grid[i] - step, 0.0, np.pi / 2)
        hi = np.clip(grid[i] + step, 0.0, np.pi / 2)
        p0, p1 = p0[:, 0], p1[:, 0]

        def dist2(t):  # called only in this iteration of the loop
            return (p0 - a * np.cos(t)) ** 2 + (p1 - b * np.sin(t)) ** 2  # noqa: B023

        for _ in range(90):  # golden section: the bracket shrinks to rounding
            m1 = hi - _GOLDEN * (hi - lo)
            m2 = lo + _GOLDEN * (hi - lo)
            left = dist2(m1) <= dist2(m2)
            hi = np.where(left, m2, hi)
            lo = np.where(left, lo, m1)
        t = 0.5 * (lo + hi)
        # Polish t with Newton steps on the stationarity condition (the bracket only pins it
        # to about sqrt(eps) of the flat minimum); a step is kept where it stays near the
        # bracket.
        for _ in range(4):
            c, sn = np.cos(t), np.sin(t)
            f = (a * a - b * b) * sn * c - p0 * a * sn + p1 * b * c
            df = (a * a - b * b) * (c * c - sn * sn) - p0 * a * c - p1 * b * sn
            with np.errstate(divide="ignore", invalid="ignore"):
                tn = t - f / df
            ok = (tn >= lo - step) & (tn <= hi + step) & np.isfinite(tn)
            t = np.where(ok, np.clip(tn, 0.0, np.pi / 2), t)
        # The ends of the quadrant (the vertices) are candidates too.
        cands = np.stack([t, np.zeros_like(t), np.full_like(t, np.pi / 2)])
        dc = np.stack([dist2(c) for c in cands])
        k = np.argmin(dc, axis=0)
        t_best[s : s + chunk] = cands[k, np.arange(t.size)]
        d[s : s + chunk] = np.sqrt(dc[k, np.arange(t.size)])
    inside = (y0 / a) ** 2 + (y1 / b) ** 2 < 1.0
    d = np.where(inside, -d, d)
    # Gradient: the unit vector from the closest point q (away from it outside, towards it
    # inside), or, on and very near the boundary, the normal (x0 / a**2, x1 / b**2) at q.
    q0, q1 = a * np.cos(t_best), b * np.sin(t_best)
    n0, n1 = q0 / (a * a), q1 / (b * b)
    nn = np.hypot(n0, n1)
    dist = np.abs(d)
    far = dist > 1e-9 * max(a, b)
    with np.errstate(invalid="ignore", divide="ignore"):
        n0 = np.where(far, np.sign(d) * (y0 - q0) / dist, n0 / nn)
        n1 = np.where(far, np.sign(d) * (y1 - q1) / dist, n1 / nn)
    gu = np.where(u.ravel() >= 0, 1.0, -1.0) * n0
    gv = np.where(v.ravel() >= 0, 1.0, -1.0) * n1
    return d.reshape(shape), gu.reshape(shape), gv.reshape(shape)


def polygon(
    u: np.ndarray, v: np.ndarray, verts: np.ndarray, chunk: int = 256
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Signed distance to the polygon with vertices ``verts`` (either orientation) and its
    gradient, as the minimum of vertex and edge-interior distances, signed by winding number."""
    shape = u.shape
    pu, pv = u.ravel(), v.ravel()
    a = verts
    b = np.roll(verts, -1, axis=0)
    e = b - a
    elen = np.hypot(e[:, 0], e[:, 1])
    area2 = np.sum(a[:, 0] * b[:, 1] - b[:, 0] * a[:, 1])
    orient = 1.0 if area2 > 0 else -1.0
    out_n = orient * np.stack([e[:, 1], -e[:, 0]], -1) / elen[:, None]  # outward unit normals
    d = np.empty(pu.size)
    gu = np.empty(pu.size)
    gv = np.empty(pu.size)
    for s in range(0, pu.size, chunk):
        x, y = pu[s : s + chunk, None], pv[s : s + chunk, None]
        rx, ry = x - a[:, 0], y - a[:, 1]  # from each vertex
        vdist = np.hypot(rx, ry)
        along = (rx * e[:, 0] + ry * e[:, 1]) / elen  # foot position along the edge
        perp = rx * out_n[:, 0] + ry * out_n[:, 1]  # signed, + outside the edge
        on_edge = (along >= 0) & (along <= elen)
        edist = np.where(on_edge, np.abs(perp), np.inf)
        # winding number: sum of the signed angles subtended by the edges
        bx, by = x - b[:, 0], y - b[:, 1]
        ang = np.arctan2(rx * by - ry * bx, rx * bx + ry * by)
        inside = np.abs(ang.sum(axis=1)) > np.pi
        iv, ie = np.argmin(vdist, axis=1), np.argmin(edist, axis=1)
        rows = np.arange(x.shape[0])
        dv_, de_ = vdist[rows, iv], edist[rows, ie]
        use_edge = de_ < dv_
        dist = np.where(use_edge, de_, dv_)
        sign = np.where(inside, -1.0, 1.0)
        # gradient: away from the closest point (outside), towards it (inside)
        with np.errstate(invalid="ignore", divide="ignore"):
            vgx, vgy = rx[rows, iv] / dv_, ry[rows, iv] / dv_
        # nearest point inside an edge: the edge's outward normal on both sides (and on it)
        gx = np.where(use_edge, out_n[ie, 0], sign * vgx)
        gy = np.where(use_edge, out_n[ie, 1], sign * vgy)
        zero = dist == 0
        gx = np.where(zero, out_n[ie, 0], gx)
        gy = np.where(zero, out_n[ie, 1], gy)
        d[s : s + chunk] = sign * dist
        gu[s : s + chunk] = gx
        gv[s : s + chunk] = gy
    return d.reshape(shape), gu.reshape(shape), gv.reshape(shape)


def outline(u: np.ndarray, v: np.ndarray, table: np.ndarray, chunk: int = 64) -> tuple:
    """Signed distance to the region bounded by the outline ``table`` (the layout of
    :func:`fastsdf.backends.kernel.prims.outline_vg`) and its gradient."""
    shape = u.shape
    pu, pv = u.ravel(), v.ravel()
    rows = table[1:]
    kind = rows[:, 0]
    p0, p1, p2 = rows[:, 1:3], rows[:, 3:5], rows[:, 5:7]
    p1 = np.where(kind[:, None] == 0, 0.5 * (p0 + p2), p1)  # a line as a flat quadratic
    a, b = p1 - p0, p0 - 2 * p1 + p2
    nonzero = table[0, 0] == 2.0
    d = np.empty(pu.size)
    gu = np.empty(pu.size)
    gv = np.empty(pu.size)
    ts = np.linspace(0.0, 1.0, 3)
    for s in range(0, pu.size, chunk):
        x, y = pu[s : s + chunk, None], pv[s : s + chunk, None]
        dx, dy = p0[:, 0] - x, p0[:, 1] - y  # (points, segments)
        bb = np.broadcast_to(b[:, 0] ** 2 + b[:, 1] ** 2, dx.shape)
        ab = np.broadcast_to(a[:, 0] * b[:, 0] + a[:, 1] * b[:, 1], dx.shape)
        aa = np.broadcast_to(a[:, 0] ** 2 + a[:, 1] ** 2, dx.shape)
        db = dx * b[:, 0] + dy * b[:, 1]
        da = dx * a[:, 0] + dy * a[:, 1]
        # candidates: the ends, the line foot (flat curves), the cubic's roots
        cands = [np.broadcast_to(t, dx.shape) for t in ts[[0, 2]]]
        with np.errstate(all="ignore"):
            cands.append(np.clip(-da / (2 * aa), 0, 1))
            flat = bb <= 1e-20 * aa
            c2 = np.where(flat, 0.0, 3 * ab / bb)
            c1 = np.where(flat, 0.0, (2 * aa + db) / bb)
            c0 = np.where(flat, 0.0, da / bb)
        comp = np.zeros(dx.shape + (3, 3))
        comp[..., 0, 0], comp[..., 0, 1], comp[..., 0, 2] = -c2, -c1, -c0
        comp[..., 1, 0] = comp[..., 2, 1] = 1.0
        roots = np.linalg.eigvals(comp).real
        cands += [np.clip(roots[..., k], 0, 1) for k in range(3)]
        T = np.stack(cands, -1)  # (points, segments, 6)
        qx = (
            (1 - T) ** 2 * p0[:, 0, None] + 2 * T * (1 - T) * p1[:, 0, None] + T**2 * p2[:, 0, None]
        )
        qy = (
            (1 - T) ** 2 * p0[:, 1, None] + 2 * T * (1 - T) * p1[:, 1, None] + T**2 * p2[:, 1, None]
        )
        dist2 = (x[..., None] - qx) ** 2 + (y[..., None] - qy) ** 2
        flat_idx = dist2.reshape(dist2.shape[0], -1).argmin(1)
        r = np.arange(dist2.shape[0])
        bx = qx.reshape(qx.shape[0], -1)[r, flat_idx]
        by = qy.reshape(qy.shape[0], -1)[r, flat_idx]
        dist = np.hypot(x[:, 0] - bx, y[:, 0] - by)
        # winding, by the kernel's rule (rows are y-monotone): a row whose ends lie on either
        # side of the height v (half-open: an end at v counts as below, so a ray through a
        # shared end counts it once) crosses the ray towards +x where x(t) > u, in the
        # direction of y2 - y0
        y0, y1, y2 = p0[:, 1], p1[:, 1], p2[:, 1]
        cross = (y0 > y) != (y2 > y)  # (points, segments)
        qa = np.broadcast_to(y0 - 2 * y1 + y2, dx.shape)
        qb = np.broadcast_to(2 * (y1 - y0), dx.shape)
        qc = y0 - y
        with np.errstate(all="ignore"):
            lin = np.abs(qa) <= 1e-14 * (np.abs(qb) + np.abs(qc))
            disc = np.sqrt(np.maximum(qb * qb - 4 * qa * qc, 0.0))
            qq = -0.5 * (qb + np.copysign(disc, qb))
            t1 = qq / qa
            t2 = np.where(qq != 0, qc / qq, t1)
            t = np.where((t1 >= -1e-12) & (t1 <= 1 + 1e-12), t1, t2)
            t = np.where(lin, np.where(qb != 0, -qc / qb, 0.0), t)
        t = np.clip(np.nan_to_num(t), 0.0, 1.0)
        xt = (1 - t) ** 2 * p0[:, 0] + 2 * t * (1 - t) * p1[:, 0] + t**2 * p2[:, 0]
        hit = cross & (xt > x)
        wind = np.sum(np.where(hit, np.sign(y2 - y0), 0.0), axis=1)
        inside = (wind != 0) if nonzero else (np.abs(wind) % 2 == 1)
        sign = np.where(inside, -1.0, 1.0)
        with np.errstate(invalid="ignore", divide="ignore"):
            d[s : s + chunk] = sign * dist
            gu[s : s + chunk] = sign * (x[:, 0] - bx) / dist
            gv[s : s + chunk] = sign * (y[:, 0] - by) / dist
    return d.reshape(shape), gu.reshape(shape), gv.reshape(shape)
