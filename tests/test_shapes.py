"""The modelling DSL: primitives against analytic values and brute-force distances, the
notebook's operations and blends, transforms, numerical hard cases and bad input."""

import math
import threading

import numpy as np
import pytest
from conftest import brute_distance, central_gradient, rotate

import fastsdf as sdf
from fastsdf.expr.graph import evaluate_numpy
from fastsdf.shapes.scenes import box_world, mixed_scene


def _boundary_circle(center, radius, n=20000):
    t = np.linspace(0, 2 * np.pi, n, endpoint=False)
    return np.stack([center[0] + radius * np.cos(t), center[1] + radius * np.sin(t)], -1)


def _boundary_box(minc, maxc, n=5000):
    (x0, y0), (x1, y1) = minc, maxc
    s = np.linspace(0, 1, n)
    edges = [
        np.stack([x0 + (x1 - x0) * s, np.full(n, y0)], -1),
        np.stack([x0 + (x1 - x0) * s, np.full(n, y1)], -1),
        np.stack([np.full(n, x0), y0 + (y1 - y0) * s], -1),
        np.stack([np.full(n, x1), y0 + (y1 - y0) * s], -1),
    ]
    return np.concatenate(edges)


def test_circle_is_exact_against_sampled_boundary(rng):
    center, radius = np.array([0.3, -0.2]), 0.7
    f = sdf.Circle(center=center, radius=radius)
    pts = np.concatenate(
        [
            rng.uniform(-2, 2, (300, 2)),  # far and inside
            center + rng.normal(0, 0.05, (100, 2)) + [radius, 0],
        ]
    )  # near boundary
    d = f(pts[:, 0], pts[:, 1])
    inside = np.hypot(*(pts - center).T) < radius
    assert np.all((d < 0) == inside)
    spacing = 2 * np.pi * radius / 20000
    brute = brute_distance(pts, _boundary_circle(center, radius))
    assert np.all(brute >= np.abs(d) - 1e-12)
    np.testing.assert_allclose(np.abs(d), brute, atol=spacing / 2)


@pytest.mark.parametrize(
    "angle,offset", [(0.0, (0.0, 0.0)), (0.4, (0.5, -0.3)), (-2.0, (1.0, 1.0))]
)
def test_box_is_exact_against_sampled_boundary(rng, angle, offset):
    minc, maxc = np.array([-0.5, -0.2]), np.array([0.3, 0.6])
    with sdf.transform(angle=angle, offset=offset):
        f = sdf.Box(minc=minc, maxc=maxc)
    pts = np.concatenate([rng.uniform(-2, 2, (400, 2)), rng.uniform(-0.7, 0.7, (200, 2)) + offset])
    d = f(pts[:, 0], pts[:, 1])
    local = rotate(pts - offset, -angle)  # world -> box frame
    inside = np.all((local > minc) & (local < maxc), axis=1)
    assert np.all((d < 0) == inside)
    boundary = rotate(_boundary_box(minc, maxc), angle) + offset
    brute = brute_distance(pts, boundary)
    # A sampled boundary can only be farther than the true one, by at most half a spacing.
    spacing = np.max(maxc - minc) / 4999
    assert np.all(brute >= np.abs(d) - 1e-12)
    np.testing.assert_allclose(np.abs(d), brute, atol=spacing / 2)


def test_box_matches_notebook_box_inside_and_bounds_it_outside(rng):
    """The notebook's box (four half-spaces intersected) equals the exact box inside and along the
    faces; outside the corners it is a lower bound (the L-infinity distance)."""
    minc, maxc = [-0.4, -0.3], [0.4, 0.3]
    exact = sdf.Box(minc=minc, maxc=maxc)
    seed = (
        sdf.Halfspace([0, -1], -minc[1])
        & sdf.Halfspace([1, 0], maxc[0])
        & sdf.Halfspace([0, 1], maxc[1])
        & sdf.Halfspace([-1, 0], -minc[0])
    )
    p = rng.uniform(-1.5, 1.5, (2000, 2))
    de, ds = exact(p[:, 0], p[:, 1]), seed(p[:, 0], p[:, 1])
    corner = (np.abs(p[:, 0]) > 0.4) & (np.abs(p[:, 1]) > 0.3)
    np.testing.assert_allclose(de[~corner], ds[~corner], atol=1e-15)
    assert np.all(ds[corner] < de[corner])


