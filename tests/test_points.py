"""How every evaluator takes coordinates: x and y arrays of one shape, arrays that broadcast
(``f(x, 0.0)``), or one array of points along a last axis of length 2 (``f(points)``)."""

import numpy as np
import pytest
from conftest import HAS_NUMBA_CUDA

import fastsdf as sdf
from fastsdf.backends import request
from fastsdf.expr import points
from fastsdf.expr.points import as_points


@pytest.fixture(scope="module")
def world():
    return sdf.Circle([0.2, 0.1], 0.7) | sdf.Box([-1, -1], [0, -0.5])


def test_points_array_equals_separate_coordinates(world):
    p = np.random.default_rng(0).uniform(-2, 2, (50, 2))
    d, g = world(p, compute_gradient=True)
    d2, g2 = world(p[:, 0], p[:, 1], compute_gradient=True)
    np.testing.assert_array_equal(d, d2)
    np.testing.assert_array_equal(g, g2)
    grid = sdf.GridSDF(world, samples=[41j, 41j])
    np.testing.assert_array_equal(grid(p), grid(p[:, 0], p[:, 1]))
    # Points on a grid of shape (4, 5, 2) give values of shape (4, 5).
    assert world(p[:20].reshape(4, 5, 2)).shape == (4, 5)


def test_scalars_broadcast_against_arrays(world):
    x = np.linspace(-2, 2, 9)
    np.testing.assert_array_equal(world(x, 0.0), world(x, np.zeros_like(x)))
    np.testing.assert_array_equal(world(0.3, x), world(np.full_like(x, 0.3), x))
    col, row = np.linspace(-1, 1, 3)[:, None], np.linspace(-1, 1, 4)[None, :]
    d = world(col, row)
    assert d.shape == (3, 4)
    assert d[2, 1] == world(1.0, row[0, 1])


def test_bad_point_shapes_are_named():
    with pytest.raises(ValueError, match=r"last axis of length 2.*\(5, 3\)"):
        as_points(np.zeros((5, 3)))
    with pytest.raises(ValueError, match=r"same shape.*\(3,\).*\(4,\)"):
        as_points(np.zeros(3), np.zeros(4))
    with pytest.raises(TypeError, match="real numbers"):
        as_points(np.array(["a"]), 0.0)


def test_each_call_validates_its_points_once(world, monkeypatch):
    """A call's coordinates are checked and flattened once, whichever evaluator answers: the
    kernel (serial, parallel, pruned), NumPy, the CUDA target (NumPy points copied to the
    device), a grid (and its exact fallback outside its samples) and a narrow band."""
    calls = []

    def counting(name, fn):
        def wrapped(*args, **kwargs):
            calls.append(name)
            return fn(*args, **kwargs)

        return wrapped

    monkeypatch.setattr(request, "as_points", counting("host", request.as_points))
    monkeypatch.setattr(request, "device_points", counting("device", request.device_points))
    monkeypatch.setattr(points, "as_points", counting("inner", points.as_points))
    grid = sdf.GridSDF(world, bounds=[(-1, 1), (-1, 1)], samples=[41j, 41j], mode="exact")
    band = sdf.NarrowBandGridSDF(
        world, bounds=[(-1.5, 1.5), (-1.5, 1.5)], band=0.2, samples=[257, 257]
    )
    p = np.random.default_rng(1).uniform(-2, 2, (5000, 2))  # some outside the grid
    cases = {
        "kernel serial": lambda: world(p[:100], compute_gradient=True, backend="kernel"),
        "kernel parallel": lambda: world(p[:, 0], p[:, 1], backend="kernel"),
        "kernel pruned": lambda: world(p, compute_gradient=True, prune=True),
        "numpy": lambda: world(p, compute_gradient=True, backend="numpy"),
        "grid": lambda: grid(p, compute_gradient=True),
        "band": lambda: band(p),
    }
    if HAS_NUMBA_CUDA:
        cases["cuda"] = lambda: world(p[:64], compute_gradient=True, backend="cuda")
    for name, call in cases.items():
        calls.clear()
        call()
        expected = ["device", "inner"] if name == "cuda" else ["host"]
        assert calls == expected, name
