"""GridSDF: node values, bilinear reproduction of affine functions, second-order convergence,
out-of-bounds modes, float32 storage bounds, NaN handling, parameter validation, and the numba
sampler contract. Grids are small so that the file runs in seconds once kernels are cached."""

import math

import numpy as np
import pytest
from numba import njit

import fastsdf as sdf
import fastsdf.graph as cg
from fastsdf.expr.points import PARALLEL_MIN_POINTS
from fastsdf.fields.grid import BYTES_PER_NODE, GridError, GridSDF, measure_error

EPS32 = 2.0**-24
MODES = ("exact", "nearest")
GRADIENTS = ("stored", "fd")
DTYPES = (np.float64, np.float32)


@pytest.fixture(scope="module")
def circle():
    return sdf.Circle(center=[0.1, -0.05], radius=1.0)


@pytest.fixture(scope="module")
def plane():
    return sdf.Halfspace(normal=[0.3, 1.0], d=0.2)


def _rng(seed=0):
    return np.random.default_rng(seed)


def test_exported_from_package():
    assert sdf.GridSDF is GridSDF
    assert "GridSDF" in sdf.__all__


@pytest.mark.parametrize("gradient", GRADIENTS)
def test_values_equal_exact_sdf_at_nodes(circle, gradient):
    g = GridSDF(circle, bounds=[(-1.7, 2.1), (-1.3, 1.5)], samples=[23j, 17j], gradient=gradient)
    ax, ay = g.axes
    assert ax[0] == -1.7 and ax[-1] == 2.1 and ay[0] == -1.3 and ay[-1] == 1.5
    X, Y = np.meshgrid(ax, ay, indexing="ij")
    d, grad = circle(X, Y, compute_gradient=True)
    np.testing.assert_array_equal(g.values, d)  # stored as sampled, bitwise
    if gradient == "stored":
        np.testing.assert_array_equal(g.data[:, :, 1:], grad)
    # Querying exactly at the nodes gives the node values (up to the rounding of the
    # coordinate-to-cell mapping).
    dq, gq = g(X, Y, compute_gradient=True)
    np.testing.assert_allclose(dq, d, rtol=0, atol=1e-13)
    if gradient == "stored":
        np.testing.assert_allclose(gq, grad, rtol=0, atol=1e-12)


def test_samples_complex_and_int_forms_agree_with_mgrid(circle):
    a = GridSDF(circle, bounds=[(-2, 2), (-1, 3)], samples=[40j, 25j])
    b = GridSDF(circle, bounds=[(-2, 2), (-1, 3)], samples=[40, np.int64(25)])
    assert a.shape == b.shape == (40, 25)
    np.testing.assert_array_equal(a.data, b.data)
    X, Y = np.mgrid[-2:2:40j, -1:3:25j]
    ax, ay = a.axes
    np.testing.assert_allclose(ax, X[:, 0], atol=1e-15)
    np.testing.assert_allclose(ay, Y[0, :], atol=1e-15)
    assert a.spacing == pytest.approx((4 / 39, 4 / 24))


@pytest.mark.parametrize("gradient", GRADIENTS)
@pytest.mark.parametrize("n", [50, PARALLEL_MIN_POINTS + 17])  # serial and parallel paths
def test_affine_function_is_reproduced_to_roundoff(plane, gradient, n):
    # Bilinear interpolation reproduces affine functions; so do central and second-order
    # one-sided differences (the 'fd' gradient), everywhere inside, edges and corners included.
    g = GridSDF(plane, bounds=[(-2, 1.5), (-1, 2)], samples=[7, 5], gradient=gradient)
    rng = _rng(1)
    x, y = rng.uniform(-2, 1.5, n), rng.uniform(-1, 2, n)
    x[:4], y[:4] = [-2, 1.5, -2, 1.5], [-1, -1, 2, 2]  # the four corners
    d, grad = g(x, y, compute_gradient=True)
    de, ge = plane(x, y, compute_gradient=True)
    np.testing.assert_allclose(d, de, rtol=0, atol=1e-14)
    np.testing.assert_allclose(grad, ge, rtol=0, atol=1e-14)
    np.testing.assert_array_equal(g(x, y), d)  # value-only kernel agrees
    err = measure_error(g, n=2000, seed=3)
    assert err.value_max < 1e-14 and err.angle_max_deg < 1e-6


