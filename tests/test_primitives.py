"""Issue 7: the new primitives against brute-force distances to densely sampled boundaries
(signs from independent point-in-shape tests), gradients against central differences, the
compiled primitives against their NumPy references, polynomial blends, exactness flags,
modifiers and bad input.

Each scene costs a numba compile, so every test checks several things on one compiled scene."""

import math

import numpy as np
import pytest
from conftest import brute_distance, central_gradient, rotate, value_of
from matplotlib.path import Path

import fastsdf as sdf
from fastsdf.expr.graph import Symbol, evaluate_numpy, substitute, sym_abs, sym_cmin, sym_qmin

TF = (0.4, (0.3, -0.2))  # a transform every primitive is also built under


# ---------------------------------------------------------------------------------------------
# Boundary samplers and inside tests, in the primitive's local frame.


def _polyline(vertices, closed=True, step=2e-4):
    v = np.asarray(vertices, dtype=float)
    if closed:
        v = np.vstack([v, v[:1]])
    out = []
    for a, b in zip(v[:-1], v[1:]):
        n = max(2, int(np.hypot(*(b - a)) / step) + 1)
        out.append(a + np.linspace(0, 1, n)[:, None] * (b - a))
    return np.concatenate(out)


def _arc_points(c, r, t0, t1, step=2e-4):
    n = max(2, int(abs(t1 - t0) * r / step) + 1)
    t = np.linspace(t0, t1, n)
    return np.stack([c[0] + r * np.cos(t), c[1] + r * np.sin(t)], -1)


def _path_inside(boundary):
    path = Path(boundary)
    return lambda p: path.contains_points(p)


def _seg_dist(p, a, b):
    a, b = np.asarray(a, float), np.asarray(b, float)
    e = b - a
    ee = e @ e
    t = np.clip(((p - a) @ e) / ee, 0, 1) if ee > 0 else np.zeros(len(p))
    return np.hypot(*(p - a - t[:, None] * e).T)


def _rounded_box_outline(minc, maxc, r):
    (x0, y0), (x1, y1) = minc, maxc
    ur, ul, ll, lr = r
    parts = []
    for rad, (cx, cy), (sx, sy), t0 in [
        (ur, (x1, y1), (-1, -1), 0.0),
        (ul, (x0, y1), (1, -1), 0.5),
        (ll, (x0, y0), (1, 1), 1.0),
        (lr, (x1, y0), (-1, 1), 1.5),
    ]:
        if rad:
            parts.append(
                _arc_points((cx + sx * rad, cy + sy * rad), rad, t0 * np.pi, (t0 + 0.5) * np.pi)
            )
        else:
            parts.append(np.array([[cx, cy]]))
    return _polyline(np.concatenate(parts))


