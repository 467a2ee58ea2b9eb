"""Adding an operation is one entry of the op table (fastsdf.expr.ops.OPS): a test operation,
registered here and nowhere else, runs through the NumPy reference, the compiled kernel (serial
and parallel, value and gradient), ``backend='numpy'``, the CUDA target (under numba-cuda's
simulator without a GPU), interval bounds and the default call."""

import numpy as np
import pytest
from conftest import HAS_NUMBA_CUDA

import fastsdf as sdf
from fastsdf.expr.graph import Expr, Symbol, evaluate_numpy, sym_min
from fastsdf.expr.interval import bounds
from fastsdf.expr.ops import OPS, Op

X, Y = Symbol("x"), Symbol("y")
EPS = np.finfo(np.float64).eps


def _iv_cube(node, lo, hi):
    """x**3 is increasing; the bound is widened by a few ulps for the rounding of a * a * a."""
    lo3, hi3 = lo[0] ** 3, hi[0] ** 3
    return lo3 - 4 * EPS * np.abs(lo3), hi3 + 4 * EPS * np.abs(hi3)


CUBE = Op(
    "cube_test",
    1,
    fmt=lambda node, s: f"cube_test({s[0]})",
    np=lambda node, av, g: (av[0] * av[0] * av[0], [3.0 * av[0] * av[0]] if g else None),
    emit=lambda em, out, node, a, r: (
        em.assign(out, r, a[0].v * a[0].v * a[0].v),
        [3.0 * a[0].v * a[0].v],
    )[1],
    interval=_iv_cube,
)


@pytest.fixture
def cube(monkeypatch):
    monkeypatch.setitem(OPS, "cube_test", CUBE)
    return lambda e: Expr("cube_test", (e,))


def test_a_new_operation_runs_through_every_path(cube):
    u = 0.5 * X - 0.2
    e = sym_min(cube(u) + Y - 0.1, sdf.Circle([0.7, -0.4], 0.3).f)
    f = sdf.Function(e, [X, Y])
    rng = np.random.default_rng(3)
    x, y = rng.uniform(-2, 2, (2, 6000))
    # the analytic value and gradient
    c = (0.5 * x - 0.2) ** 3 + y - 0.1
    r = np.hypot(x - 0.7, y + 0.4)
    circle = r - 0.3
    d_true = np.minimum(c, circle)
    g_true = np.where(
        (c <= circle)[:, None],
        np.stack([1.5 * (0.5 * x - 0.2) ** 2, np.ones_like(x)], 1),
        np.stack([(x - 0.7) / r, (y + 0.4) / r], 1),
    )
    far = np.abs(c - circle) > 1e-9  # away from the kink, where the gradient is one-sided
    d_ref, (gx, gy) = evaluate_numpy(e, {"x": x, "y": y}, compute_gradient=True)
    np.testing.assert_allclose(d_ref, d_true, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(np.stack([gx, gy], 1)[far], g_true[far], rtol=1e-12, atol=1e-12)
    paths = [("kernel", 100), ("kernel", 6000), ("numpy", 6000)]
    for backend, n in paths + ([("cuda", 300)] if HAS_NUMBA_CUDA else []):
        d, g = f(x[:n], y[:n], compute_gradient=True, backend=backend)
        np.testing.assert_allclose(d, d_ref[:n], rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(g[far[:n]], g_true[:n][far[:n]], rtol=1e-9, atol=1e-9)
        np.testing.assert_allclose(f(x[:n], y[:n], backend=backend), d, rtol=0, atol=0)
    # interval bounds hold every value computed in each box
    edges = np.linspace(-2, 2, 9)
    lo_x, lo_y = np.meshgrid(edges[:-1], edges[:-1])
    lo, hi = bounds(
        e, {"x": (lo_x.ravel(), lo_x.ravel() + 0.5), "y": (lo_y.ravel(), lo_y.ravel() + 0.5)}
    )
    d = f(x, y, backend="kernel")
    box = np.floor((x + 2) / 0.5).astype(int).clip(0, 7) + 8 * np.floor((y + 2) / 0.5).astype(
        int
    ).clip(0, 7)
    assert np.all(lo[box] <= d) and np.all(d <= hi[box])
    # the default call answers with the kernel's bits
    d_auto, g_auto = f(x, y, compute_gradient=True, backend="auto")
    d_k, g_k = f(x, y, compute_gradient=True, backend="kernel")
    assert d_auto.tobytes() == d_k.tobytes() and g_auto.tobytes() == g_k.tobytes()