@pytest.mark.parametrize("gradient", GRADIENTS)
def test_error_falls_at_second_order_on_a_circle(circle, gradient):
    # In the band |d| < 0.1 around a circle (far from its centre, the one kink) the SDF is
    # smooth: bilinear error <= h^2/8 (|d_xx| + |d_yy|) = h^2 / (8 r), second order in h.
    errs = [
        measure_error(
            GridSDF(circle, samples=[n, n], gradient=gradient), n=40_000, band=0.1, seed=7
        )
        for n in (41, 81)
    ]
    for e in errs:
        h = e.spacing[0]
        assert e.band_n > 1000
        assert e.band_value_max <= h * h / (8 * 0.9) * 1.001
    order = {
        k: math.log2(getattr(errs[0], k) / getattr(errs[1], k))
        for k in ("band_value_max", "band_value_rms", "band_angle_rms_deg", "band_angle_max_deg")
    }
    for k, p in order.items():
        assert 1.8 < p < 2.2, (k, p, order)


def test_stored_gradients_beat_finite_differences(circle):
    stored = measure_error(GridSDF(circle, samples=[41, 41], gradient="stored"), n=20_000)
    fd = measure_error(GridSDF(circle, samples=[41, 41], gradient="fd"), n=20_000)
    assert stored.band_value_max == fd.band_value_max  # same values, same interpolation
    assert stored.band_angle_rms_deg < fd.band_angle_rms_deg


@pytest.mark.parametrize("gradient", GRADIENTS)
def test_outside_bounds_exact_mode_uses_the_exact_sdf(circle, gradient):
    g = GridSDF(circle, bounds=[(-1, 1), (-1, 1)], samples=[21, 21], gradient=gradient)
    assert g.mode == "exact" and g.exact is circle
    rng = _rng(2)
    for n in (40, PARALLEL_MIN_POINTS + 5):
        x, y = rng.uniform(-3, 3, n), rng.uniform(-3, 3, n)
        out = ~g.contains(x, y)
        assert 0 < out.sum() < n
        d, grad = g(x, y, compute_gradient=True)
        de, ge = circle(x, y, compute_gradient=True)
        np.testing.assert_array_equal(d[out], de[out])
        np.testing.assert_array_equal(grad[out], ge[out])
        np.testing.assert_array_equal(g(x, y)[out], de[out])
        assert np.abs(d[~out] - de[~out]).max() < g.spacing[0]  # inside: interpolated (O(h) at
        # the centre, a kink)


@pytest.mark.parametrize("gradient", GRADIENTS)
def test_outside_bounds_nearest_mode_clamps(circle, gradient):
    g = GridSDF(
        circle, bounds=[(-1, 1), (-0.5, 1)], samples=[21, 16], mode="nearest", gradient=gradient
    )
    rng = _rng(3)
    x, y = rng.uniform(-4, 4, 500), rng.uniform(-4, 4, 500)
    d, grad = g(x, y, compute_gradient=True)
    dc, gc = g(np.clip(x, -1, 1), np.clip(y, -0.5, 1), compute_gradient=True)
    np.testing.assert_array_equal(d, dc)
    np.testing.assert_array_equal(grad, gc)
    np.testing.assert_array_equal(g(x, y), dc)


def test_nearest_mode_matches_the_notebooks_map_coordinates(circle):
    # The seed's GridSDF: three passes of scipy's map_coordinates, order=1, mode='nearest'.
    ndimage = pytest.importorskip("scipy.ndimage")
    g = GridSDF(circle, bounds=[(-2, 2), (-1.5, 2.5)], samples=[33j, 29j], mode="nearest")
    rng = _rng(4)
    x, y = rng.uniform(-3, 3, 2000), rng.uniform(-2.5, 3.5, 2000)
    u = (x - -2) / g.spacing[0]
    v = (y - -1.5) / g.spacing[1]
    ref = [
        ndimage.map_coordinates(
            np.ascontiguousarray(g.data[:, :, c]), [u, v], order=1, mode="nearest"
        )
        for c in range(3)
    ]
    d, grad = g(x, y, compute_gradient=True)
    np.testing.assert_allclose(d, ref[0], rtol=0, atol=1e-12)
    np.testing.assert_allclose(grad, np.stack(ref[1:], axis=1), rtol=0, atol=1e-12)