def _case(name):
    """(builder, boundary in local frame, inside test in local frame, local extent)."""
    if name == "segment":
        a, b = (-0.5, -0.2), (0.7, 0.4)
        return (
            lambda: sdf.Segment(a, b),
            _polyline([a, b], closed=False),
            lambda p: np.zeros(len(p), bool),
            1.0,
        )
    if name == "segment_zero_length":
        a = (0.3, -0.1)
        return (lambda: sdf.Segment(a, a), np.array([a]), lambda p: np.zeros(len(p), bool), 0.5)
    if name == "capsule":
        a, b, r = np.array([-0.5, -0.2]), np.array([0.7, 0.4]), 0.25
        n = np.array([-(b - a)[1], (b - a)[0]]) / np.hypot(*(b - a)) * r
        cand = np.concatenate(
            [
                _arc_points(a, r, 0, 2 * np.pi),
                _arc_points(b, r, 0, 2 * np.pi),
                _polyline([a + n, b + n], False),
                _polyline([a - n, b - n], False),
            ]
        )
        boundary = cand[_seg_dist(cand, a, b) > r - 1e-9]
        return (lambda: sdf.Capsule(a, b, r), boundary, lambda p: _seg_dist(p, a, b) < r, 1.0)
    if name == "rounded_box":
        minc, maxc, r = (-0.8, -0.5), (0.6, 0.7), (0.1, 0.3, 0.0, 0.6)  # 0.6 = half the width
        outline = _rounded_box_outline(minc, maxc, r)
        return (lambda: sdf.RoundedBox(minc, maxc, r), outline, _path_inside(outline), 1.0)
    if name == "oriented_box":
        a, b, t = np.array([-0.8, -0.5]), np.array([0.6, 0.7]), 0.3
        n = np.array([-(b - a)[1], (b - a)[0]]) / np.hypot(*(b - a)) * t / 2
        outline = _polyline([a - n, b - n, b + n, a + n])
        return (lambda: sdf.OrientedBox(a, b, t), outline, _path_inside(outline), 1.0)
    if name in ("triangle", "triangle_cw"):
        v = [(-0.8, -0.5), (0.9, -1.0), (0.6, 0.7)]
        v = v[::-1] if name == "triangle_cw" else v
        outline = _polyline(v)
        return (lambda: sdf.Triangle(*v), outline, _path_inside(outline), 1.0)
    if name == "equilateral_triangle":
        c, r = (0.1, 0.2), 0.9
        t = np.pi / 2 + 2 * np.pi * np.arange(3) / 3
        outline = _polyline(np.stack([c[0] + r * np.cos(t), c[1] + r * np.sin(t)], -1))
        return (lambda: sdf.EquilateralTriangle(c, r), outline, _path_inside(outline), 1.0)
    if name == "regular_polygon":
        c, r, n = (0.1, 0.2), 0.9, 7
        t = np.pi / 2 + 2 * np.pi * np.arange(n) / n
        outline = _polyline(np.stack([c[0] + r * np.cos(t), c[1] + r * np.sin(t)], -1))
        return (lambda: sdf.RegularPolygon(c, r, n), outline, _path_inside(outline), 1.0)
    if name == "polygon_concave_collinear":
        # concave, clockwise, with extra vertices on two edges (collinear points)
        v = [(0, 0), (0, 1), (0.5, 0.2), (1, 1), (1, 0.5), (1, 0), (0.4, 0), (0.2, 0)]
        outline = _polyline(v)
        return (lambda: sdf.Polygon(v), outline, _path_inside(outline), 1.0)
    if name == "star":
        c, r, ri, n = (0.0, 0.1), 1.0, 0.4, 5
        t = np.pi / 2 + np.pi * np.arange(2 * n) / n
        rr = np.where(np.arange(2 * n) % 2 == 0, r, ri)
        outline = _polyline(np.stack([c[0] + rr * np.cos(t), c[1] + rr * np.sin(t)], -1))
        return (lambda: sdf.Star(c, r, n, ri), outline, _path_inside(outline), 1.0)
    if name.startswith("ellipse"):
        c, ax = {
            "ellipse": ((0.1, -0.1), (1.0, 0.4)),
            "ellipse_circle": ((0.1, -0.1), (0.7, 0.7)),
            "ellipse_thin": ((0.0, 0.1), (1.0, 1e-3)),
            "ellipse_thin_y": ((0.0, 0.1), (1e-3, 1.0)),
        }[name]
        t = np.linspace(0, 2 * np.pi, 100001)
        pts = np.stack([c[0] + ax[0] * np.cos(t), c[1] + ax[1] * np.sin(t)], -1)

        def inside(p):
            return ((p[:, 0] - c[0]) / ax[0]) ** 2 + ((p[:, 1] - c[1]) / ax[1]) ** 2 < 1

        return (lambda: sdf.Ellipse(c, ax), pts, inside, max(ax))
    if name == "ring":
        c, r, t = (0.1, 0.0), 0.7, 0.3
        outline = np.concatenate(
            [_arc_points(c, r - t / 2, 0, 2 * np.pi), _arc_points(c, r + t / 2, 0, 2 * np.pi)]
        )
        inside = lambda p: np.abs(np.hypot(*(p - c).T) - r) < t / 2
        return (lambda: sdf.Ring(c, r, t), outline, inside, 1.0)
    if name.startswith("arc"):
        c, r, ap, t = {
            "arc": ((0.1, 0.0), 0.8, 2.0, 0.2),
            "arc_wide": ((0.0, 0.0), 0.8, 5.5, 0.3),
            "arc_full": ((0.0, 0.1), 0.8, 2 * np.pi, 0.3),
        }[name]
        lo, hi = np.pi / 2 - ap / 2, np.pi / 2 + ap / 2
        ends = [np.array([c[0] + r * np.cos(e), c[1] + r * np.sin(e)]) for e in (lo, hi)]

        def to_center_line(p):  # distance to the arc of radius r (not the tube)
            q = p - c
            within = np.mod(np.arctan2(q[:, 1], q[:, 0]) - lo, 2 * np.pi) <= hi - lo + 1e-15
            to_ends = np.minimum(np.hypot(*(p - ends[0]).T), np.hypot(*(p - ends[1]).T))
            return np.where(within, np.abs(np.hypot(*q.T) - r), to_ends)

        cand = np.concatenate(
            [
                _arc_points(c, r + t / 2, lo, hi),
                _arc_points(c, r - t / 2, lo, hi),
                _arc_points(ends[0], t / 2, 0, 2 * np.pi),
                _arc_points(ends[1], t / 2, 0, 2 * np.pi),
            ]
        )
        keep = to_center_line(cand) > t / 2 - 1e-12
        return (lambda: sdf.Arc(c, r, ap, t), cand[keep], lambda p: to_center_line(p) < t / 2, 1.0)
    raise KeyError(name)