def test_halfspace_normalizes_and_is_signed():
    h = sdf.Halfspace(normal=[3, 4], d=1.0)
    d, g = h(np.array([0.0, 0.6, 3.0]), np.array([0.0, 0.8, 4.0]), compute_gradient=True)
    np.testing.assert_allclose(d, [-1.0, 0.0, 4.0], atol=1e-15)
    np.testing.assert_allclose(g, [[0.6, 0.8]] * 3, atol=1e-15)


def test_set_operations_are_min_max(rng):
    a, b = sdf.Circle([-0.6, 0], 1.0), sdf.Circle([0.6, 0], 1.0)
    p = rng.uniform(-2, 2, (500, 2))
    da, db = a(*p.T), b(*p.T)
    np.testing.assert_array_equal((a | b)(*p.T), np.minimum(da, db))
    np.testing.assert_array_equal((a & b)(*p.T), np.maximum(da, db))
    np.testing.assert_array_equal((a - b)(*p.T), np.maximum(da, -db))
    with sdf.smoothness(10):  # difference stays hard, as in the notebook
        np.testing.assert_array_equal((a - b)(*p.T), np.maximum(da, -db))
    f = a
    f |= b
    np.testing.assert_array_equal(f(*p.T), np.minimum(da, db))


def test_complement_negates_the_value_and_the_gradient(rng):
    shapes = [
        sdf.Polygon([[0, 0], [1, 0], [0.2, 0.3], [0, 1]]),  # not convex
        sdf.Circle([0.2, -0.1], 0.6) | sdf.Box([-1, -0.2], [0.1, 0.5]),
        sdf.Halfspace([1, 1], 0.3),
    ]
    p = rng.uniform(-1.5, 1.5, (400, 2))
    for f in shapes:
        d, grad = f(*p.T, compute_gradient=True)
        dc, gradc = (-f)(*p.T, compute_gradient=True)
        np.testing.assert_array_equal(dc, -d)
        np.testing.assert_array_equal(gradc, -grad)
        np.testing.assert_allclose(gradc, central_gradient(-f, *p.T), atol=1e-5)
        twice = -f
        np.testing.assert_array_equal((-twice)(*p.T), d)


def test_difference_is_intersection_with_the_complement(rng):
    a = sdf.Star([0.1, 0], 1.0, 5)
    b = sdf.Ellipse([0.5, 0.2], [0.6, 0.3])
    p = rng.uniform(-1.5, 1.5, (500, 2))
    want, want_grad = (a - b)(*p.T, compute_gradient=True)
    got, got_grad = (a & -b)(*p.T, compute_gradient=True)
    np.testing.assert_array_equal(got, want)
    np.testing.assert_array_equal(got_grad, want_grad)
    assert (a & -b).exactness == (a - b).exactness == "bound"
    assert (a & -b).exact_inside and (a - b).exact_inside


def test_complement_is_exact_where_the_shape_is_and_unbounded(rng):
    lo, hi = (-0.4, -0.25), (0.5, 0.3)
    box = sdf.Box(lo, hi)
    p = rng.uniform(-1, 1, (600, 2))
    inside_box = np.all((p > lo) & (p < hi), axis=1)
    dist = brute_distance(p, _boundary_box(lo, hi))
    np.testing.assert_allclose((-box)(*p.T), np.where(inside_box, dist, -dist), atol=1e-3)
    assert (-box).exactness == "exact"
    # exact inside and outside trade places
    u = sdf.Circle([-0.3, 0], 0.5) | sdf.Circle([0.3, 0], 0.5)
    assert (-u).exact_inside and not (-u).exact_outside and (-u).exactness == "bound"
    back = -u
    assert (-back).exact_outside and not (-back).exact_inside
    # not a distance bound stays no bound
    assert (-sdf.SDF(sdf.Circle([0, 0], 1).f * 2)).exactness == "none"
    # Unbounded: a disc right of the axis mirrors exactly, its complement (which reaches
    # across the axis) does not; a copy of it overlaps every other copy.
    off = sdf.Circle([0.6, 0.2], 0.2)
    assert off.mirror("x").exactness == "exact"
    assert (-off).mirror("x").exactness == "bound"
    centred = sdf.Circle([0, 0], 0.2)
    assert centred.repeat(1.0, 3).exactness == "exact"
    assert (-centred).repeat(1.0, 3).exactness != "exact"