@pytest.mark.parametrize("gradient", GRADIENTS)
def test_float32_storage_stays_within_its_stated_error(circle, gradient):
    kw = dict(bounds=[(-2, 2), (-2, 2)], samples=[61, 61], gradient=gradient)
    g64 = GridSDF(circle, dtype=np.float64, **kw)
    g32 = GridSDF(circle, dtype="float32", **kw)
    assert g32.dtype == np.float32 and g32.data.dtype == np.float32
    assert g32.nbytes * 2 == g64.nbytes
    rng = _rng(5)
    x, y = rng.uniform(-2, 2, 5000), rng.uniform(-2, 2, 5000)
    d64, gr64 = g64(x, y, compute_gradient=True)
    d32, gr32 = g32(x, y, compute_gradient=True)
    assert d32.dtype == np.float64 and gr32.dtype == np.float64
    big = np.abs(g64.values).max()
    assert np.abs(d32 - d64).max() <= EPS32 * big * (1 + 1e-9)
    assert np.abs(d32 - d64).max() > 0  # really rounded
    if gradient == "stored":
        bound = EPS32 * np.abs(g64.data[:, :, 1:]).max()
    else:  # central differences: eps*M/h; second-order one-sided on the edges: 4 eps*M/h
        bound = 4 * EPS32 * big / min(g64.spacing)
    assert np.abs(gr32 - gr64).max() <= bound * (1 + 1e-9)


@pytest.mark.parametrize("mode", MODES)
@pytest.mark.parametrize("gradient", GRADIENTS)
@pytest.mark.parametrize("n", [9, PARALLEL_MIN_POINTS + 3])
def test_non_finite_points_give_nan(circle, mode, gradient, n):
    g = GridSDF(circle, samples=[11, 11], mode=mode, gradient=gradient)
    rng = _rng(6)
    x, y = rng.uniform(-2, 2, n), rng.uniform(-2, 2, n)
    bad = np.zeros(n, bool)
    bad[[0, 3, 5, 7]] = True
    x[0], y[3], x[5], y[7] = np.nan, np.inf, -np.inf, np.nan
    d, grad = g(x, y, compute_gradient=True)
    assert np.all(np.isnan(d[bad])) and np.all(np.isnan(grad[bad]))
    assert np.all(np.isfinite(d[~bad])) and np.all(np.isfinite(grad[~bad]))
    dv = g(x, y)
    assert np.all(np.isnan(dv[bad])) and np.array_equal(dv[~bad], d[~bad])


def test_query_shapes_follow_function_conventions(circle):
    g = GridSDF(circle, samples=[11, 11])
    assert np.shape(g(0.3, 0.2)) == () and isinstance(g(0.3, 0.2), np.float64)
    assert g(0.3, 0.2, compute_gradient=True)[1].shape == (2,)
    assert g(np.array([0.3]), 0.2).shape == (1,)
    d, grad = g(np.zeros((3, 4)), np.ones((3, 4), dtype=np.float32), compute_gradient=True)
    assert d.shape == (3, 4) and grad.shape == (3, 4, 2) and d.dtype == np.float64
    assert g(np.array([]), np.array([])).shape == (0,)
    with pytest.raises(ValueError, match="same shape"):
        g(np.zeros(3), np.zeros(4))
    with pytest.raises(TypeError, match="real numbers"):
        g(np.array(["a"]), np.array(["b"]))


def test_serial_and_parallel_paths_agree(circle):
    g = GridSDF(circle, samples=[31, 31], gradient="fd", mode="nearest")
    rng = _rng(8)
    n = 3 * PARALLEL_MIN_POINTS
    x, y = rng.uniform(-2.5, 2.5, n), rng.uniform(-2.5, 2.5, n)
    d, grad = g(x, y, compute_gradient=True)
    parts = [g(x[i : i + 1000], y[i : i + 1000], compute_gradient=True) for i in range(0, n, 1000)]
    np.testing.assert_array_equal(d, np.concatenate([p[0] for p in parts]))
    np.testing.assert_array_equal(grad, np.concatenate([p[1] for p in parts]))