CASES = [
    "segment",
    "segment_zero_length",
    "capsule",
    "rounded_box",
    "oriented_box",
    "triangle",
    "triangle_cw",
    "equilateral_triangle",
    "regular_polygon",
    "polygon_concave_collinear",
    "star",
    "ellipse",
    "ellipse_circle",
    "ellipse_thin",
    "ellipse_thin_y",
    "ring",
    "arc",
    "arc_wide",
    "arc_full",
]


def _spacing(boundary):
    if len(boundary) < 2:
        return 0.0
    # the largest gap between a sample and its nearest other sample bounds the sampling error
    gaps = np.hypot(*np.diff(boundary, axis=0).T)
    return float(np.max(gaps[gaps < 0.05])) if np.any(gaps < 0.05) else 0.0


@pytest.mark.parametrize("name", CASES)
def test_primitive_is_exact_against_sampled_boundary(name):
    build, boundary, inside_fn, extent = _case(name)
    rng = np.random.default_rng(sum(map(ord, name)))
    idx = rng.integers(0, len(boundary), 300)
    local = np.concatenate(
        [
            rng.uniform(-1.5, 1.5, (300, 2)) * extent,  # around and inside
            boundary[idx] + rng.normal(0, 0.02, (300, 2)) * min(extent, 0.1),  # near the boundary
            rng.normal(0, 1, (30, 2)) * 50,  # far away
        ]
    )
    with sdf.transform(angle=TF[0], offset=TF[1]):
        f = build()
    assert f.exactness == "exact"
    world = rotate(local, TF[0]) + TF[1]
    d, g = f(*world.T, compute_gradient=True)
    brute = brute_distance(local, boundary)
    # sign from the independent inside test, away from the boundary
    clear = brute > 1e-6
    inside = inside_fn(local)
    assert np.all((d[clear] < 0) == inside[clear])
    if name.startswith("segment"):
        assert np.all(d >= 0)
    # a sampled boundary is never closer than the true one, and at most half a gap farther
    tol = 1e-12 * (1 + np.abs(brute))
    assert np.all(np.abs(d) <= brute + tol)
    np.testing.assert_allclose(np.abs(d), brute, atol=_spacing(boundary) / 2 + 1e-12, rtol=1e-12)
    # gradients: central differences where the function is smooth at the step's scale, unit
    # length everywhere (the segment's zero-length case included)
    near = np.abs(d) < 5 * extent
    fd1 = central_gradient(value_of(f), *world[near].T, h=1e-6)
    fd2 = central_gradient(value_of(f), *world[near].T, h=5e-7)
    smooth = np.all(np.abs(fd1 - fd2) < 1e-6, axis=1)
    assert smooth.mean() > 0.8
    np.testing.assert_allclose(g[near][smooth], fd1[smooth], atol=2e-5)
    np.testing.assert_allclose(np.hypot(*g.T), 1.0, atol=1e-12)
    # value-only kernel and the NumPy reference of the same graph
    np.testing.assert_array_equal(f(*world.T), d)
    ref, (rgx, rgy) = evaluate_numpy(
        f.f, {"x": world[:, 0], "y": world[:, 1]}, compute_gradient=True
    )
    np.testing.assert_allclose(d, ref, rtol=1e-12, atol=1e-12)
    grad_ok = np.hypot(g[:, 0] - rgx, g[:, 1] - rgy) < 1e-6
    assert grad_ok.mean() > 0.99  # (medial-axis ties may pick different closest points)


# ---------------------------------------------------------------------------------------------
# The compiled primitives (graph op "prim") against their NumPy references on hard points.