@pytest.mark.parametrize("k", [0.5, 10.0, 30.0])
def test_smooth_blends_reproduce_the_notebook_formula(rng, k):
    a, b = sdf.Circle([-0.6, 0], 1.0), sdf.Halfspace([0.3, 1], 0.2)
    with sdf.smoothness(k):
        u, i = a | b, a & b
    p = rng.uniform(-2, 2, (500, 2))
    da, db = a(*p.T), b(*p.T)
    notebook_u = -np.log(np.exp(-k * da) + np.exp(-k * db)) / k
    notebook_i = np.log(np.exp(k * da) + np.exp(k * db)) / k
    np.testing.assert_allclose(u(*p.T), notebook_u, rtol=1e-12, atol=1e-13)
    np.testing.assert_allclose(i(*p.T), notebook_i, rtol=1e-12, atol=1e-13)
    for f, ref in (
        (u, lambda X, Y: -np.log(np.exp(-k * a(X, Y)) + np.exp(-k * b(X, Y))) / k),
        (i, lambda X, Y: np.log(np.exp(k * a(X, Y)) + np.exp(k * b(X, Y))) / k),
    ):
        _, g = f(*p.T, compute_gradient=True)
        np.testing.assert_allclose(g, central_gradient(ref, *p.T), rtol=1e-5, atol=1e-6)