@pytest.mark.parametrize("gradient", GRADIENTS)
@pytest.mark.parametrize("dtype", DTYPES)
def test_memory_per_node(circle, gradient, dtype):
    g = GridSDF(circle, samples=[13, 7], gradient=gradient, dtype=dtype)
    per = BYTES_PER_NODE[(gradient, np.dtype(dtype).name)]
    assert (
        g.bytes_per_node
        == per
        == {("stored", 8): 24, ("stored", 4): 12, ("fd", 8): 8, ("fd", 4): 4}[
            (gradient, np.dtype(dtype).itemsize)
        ]
    )
    assert g.nbytes == 13 * 7 * per == g.data.nbytes
    assert g.data.flags.c_contiguous
    assert g.data.shape == ((13, 7, 3) if gradient == "stored" else (13, 7))


def test_interpolant_is_sqrt2_lipschitz(circle):
    # The documented bound for conservative advancement: each partial derivative of the
    # bilinear interpolant of a 1-Lipschitz SDF is a blend of node differences <= 1.
    f = circle | sdf.Box(minc=[-1.5, 0.2], maxc=[-0.4, 1.1])
    g = GridSDF(f, samples=[17, 23])
    rng = _rng(10)
    p = rng.uniform(-2, 2, (20_000, 2))
    q = p + rng.normal(0, 0.2, p.shape)
    q = np.clip(q, -2, 2)
    dist = np.hypot(*(p - q).T)
    change = np.abs(g(p[:, 0], p[:, 1]) - g(q[:, 0], q[:, 1]))
    ratio = change[dist > 0] / dist[dist > 0]
    assert ratio.max() <= math.sqrt(2) * (1 + 1e-9)
    assert ratio.max() > 1.05  # the bound is approached: the grid is not 1-Lipschitz


# -- the numba sampler contract (used by compiled particle loops) -----------------------------


@njit
def _sample_all(sampler, data, xs, ys):
    n = xs.shape[0]
    out = np.empty((n, 3))
    ins = np.empty(n, dtype=np.bool_)
    for k in range(n):
        d, gx, gy, inside = sampler(data, xs[k], ys[k])
        out[k, 0], out[k, 1], out[k, 2] = d, gx, gy
        ins[k] = inside
    return out, ins


@njit
def _sample_with_fallback(sampler, data, exact, xs, ys):
    n = xs.shape[0]
    out = np.empty((n, 3))
    for k in range(n):
        d, gx, gy, inside = sampler(data, xs[k], ys[k])
        if not inside:
            d, gx, gy = exact(xs[k], ys[k])
        out[k, 0], out[k, 1], out[k, 2] = d, gx, gy
    return out


@pytest.mark.parametrize("gradient", GRADIENTS)
@pytest.mark.parametrize("dtype", DTYPES)
def test_sampler_contract_from_njit_code(circle, gradient, dtype):
    rng = _rng(9)
    x, y = rng.uniform(-3, 3, 400), rng.uniform(-3, 3, 400)
    x[0], y[1] = np.nan, np.inf
    near = GridSDF(
        circle,
        bounds=[(-2, 2), (-2, 2)],
        samples=[21, 21],
        mode="nearest",
        gradient=gradient,
        dtype=dtype,
    )
    vals, inside = _sample_all(near.sampler, near.sampler_data, x, y)
    np.testing.assert_array_equal(inside, near.contains(x, y))
    d, grad = near(x, y, compute_gradient=True)
    np.testing.assert_array_equal(vals[:, 0], d)
    np.testing.assert_array_equal(vals[:, 1:], grad)
    # mode='exact': fall back to the exact per-point function where the sampler says outside.
    ex = GridSDF(
        circle, bounds=[(-2, 2), (-2, 2)], samples=[21, 21], gradient=gradient, dtype=dtype
    )
    vals = _sample_with_fallback(ex.sampler, ex.sampler_data, ex.exact.point_fn, x, y)
    d, grad = ex(x, y, compute_gradient=True)
    np.testing.assert_array_equal(vals[:, 0], d)
    np.testing.assert_array_equal(vals[:, 1:], grad)


# -- measure_error ----------------------------------------------------------------------------


def test_measure_error_fields(circle):
    g = GridSDF(circle, samples=[21, 21])
    e = measure_error(g, n=3000, band=0.2, seed=1)
    assert isinstance(e, GridError)
    assert e.n == 3000 and 0 < e.band_n < 3000 and e.band == 0.2
    assert 0 < e.value_rms <= e.value_max and 0 < e.angle_rms_deg <= e.angle_max_deg <= 180
    assert e.band_value_max <= e.value_max
    assert measure_error(g, n=3000, band=0.2, seed=1) == e  # reproducible
    assert e.as_dict()["band_n"] == e.band_n
    pts = measure_error(g, points=(np.array([0.3, 0.4]), np.array([0.1, 5.0])), band=1e-9)
    assert pts.n == 2 and pts.band_n == 0 and math.isnan(pts.band_value_max)
    with pytest.raises(TypeError, match="GridSDF"):
        measure_error(circle)
    with pytest.raises(ValueError, match="band"):
        measure_error(g, band=-1)
    with pytest.raises(ValueError, match="n="):
        measure_error(g, n=0)


