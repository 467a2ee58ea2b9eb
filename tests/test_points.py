"""How every evaluator takes coordinates: x and y arrays of one shape, arrays that broadcast
(``f(x, 0.0)``), or one array of points along a last axis of length 2 (``f(points)``)."""

import numpy as np
import pytest

import fastsdf as sdf
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
    assert d[2, 1] == world(1.0, row[0, 1])[0]


def test_bad_point_shapes_are_named():
    with pytest.raises(ValueError, match=r"last axis of length 2.*\(5, 3\)"):
        as_points(np.zeros((5, 3)))
    with pytest.raises(ValueError, match=r"same shape.*\(3,\).*\(4,\)"):
        as_points(np.zeros(3), np.zeros(4))
    with pytest.raises(TypeError, match="real numbers"):
        as_points(np.array(["a"]), 0.0)