@pytest.mark.parametrize(
    "axes", [(1.0, 0.4), (0.4, 1.0), (1.0, 1e-3), (1e-6, 1.0), (1.0, 1.0), (2.0, 1.999999)]
)
def test_ellipse_hard_points_match_reference(axes):
    a, b = axes
    rng = np.random.default_rng(7)
    n = 200
    t = rng.uniform(0, 2 * np.pi, n)
    on = np.stack([a * np.cos(t), b * np.sin(t)], -1)
    p = np.concatenate(
        [
            on,
            on + rng.normal(0, 1e-9, (n, 2)),  # on / next to it
            np.stack([rng.uniform(-2, 2, n) * a, np.zeros(n)], -1),  # on the axes
            np.stack([np.zeros(n), rng.uniform(-2, 2, n) * b], -1),
            np.stack([rng.uniform(-1.2, 1.2, n) * a, rng.normal(0, 1e-13, n)], -1),  # just off them
            rng.uniform(-1, 1, (n, 2)) * 1e-4 * np.array([a, b]),  # near the centre
            rng.uniform(-3, 3, (n, 2)),
            [[0.0, 0.0], [1e6, -1e6], [a, 0.0], [0.0, -b]],
        ]
    )
    f = sdf.Ellipse((0, 0), axes)
    d, g = f(*p.T, compute_gradient=True)
    ref, (rgx, rgy) = evaluate_numpy(f.f, {"x": p[:, 0], "y": p[:, 1]}, compute_gradient=True)
    np.testing.assert_allclose(d, ref, rtol=1e-12, atol=1e-12 * max(axes))
    np.testing.assert_allclose(np.hypot(*g.T), 1.0, atol=1e-12)
    # away from the medial axis (the segment between the centres of curvature of the vertices)
    # the closest point is unique and the gradients agree
    lo = min(a, b)
    off_medial = (np.abs(p[:, 0]) > lo * 1e-3) & (np.abs(p[:, 1]) > lo * 1e-3) | (np.abs(d) > lo)
    np.testing.assert_allclose(g[off_medial], np.stack([rgx, rgy], -1)[off_medial], atol=1e-6)
    assert d[-4] == pytest.approx(-min(axes), abs=1e-15)


def test_polygon_with_many_vertices_matches_reference():
    rng = np.random.default_rng(3)
    n = 200
    t = np.sort(rng.uniform(0, 2 * np.pi, n))
    r = 1 + 0.3 * np.sin(5 * t) + rng.uniform(0, 0.1, n)
    v = np.stack([r * np.cos(t), r * np.sin(t)], -1)
    f = sdf.Polygon(v)
    p = np.concatenate([rng.uniform(-1.6, 1.6, (2000, 2)), v, v + 1e-10])
    d, g = f(*p.T, compute_gradient=True)
    ref, (rgx, rgy) = evaluate_numpy(f.f, {"x": p[:, 0], "y": p[:, 1]}, compute_gradient=True)
    np.testing.assert_allclose(d, ref, rtol=1e-12, atol=1e-13)
    # (on and within 1e-10 of a vertex, a kink, each picks its own one-sided direction)
    assert np.mean(np.hypot(g[:2000, 0] - rgx[:2000], g[:2000, 1] - rgy[:2000]) < 1e-9) > 0.99
    np.testing.assert_allclose(np.hypot(*g.T), 1.0, atol=1e-12)
    assert np.all((d[:2000] < 0) == Path(v).contains_points(p[:2000]))
    assert np.all(d[2000 : 2000 + n] == 0)