def test_seed_world_value_matches_notebook_construction(rng):
    """Notebook cell 21's world, built through the DSL, against the literal notebook formulas."""
    from fastsdf.shapes.scenes import seed_world

    f = seed_world()
    p = rng.uniform(-2, 2, (1000, 2))
    X, Y = p.T
    n2 = np.array([1, 1]) / math.sqrt(2)
    floor = np.minimum(
        np.minimum(Y + 1.8, n2[0] * X + n2[1] * Y + 1.8), -n2[0] * X + n2[1] * Y + 1.8
    )
    n4 = np.array([0.1, 1]) / np.hypot(0.1, 1)
    disc = (
        np.log(np.exp(10 * (np.hypot(X, Y) - 0.5)) + np.exp(10 * (n4[0] * X + n4[1] * Y - 0.3)))
        / 10
    )
    ref = -np.log(np.exp(-10 * floor) + np.exp(-10 * disc)) / 10
    np.testing.assert_allclose(f(X, Y), ref, rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("k", [1e-3, 1.0, 1e3, 1e6])
@pytest.mark.parametrize("scale", [1.0, 1e4, 1e8])
def test_smooth_blends_never_overflow(k, scale):
    """The notebook's literal formula overflows for k*|d| > ~709; fastsdf's does not."""
    a, b = sdf.Circle([0, 0], 1.0), sdf.Halfspace([0, 1], 0.0)
    with sdf.smoothness(k):
        fs = [a | b, a & b]
    X = np.array([0.0, scale, -scale, scale, 0.3]) * 1.0
    Y = np.array([scale, -scale, scale, scale, -0.1])
    for f in fs:
        d, g = f(X, Y, compute_gradient=True)
        assert np.all(np.isfinite(d)) and np.all(np.isfinite(g))
        hard = np.minimum(a(X, Y), b(X, Y)) if f is fs[0] else np.maximum(a(X, Y), b(X, Y))
        # The blend differs from the hard min/max by at most log(2)/k (plus rounding).
        assert np.all(np.abs(d - hard) <= math.log(2) / k * (1 + 1e-9) + 1e-12 * np.abs(hard))
        np.testing.assert_allclose(np.hypot(*g.T), 1.0, atol=1.0)  # convex combination: |g| <= 1


def test_gradient_is_finite_and_unit_at_circle_centre():
    c = sdf.Circle(center=[0.5, -0.25], radius=0.3)
    d, g = c(np.array([0.5]), np.array([-0.25]), compute_gradient=True)
    assert d[0] == -0.3
    np.testing.assert_array_equal(g[0], [1.0, 0.0])  # documented choice: the local +x axis
    # Under a rotation the centre is only reached up to rounding; any unit direction is valid.
    with sdf.transform(angle=0.7, offset=[1.0, 2.0]):
        c = sdf.Circle(center=[0.5, 0.0], radius=0.3)
    centre = np.array([1.0 + 0.5 * math.cos(0.7)]), np.array([2.0 + 0.5 * math.sin(0.7)])
    d, g = c(*centre, compute_gradient=True)
    assert d[0] == pytest.approx(-0.3, abs=1e-15)
    assert np.hypot(*g[0]) == pytest.approx(1.0, abs=1e-12)


def test_gradient_is_finite_on_box_kinks_and_ties():
    b = sdf.Box([-1, -1], [1, 1])
    X = np.array([0.0, 1.0, 1.0, 0.0, 0.5, -1.0])
    Y = np.array([0.0, 1.0, 0.0, 0.0, 0.5, -1.0])  # centre, corner, face, diagonal tie
    d, g = b(X, Y, compute_gradient=True)
    assert np.all(np.isfinite(g))
    np.testing.assert_allclose(np.hypot(*g.T), 1.0, atol=1e-15)  # a one-sided gradient


def _unit_gradient_scenes():
    with sdf.transform(angle=0.3, offset=[0.2, -0.1]):
        box = sdf.Box([-0.5, -0.3], [0.4, 0.2])
        circ = sdf.Circle([0.9, 0.4], 0.35)
    return {
        "circle": circ,
        "box": box,
        "halfspace": sdf.Halfspace([1, -2], 0.3),
        "union": box | circ,
        "intersection": box & sdf.Halfspace([1, 1], 0.1),
        "difference": box - circ,
    }


@pytest.mark.parametrize("name", list(_unit_gradient_scenes()))
def test_exact_sdf_gradients_have_unit_length(name, rng):
    f = _unit_gradient_scenes()[name]
    p = rng.uniform(-1.5, 1.5, (3000, 2))
    d, g = f(*p.T, compute_gradient=True)
    # Away from kinks (where central differences disagree across the kink) |grad| = 1 to 1e-12.
    fd = central_gradient(f, *p.T, h=1e-7)
    smooth = np.hypot(*(fd - g).T) < 1e-5
    assert smooth.mean() > 0.9
    np.testing.assert_allclose(np.hypot(*g[smooth].T), 1.0, atol=1e-12)


def test_non_finite_points_give_nan_for_those_points_only():
    f = box_world(8)
    X = np.array([0.1, np.nan, 0.3, np.inf, -np.inf, 0.5, 0.2])
    Y = np.array([0.2, 0.0, np.nan, 0.0, 1.0, 0.1, np.inf])
    for n_rep in (1, 2000):  # serial and parallel kernels
        Xr, Yr = np.tile(X, n_rep), np.tile(Y, n_rep)
        d, g = f(Xr, Yr, compute_gradient=True)
        bad = ~(np.isfinite(Xr) & np.isfinite(Yr))
        assert np.all(np.isnan(d[bad])) and np.all(np.isnan(g[bad]))
        assert np.all(np.isfinite(d[~bad])) and np.all(np.isfinite(g[~bad]))
        np.testing.assert_array_equal(f(Xr, Yr), d)
        ok = ~bad
        np.testing.assert_allclose(
            d[ok], evaluate_numpy(f.f, {"x": Xr[ok], "y": Yr[ok]}), rtol=1e-12, atol=1e-12
        )


def test_huge_coordinates_stay_finite_and_exact():
    c, b = sdf.Circle([0, 0], 1.0), sdf.Box([-1, -1], [1, 1])
    X = np.array([1e8, 1e155, 3e200, -1e300])
    Y = np.array([1e8, 1e155, 4e200, 0.0])
    d, g = c(X, Y, compute_gradient=True)
    np.testing.assert_allclose(d, np.hypot(X, Y) - 1, rtol=1e-15)
    assert np.all(np.isfinite(g))
    np.testing.assert_allclose(np.hypot(*g.T), 1.0, atol=1e-15)
    d, g = b(X, Y, compute_gradient=True)
    assert np.all(np.isfinite(d)) and np.all(np.isfinite(g))


def test_float32_inputs_are_computed_in_float64():
    f = sdf.Circle([0.1, 0.2], 0.5)
    X = np.linspace(-1, 1, 50, dtype=np.float32)
    Y = np.linspace(1, -1, 50, dtype=np.float32)
    d = f(X, Y)
    assert d.dtype == np.float64
    np.testing.assert_array_equal(d, f(X.astype(np.float64), Y.astype(np.float64)))


def test_context_managers_nest_and_restore():
    with sdf.transform(angle=0.5, offset=[1.0, 0.0]):
        with sdf.transform(angle=0.25, offset=[0.0, 2.0]):
            c = sdf.Circle(center=[0.3, 0.0], radius=0.1)
        with sdf.smoothness(4):
            assert sdf.shapes.current_smoothness() == 4
            with sdf.smoothness(0):
                assert sdf.shapes.current_smoothness() == 0
            assert sdf.shapes.current_smoothness() == 4
    assert sdf.shapes.current_smoothness() == 0
    # inner transform first, outer applied last: R(0.5) (R(0.25) c + o2) + o1
    centre = rotate(rotate(np.array([[0.3, 0.0]]), 0.25) + [0.0, 2.0], 0.5) + [1.0, 0.0]
    assert c(*centre.T)[0] == pytest.approx(-0.1, abs=1e-14)
    assert sdf.Circle([0, 0], 1)(np.array([1.0]), np.array([0.0]))[0] == 0.0  # state restored


def test_context_restored_after_exception():
    with pytest.raises(RuntimeError), sdf.smoothness(3), sdf.transform(angle=1.0):
        raise RuntimeError("boom")
    assert sdf.shapes.current_smoothness() == 0
    assert sdf.Halfspace([1, 0], 0)(np.array([2.0]), np.array([0.0]))[0] == 2.0


def _scene(i, barrier):
    """A scene whose value depends on the smoothness and transform it was built under."""
    f = sdf.Halfspace([0, 1], -1.0)
    with sdf.smoothness(1.0 + i), sdf.transform(angle=0.1 * i, offset=[0.05 * i, 0.0]):
        barrier.wait()  # every thread is inside its own contexts before any primitive is built
        f |= sdf.Circle([0.2, 0.0], 0.5) & sdf.Box([-0.4, -0.3], [0.4, 0.1])
        with sdf.transform(angle=-0.2 * i):
            barrier.wait()
            f |= sdf.Capsule([0, 0], [0.5, 0.1], 0.1)
    return f, sdf.shapes.current_blend()


def test_contexts_are_per_thread():
    """Scenes built concurrently in threads see only their own smoothness and transform."""
    n = 6
    x = np.linspace(-2, 2, 41)
    X, Y = np.meshgrid(x, x)
    alone = threading.Barrier(1)
    expected = [evaluate_numpy(_scene(i, alone)[0].f, {"x": X, "y": Y}) for i in range(n)]
    together = threading.Barrier(n, timeout=30)
    results = [None] * n

    def work(i):
        results[i] = _scene(i, together)

    with sdf.smoothness(99.0), sdf.transform(offset=[7.0, 7.0]):  # the main thread's contexts
        threads = [threading.Thread(target=work, args=(i,)) for i in range(n)]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
        assert sdf.shapes.current_blend() == (99.0, "exponential")
    assert sdf.shapes.current_blend() == (0.0, "exponential")
    for i, (f, after) in enumerate(results):
        assert after == (0.0, "exponential")  # each thread restored its own state
        np.testing.assert_array_equal(evaluate_numpy(f.f, {"x": X, "y": Y}), expected[i])


def test_transform_composes_where_it_is_entered():
    t = sdf.transform(offset=[1.0, 0.0])  # created outside, entered inside another transform
    with sdf.transform(offset=[0.0, 2.0]), t:
        c = sdf.Circle([0, 0], 0.5)
    assert evaluate_numpy(c.f, {"x": np.array([1.0]), "y": np.array([2.0])})[0] == -0.5


@pytest.mark.parametrize(
    "make,match",
    [
        (lambda: sdf.Halfspace(normal=[0, 0]), "normal"),
        (lambda: sdf.Halfspace(normal=[1, 0, 0]), "normal"),
        (lambda: sdf.Halfspace(normal="ab"), "normal"),
        (lambda: sdf.Halfspace(d=float("nan")), "d"),
        (lambda: sdf.Circle(radius=0), "radius"),
        (lambda: sdf.Circle(radius=-1), "radius"),
        (lambda: sdf.Circle(radius="1"), "radius"),
        (lambda: sdf.Circle(center=[np.inf, 0]), "center"),
        (lambda: sdf.Box(minc=[0, 0], maxc=[1, 0]), "minc"),
        (lambda: sdf.Box(minc=[1, 1], maxc=[0, 2]), "minc"),
        (lambda: sdf.smoothness(-1), "k"),
        (lambda: sdf.smoothness(float("inf")), "k"),
        (lambda: sdf.smoothness("10"), "k"),
        (lambda: sdf.transform(angle=float("nan")), "angle"),
        (lambda: sdf.transform(offset=[0, np.nan]), "offset"),
        (lambda: sdf.transform(offset=[0, 1, 2]), "offset"),
        (lambda: sdf.Circle() | 3, "SDF"),
        (lambda: box_world(-1), "n_boxes"),
        (lambda: mixed_scene(0), "n"),
        (lambda: mixed_scene(2.5), "n"),
    ],
)
def test_bad_input_names_the_parameter(make, match):
    with pytest.raises((ValueError, TypeError), match=match):
        make()


def test_mixed_scene_is_its_floor_cut_by_seeded_shapes():
    """One primitive is the floor y = -1.8; more add shapes drawn from the seed only."""
    x, y = np.random.default_rng(3).uniform(-2, 2, (2, 500))
    np.testing.assert_array_equal(evaluate_numpy(mixed_scene(1).f, {"x": x, "y": y}), y + 1.8)
    a, b = (evaluate_numpy(mixed_scene(12, seed=s).f, {"x": x, "y": y}) for s in (4, 4))
    np.testing.assert_array_equal(a, b)
    c = evaluate_numpy(mixed_scene(12, seed=5).f, {"x": x, "y": y})
    assert np.any(a != c) and np.any(a != y + 1.8)


@pytest.mark.parametrize(
    "k, kind", [(0.0, "exponential"), (5.0, "exponential"), (0.1, "quadratic"), (0.1, "cubic")]
)
def test_nary_union_and_intersection_are_the_left_folds(k, kind):
    # fastsdf.union / intersection of a list: the same expression (same node, so the same
    # kernels) and the same exactness bookkeeping as the left fold of the binary operations
    import functools

    rng = np.random.default_rng(3)
    shapes = []
    for i, c in enumerate(rng.uniform(-2, 2, (12, 2))):
        with sdf.transform(angle=float(rng.uniform(-1, 1)) if i % 3 == 0 else 0.0):
            shapes.append(sdf.Box(c - 0.1, c + 0.2) if i % 2 else sdf.Circle(c, 0.15))
    for nary, binary in ((sdf.union, "union"), (sdf.intersection, "intersection")):
        want = functools.reduce(lambda a, b: getattr(a, binary)(b, k=k, kind=kind), shapes)
        got = nary(iter(shapes), k=k, kind=kind)  # any iterable
        assert got.f is want.f
        assert got.exactness == want.exactness and got._info == want._info
    assert sdf.union(shapes[:1]) is shapes[0]


def test_nary_union_rejects_bad_input():
    c = sdf.Circle([0, 0], 1.0)
    with pytest.raises(ValueError, match="at least one shape"):
        sdf.union([])
    with pytest.raises(TypeError, match="one SDF"):
        sdf.union(c)
    with pytest.raises(TypeError, match=r"shapes\[1\]"):
        sdf.intersection([c, 3.0])
    with pytest.raises(TypeError, match="iterable"):
        sdf.union(5)
    with pytest.raises(ValueError, match="k"):
        sdf.union([c, c], k=-1.0)


def test_polygons_with_the_same_vertices_share_their_checks_not_their_arrays():
    # the checks of a polygon's vertices run once per distinct shape (cached); each polygon
    # still owns its vertex array, and an invalid shape raises every time
    tri = [[0.0, 0.0], [1.0, 0.0], [0.3, 0.8]]
    a, b = sdf.Polygon(tri), sdf.Polygon(np.array(tri))
    assert a.f is b.f and a.vertices is not b.vertices
    np.testing.assert_array_equal(a.vertices, b.vertices)
    a.vertices[0, 0] = 5.0  # the caller's copy: the next polygon is unaffected
    assert sdf.Polygon(tri).vertices[0, 0] == 0.0
    bowtie = [[0, 0], [1, 1], [1, 0], [0, 1]]
    for _ in range(2):
        with pytest.raises(ValueError, match="vertices"):
            sdf.Polygon(bowtie)


_NUMPY_BAD = [
    np.float64(-0.1),
    np.float64("nan"),
    np.int64(-3),
    np.float32(-2.5),
    np.bool_(True),
    np.float64(1e200),
    np.array([np.float64(-1.0), np.float64(2.0)]),
    (np.float64(0.5), np.float64("inf")),
]
_VALID = {
    "center": (0.0, 0.0),
    "radius": 1.0,
    "normal": (0.0, 1.0),
    "a": (0.0, 0.0),
    "b": (1.0, 0.0),
    "minc": (0.0, 0.0),
    "maxc": (1.0, 1.0),
    "vertices": [(0.0, 0.0), (1.0, 0.0), (0.0, 1.0)],
    "shapes": [sdf.Circle((0.0, 0.0), 1.0)],
}


def _public_constructors():
    import inspect

    import fastsdf.shapes as shapes

    for name in shapes.__all__:
        obj = getattr(shapes, name)
        if not callable(obj) or name in ("SDF", "smoothness"):
            continue
        try:
            params = inspect.signature(obj).parameters.values()
        except (TypeError, ValueError):
            continue
        named = [p for p in params if p.kind in (p.POSITIONAL_OR_KEYWORD, p.KEYWORD_ONLY)]
        yield name, obj, named


def test_errors_quote_numpy_values_as_plain_numbers():
    """Every shape's error, given NumPy numbers, quotes them as Python would print the numbers
    (``radius=-0.1``, never ``np.float64(-0.1)`` or ``array([...])``)."""
    import inspect

    circle = sdf.Circle((0.0, 0.0), 1.0)
    errors = 0
    for name, make, params in _public_constructors():
        for param in params:
            for bad in _NUMPY_BAD:
                kwargs = {
                    p.name: _VALID.get(p.name, circle if p.name in ("f", "a", "b") else 1.0)
                    for p in params
                    if p.default is inspect.Parameter.empty and p.name != param.name
                }
                kwargs[param.name] = bad
                try:
                    make(**kwargs)
                except (TypeError, ValueError) as exc:
                    errors += 1
                    text = str(exc)
                    assert "np." not in text and "array(" not in text, (name, param.name, text)
    assert errors > 300  # (the sweep reached the checks)
    with pytest.raises(ValueError, match=r"got radius=-0\.1$"):
        sdf.Circle(center=(0.0, 0.0), radius=np.float64(-0.1))