# -- bad input --------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "kwargs, exc, match",
    [
        (dict(bounds=[(2, -2), (-2, 2)]), ValueError, r"bounds.*x range \(2.0, -2.0\)"),
        (dict(bounds=[(-2, 2), (1, 1)]), ValueError, r"bounds.*y range \(1.0, 1.0\)"),
        (dict(bounds=[(-2, np.inf), (-2, 2)]), ValueError, "bounds must be finite"),
        (dict(bounds=[(-2, np.nan), (-2, 2)]), ValueError, "bounds must be finite"),
        (dict(bounds=[(-2, 2)]), ValueError, "bounds must be two"),
        (dict(bounds=[(-2, 2, 3), (-2, 2)]), ValueError, "bounds must be two"),
        (dict(bounds=5), TypeError, "bounds"),
        (dict(bounds=[("a", 2), (-2, 2)]), TypeError, "bounds must hold real numbers"),
        (dict(samples=[1, 10]), ValueError, r"at least 2.*samples=\[1, 10\]"),
        (dict(samples=[10j, 1j]), ValueError, "at least 2"),
        (dict(samples=[10, 10, 10]), ValueError, "2 entries"),
        (dict(samples=10), TypeError, "samples"),
        (dict(samples="ab"), TypeError, "samples"),
        (dict(samples=[10.0, 10]), TypeError, "samples entries"),
        (dict(samples=[True, 10]), TypeError, "samples entries"),
        (dict(samples=[10.5j, 10j]), ValueError, "whole node count"),
        (dict(samples=[1 + 10j, 10j]), ValueError, "whole node count"),
        (
            dict(mode="clamp"),
            ValueError,
            r"mode must be one of 'exact', 'nearest', got mode='clamp'",
        ),
        (dict(mode=None), ValueError, "mode must be"),
        (dict(gradient="central"), ValueError, r"gradient must be one of .*gradient='central'"),
        (dict(dtype=np.int32), ValueError, "dtype must be np.float64 or np.float32"),
        (dict(dtype=np.float16), ValueError, "dtype must be"),
        (dict(dtype="nonsense"), ValueError, "dtype must be"),
    ],
)
def test_bad_parameters_are_rejected(circle, kwargs, exc, match):
    with pytest.raises(exc, match=match):
        GridSDF(circle, **kwargs)


@pytest.mark.parametrize("f", [None, lambda x, y: x, "circle", np.zeros(3)])
def test_f_must_be_an_sdf(f):
    with pytest.raises(TypeError, match="f must be a fastsdf SDF"):
        GridSDF(f)


def test_grid_of_a_grid_is_rejected(circle):
    with pytest.raises(TypeError, match="f must be a fastsdf SDF"):
        GridSDF(GridSDF(circle, samples=[5, 5]))


@pytest.mark.parametrize("gradient", GRADIENTS)
def test_non_finite_node_values_are_rejected(gradient):
    x, y = cg.Symbol("x"), cg.Symbol("y")
    f = cg.Function(cg.sym_log(x) + y, [x, y])  # NaN for x < 0, -inf at x = 0
    with pytest.raises(ValueError, match=r"non-finite value at grid node \(0, 0\) = \(-2.0"):
        GridSDF(f, bounds=[(-2, 2), (-2, 2)], samples=[5, 5], gradient=gradient)
    GridSDF(f, bounds=[(0.5, 2), (-2, 2)], samples=[5, 5], gradient=gradient)  # fine there


def test_float32_overflow_at_nodes_is_rejected():
    x, y = cg.Symbol("x"), cg.Symbol("y")
    f = cg.Function(x * 1e300 + y, [x, y])
    GridSDF(f, samples=[3, 3])  # float64 holds it
    with pytest.raises(ValueError, match="overflows float32"):
        GridSDF(f, samples=[3, 3], dtype=np.float32)