def test_same_kind_prims_fold_into_a_loop_and_polynomial_blends_fold_in_order():
    rng = np.random.default_rng(5)
    f = sdf.Halfspace([0, 1], -1.5)
    for _ in range(6):
        f |= sdf.Ellipse(rng.uniform(-1, 1, 2), rng.uniform(0.1, 0.5, 2))
    src = f.source()
    assert "for i" in src and "_P.ellipse_vg(" in src
    g = sdf.Circle([0, 0], 0.3)
    for i in range(6):
        g = g.union(sdf.Circle([0.3 * i, 0.1], 0.25), k=0.2, kind="quadratic")
    # a left fold of blends (not associative): a loop over the circles in the written order,
    # the same values as the nested binary blends of the reference below
    assert "for i" in g.source()
    p = rng.uniform(-2, 2, (500, 2))
    for h in (f, g):
        d, grad = h(*p.T, compute_gradient=True)
        ref, (rgx, rgy) = evaluate_numpy(h.f, {"x": p[:, 0], "y": p[:, 1]}, compute_gradient=True)
        np.testing.assert_allclose(d, ref, rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(grad, np.stack([rgx, rgy], -1), atol=1e-9)


def test_parallel_multi_lane_kernels_with_the_new_operations():
    """Inputs of 4096+ points run the parallel block kernels: every new operation
    (prim calls, select, floor, polynomial blends) in one scene, against the NumPy reference."""
    f = (
        sdf.Polygon([[0, 0], [1, 0], [1, 1], [0.5, 0.3], [0, 1]])
        .union(sdf.Ellipse([-0.5, 0.2], [0.6, 0.2]), k=0.2, kind="cubic")
        .intersection(
            sdf.RoundedBox([-1.5, -1], [1.5, 1.2], [0.1, 0.2, 0.3, 0.4]), k=0.1, kind="quadratic"
        )
    ) | sdf.Circle([0, 0], 0.1).repeat(0.5, (3, 2))
    p = np.random.default_rng(8).uniform(-2, 2, (4099, 2))
    p[5] = np.nan
    d, g = f(*p.T, compute_gradient=True)
    assert np.isnan(d[5]) and np.all(np.isnan(g[5]))
    ok = np.isfinite(p[:, 0])
    ref, (rgx, rgy) = evaluate_numpy(f.f, {"x": p[ok, 0], "y": p[ok, 1]}, compute_gradient=True)
    np.testing.assert_allclose(d[ok], ref, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(g[ok], np.stack([rgx, rgy], -1), atol=1e-9)
    np.testing.assert_array_equal(f(*p.T), d)


# ---------------------------------------------------------------------------------------------
# Polynomial blends.


@pytest.mark.parametrize("kind", ["quadratic", "cubic"])
def test_polynomial_blends_are_hard_outside_width_and_smooth_inside(kind):
    k = 0.3
    a, b = sdf.Circle([-0.4, 0], 0.5), sdf.Box([-0.1, -0.4], [0.8, 0.3])
    ops = [
        a.union(b, k=k, kind=kind),
        a.intersection(b, k=k, kind=kind),
        a.difference(b, k=k, kind=kind),
    ]
    with sdf.smoothness(k, kind=kind):
        assert str((a | b).f) == str(ops[0].f) and str((a & b).f) == str(ops[1].f)
        assert str((a - b).f) == str((a.difference(b)).f)  # '-' stays hard
    rng = np.random.default_rng(11)
    p = rng.uniform(-1.5, 1.5, (3000, 2))
    da, db = a(*p.T), b(*p.T)
    hard = [np.minimum(da, db), np.maximum(da, db), np.maximum(da, -db)]
    gap = [np.abs(da - db), np.abs(da - db), np.abs(da + db)]
    depth = k / 4 if kind == "quadratic" else k / 6
    for f, h, s in zip(ops, hard, gap):
        assert f.exactness == "bound"
        d, g = f(*p.T, compute_gradient=True)
        far = s >= k
        np.testing.assert_array_equal(d[far], h[far])  # exactly min/max
        assert np.all(np.abs(d - h) <= depth * (1 + 1e-12))
        # analytic gradient = central differences (the blend is C1: no kink at |a - b| = k),
        # and a convex combination of unit gradients: |g| <= 1
        fd = central_gradient(value_of(f), *p.T, h=1e-6)
        fd2 = central_gradient(value_of(f), *p.T, h=5e-7)
        smooth = np.all(np.abs(fd - fd2) < 1e-6, axis=1)
        np.testing.assert_allclose(g[smooth], fd[smooth], atol=1e-5)
        assert np.all(np.hypot(*g.T) <= 1 + 1e-12)
    # C1 across the edge of the blend region: find where |a - b| = k along the line y = 0.15
    # (bisection) and compare the gradients just inside and just outside
    f = ops[0]
    xs = np.linspace(-1.5, 1.5, 2001)
    s = np.abs(a(xs, 0.15 + 0 * xs) - b(xs, 0.15 + 0 * xs)) - k
    i = np.nonzero(np.diff(np.sign(s)))[0]
    assert len(i) >= 2
    lo, hi = xs[i], xs[i + 1]
    s_lo = np.sign(s[i])
    for _ in range(45):
        mid = (lo + hi) / 2
        same = np.sign(np.abs(a(mid, 0.15 + 0 * mid) - b(mid, 0.15 + 0 * mid)) - k) == s_lo
        lo, hi = np.where(same, mid, lo), np.where(same, hi, mid)
    _, g_lo = f(lo - 1e-9, 0.15 + 0 * lo, compute_gradient=True)
    _, g_hi = f(hi + 1e-9, 0.15 + 0 * hi, compute_gradient=True)
    assert np.all(np.hypot(*(g_lo - g_hi).T) < 1e-6)  # a kink would jump by O(1)
    # at a = b the blends sit k/4 (quadratic) or k/6 (cubic) below
    x = Symbol("x")
    e = (sym_qmin if kind == "quadratic" else sym_cmin)(x, x, k)
    assert evaluate_numpy(e, {"x": np.array([0.5]), "y": np.array([0.0])})[0] == pytest.approx(
        0.5 - depth
    )


def test_blends_are_bounds_lipschitz():
    """'bound' means |f| <= distance to the surface with the right sign; a 1-Lipschitz f has
    that property, and every blend is 1-Lipschitz: check it on random pairs of points."""
    a, b = sdf.Circle([-0.4, 0], 0.5), sdf.Ellipse([0.3, 0.1], [0.5, 0.2])
    rng = np.random.default_rng(2)
    p = rng.uniform(-1.5, 1.5, (4000, 2))
    q = p + rng.normal(0, 0.05, p.shape)
    for f in (
        a.union(b, 0.4, "quadratic"),
        a.intersection(b, 0.4, "cubic"),
        a.difference(b, 5.0, "exponential"),
    ):
        lhs = np.abs(f(*p.T) - f(*q.T))
        assert np.all(lhs <= np.hypot(*(p - q).T) * (1 + 1e-9))


# ---------------------------------------------------------------------------------------------
# Exactness flags.


def test_exactness_flags():
    c, b = sdf.Circle([0, 0], 0.5), sdf.Box([-0.3, -0.2], [0.3, 0.2])
    star = sdf.Star([0, 0], 1, 5)
    off = sdf.Circle([0.6, 0.2], 0.2)
    user = sdf.SDF(sdf.Circle([0, 0], 1).f * 2)  # an arbitrary expression: no guarantee
    expect = {
        "exact": [
            c,
            b,
            sdf.Halfspace(),
            sdf.Segment(),
            star,
            sdf.Ellipse(),
            b.round(0.1),
            sdf.Segment().round(0.2),
            c.rotate(0.3).translate([1, 2]),
            b.scale(2.0),
            off.mirror("x"),
            b.mirror("xy"),
            c.repeat(1.2, (3, 2)),
            sdf.Arc(aperture=math.pi, thickness=0.2),
            sdf.Polygon([[0, 0], [1, 0], [0, 1]]),
        ],
        "bound": [
            c | b,
            c & b,
            c - b,
            c.union(b, 0.2, "quadratic"),
            c.union(b, 5.0),
            c.intersection(b, 0.1, "cubic"),
            c.difference(b, 0.1, "quadratic"),
            star.round(0.1),
            star.round(-0.1),
            b.shell(0.1),
            sdf.Circle([0.1, 0], 0.3).mirror("x"),
            sdf.Circle([0, 0], 0.7).repeat(1.0, 3),
            sdf.Arc(aperture=6.0, thickness=0.6),
            c | b.shell(0.1),
            c.shell(0.1),
        ],
        "none": [user, off.repeat(1.0, 3), user | c, user.scale(2)],
    }
    for want, shapes in expect.items():
        for f in shapes:
            assert f.exactness == want, (want, f)
    u = c | b
    assert u.exact_outside and not u.exact_inside
    i = c & b
    assert i.exact_inside and not i.exact_outside
    # Under a transform a primitive's symmetry is unknown: repetition is no longer claimed exact
    with sdf.transform(angle=0.3):
        rc = sdf.Circle([0, 0], 0.2)
    assert rc.repeat(1.0, 3).exactness == "none"


def test_union_of_exact_is_exact_outside_but_not_inside():
    """The claims behind the flags, on one example: the union of two overlapping discs is
    exact outside; inside (in the overlap) the true distance is larger."""
    a, b = sdf.Circle([-0.3, 0], 0.5), sdf.Circle([0.3, 0], 0.5)
    u = a | b
    t = np.linspace(0, 2 * np.pi, 20000)
    ring = lambda c: np.stack([c[0] + 0.5 * np.cos(t), c[1] + 0.5 * np.sin(t)], -1)
    boundary = np.concatenate([ring((-0.3, 0)), ring((0.3, 0))])
    boundary = boundary[np.minimum(a(*boundary.T), b(*boundary.T)) >= -1e-12]
    boundary = boundary[
        np.minimum(
            np.hypot(boundary[:, 0] + 0.3, boundary[:, 1]),
            np.hypot(boundary[:, 0] - 0.3, boundary[:, 1]),
        )
        >= 0.5 - 1e-9
    ]
    p = np.random.default_rng(0).uniform(-1.2, 1.2, (800, 2))
    d = u(*p.T)
    brute = brute_distance(p, boundary)
    out = d > 0
    np.testing.assert_allclose(d[out], brute[out], atol=1e-3)
    assert np.all(-d[~out] <= brute[~out] + 1e-12)
    assert np.any(-d[~out] < brute[~out] - 0.05)  # strictly a bound in the overlap


# ---------------------------------------------------------------------------------------------
# Modifiers.


def test_modifiers_match_analytic_shapes():
    rng = np.random.default_rng(4)
    p = rng.uniform(-2.5, 2.5, (2000, 2))
    X, Y = p.T
    box = sdf.Box([-0.5, -0.3], [0.4, 0.6])
    checks = [
        (box.round(0.1), sdf.RoundedBox([-0.6, -0.4], [0.5, 0.7], 0.1)),
        (
            sdf.Segment([-0.5, 0.1], [0.4, 0.3]).round(0.2),
            sdf.Capsule([-0.5, 0.1], [0.4, 0.3], 0.2),
        ),
        (sdf.Circle([0.5, 0.1], 0.3).shell(0.1), sdf.Ring([0.5, 0.1], 0.3, 0.1)),
        (sdf.Circle([0.5, 0.1], 0.3).scale(2.0), sdf.Circle([1.0, 0.2], 0.6)),
        (
            sdf.Circle([0.5, 0.0], 0.3).mirror("x"),
            sdf.Circle([0.5, 0.0], 0.3) | sdf.Circle([-0.5, 0.0], 0.3),
        ),
    ]
    for got, want in checks:
        np.testing.assert_allclose(got(X, Y), want(X, Y), atol=1e-12)
    # rotation and translation as methods = building under transform (values and gradients)
    with sdf.transform(angle=0.7, offset=[0.3, -0.2]):
        built = sdf.Ellipse([0.1, 0.2], [0.5, 0.2]) | sdf.Triangle()
    moved = (sdf.Ellipse([0.1, 0.2], [0.5, 0.2]) | sdf.Triangle()).rotate(0.7)
    moved = moved.translate([0.3, -0.2])
    d1, g1 = built(X, Y, compute_gradient=True)
    d2, g2 = moved(X, Y, compute_gradient=True)
    np.testing.assert_allclose(d1, d2, atol=1e-12)
    np.testing.assert_allclose(g1, g2, atol=1e-12)
    # finite repetition of a centred disc = the union of the copies (exact); the count per
    # axis and one-axis repetition
    rep = sdf.Circle([0, 0], 0.2).repeat((0.7, 1.0), (3, 2))
    union = None
    for i in range(3):
        for j in range(2):
            c = sdf.Circle([0.7 * i, 1.0 * j], 0.2)
            union = c if union is None else union | c
    d, g = rep(X, Y, compute_gradient=True)
    np.testing.assert_allclose(d, union(X, Y), atol=1e-12)
    assert rep.exactness == "exact"
    # symmetric about x only: exact repeated along x, not along y (the nearest centre is
    # then not always the nearest copy)
    tri = sdf.Triangle()  # corners (-1, -0.5), (1, -0.5), (0, 1)
    row = tri.repeat(2.5, (3, 1))
    assert row.exactness == "exact" and tri.repeat((2.5, 3.0), (3, 2)).exactness == "none"
    copies = tri | tri.translate([2.5, 0]) | tri.translate([5.0, 0])
    np.testing.assert_allclose(row(X, Y), copies(X, Y), atol=1e-12)
    row = sdf.Box([-0.1, -0.2], [0.1, 0.2]).repeat(0.5, (4, 1))
    shifted = sdf.Box([1.4, -0.2], [1.6, 0.2])
    far_right = X > 1.75
    np.testing.assert_allclose(row(X, Y)[far_right], shifted(X, Y)[far_right], atol=1e-12)


def test_substitute_is_iterative_and_shares_untouched_nodes():
    x, y = Symbol("x"), Symbol("y")
    e = y * 2.0
    for i in range(5000):
        e = e + sym_abs(x - i * 1e-3)
    s = substitute(e, {"x": x * 2.0})
    assert "x" in s.symbols()
    t = substitute(e, {"z": x})
    assert t is e
    v = evaluate_numpy(s, {"x": np.array([0.3]), "y": np.array([0.1])})
    w = evaluate_numpy(e, {"x": np.array([0.6]), "y": np.array([0.1])})
    np.testing.assert_allclose(v, w, rtol=1e-12)


# ---------------------------------------------------------------------------------------------
# Bad input.


@pytest.mark.parametrize(
    "make,match",
    [
        (lambda: sdf.Segment(a=[0, 0, 0]), "a"),
        (lambda: sdf.Capsule(radius=0), "radius"),
        (lambda: sdf.Capsule(b=[np.nan, 0]), "b"),
        (lambda: sdf.RoundedBox(radii=[0.1, 0.2]), "radii"),
        (lambda: sdf.RoundedBox([-1, -0.2], [1, 0.2], radii=0.3), "radii"),
        (lambda: sdf.RoundedBox(radii=-0.1), "radii"),
        (lambda: sdf.OrientedBox([0, 0], [0, 0]), "a and b"),
        (lambda: sdf.OrientedBox(thickness=0), "thickness"),
        (lambda: sdf.Triangle([0, 0], [1, 1], [2, 2]), "collinear"),
        (lambda: sdf.EquilateralTriangle(radius=-1), "radius"),
        (lambda: sdf.RegularPolygon(n=2), "n"),
        (lambda: sdf.RegularPolygon(n=5.0), "n"),
        (lambda: sdf.Polygon([[0, 0], [1, 0]]), "vertices"),
        (lambda: sdf.Polygon([[0, 0], [1, 0], [2, 0]]), "area"),
        (lambda: sdf.Polygon([[0, 0], [1, 1], [1, 0], [0, 1]]), "not simple"),
        (lambda: sdf.Polygon([[0, 0], [2, 0], [1, 0], [1, 1]]), "not simple"),
        (lambda: sdf.Polygon([[0, 0], [2, 0], [2, 2], [1, 0], [0, 2]]), "not simple"),
        (lambda: sdf.Polygon("abc"), "vertices"),
        (lambda: sdf.Polygon([[0, 0], [1, np.inf], [0, 1]]), "vertices"),
        (lambda: sdf.Star(inner_radius=2.0), "inner_radius"),
        (lambda: sdf.Ellipse(axes=[1, 0]), "axes"),
        (lambda: sdf.Ellipse(axes=1.0), "axes"),
        (lambda: sdf.Ring(radius=0.5, thickness=1.0), "thickness"),
        (lambda: sdf.Arc(aperture=7.0), "aperture"),
        (lambda: sdf.Arc(aperture=0), "aperture"),
        (lambda: sdf.Arc(radius=0.5, thickness=1.2), "thickness"),
        (lambda: sdf.Circle().round("1"), "r"),
        (lambda: sdf.Circle().shell(0), "thickness"),
        (lambda: sdf.Circle().scale(-1), "s"),
        (lambda: sdf.Circle().translate([1]), "offset"),
        (lambda: sdf.Circle().rotate(np.nan), "angle"),
        (lambda: sdf.Circle().mirror("z"), "axis"),
        (lambda: sdf.Circle().repeat(0, 3), "spacing"),
        (lambda: sdf.Circle().repeat(1.0, 0), "count"),
        (lambda: sdf.Circle().repeat(1.0, 2.5), "count"),
        (lambda: sdf.Circle().union(sdf.Box(), k=0.1, kind="gaussian"), "kind"),
        (lambda: sdf.Circle().union(sdf.Box(), k=-0.1, kind="quadratic"), "k"),
        (lambda: sdf.Circle().union(3), "SDF"),
        (lambda: sdf.smoothness(0.1, kind="linear"), "kind"),
        (lambda: sdf.repeat("circle", 1.0, 2), "f"),
    ],
)
def test_bad_input_names_the_parameter(make, match):
    with pytest.raises((ValueError, TypeError), match=match):
        make()
