"""The angle of repose measured on synthetic heaps whose slopes are known."""

import math

import numpy as np
import pytest

from fastsdf.granular import repose_angle


def _packed_triangle(left_deg, right_deg, radius=0.5, base=40.0):
    """Discs on a square lattice (spacing one diameter) filling a triangle on the floor y = 0
    whose flanks rise at ``left_deg`` and ``right_deg``, apex at x = 0: a disc is kept where
    its top stays under the triangle's surface."""
    tl, tr = math.tan(math.radians(left_deg)), math.tan(math.radians(right_deg))
    apex = base * tl * tr / (tl + tr)  # the height where the two flanks meet
    x0 = -apex / tl
    xs = np.arange(x0 + radius, apex / tr, 2 * radius)
    ys = np.arange(radius, apex, 2 * radius)
    gx, gy = np.meshgrid(xs, ys)
    surface = np.minimum(apex + tl * gx, apex - tr * gx)
    keep = gy + radius <= surface
    return np.column_stack([gx[keep], gy[keep]])


@pytest.mark.parametrize("left,right", [(30.0, 30.0), (20.0, 35.0), (12.0, 25.0)])
def test_points_on_two_lines_give_their_angles_exactly(left, right):
    # one point per bin, exactly on each flank: the fit is the flank
    x = np.linspace(-10, 10, 81)
    apex = 10 * math.tan(math.radians(left)) * math.tan(math.radians(right))
    apex /= math.tan(math.radians(left)) + math.tan(math.radians(right))
    y = np.minimum(
        apex + math.tan(math.radians(left)) * x, apex - math.tan(math.radians(right)) * x
    )
    y = np.maximum(y, 0.0)
    res = repose_angle(np.column_stack([x, y]), 0.0, floor=0.0, bin_width=0.25)
    assert res.left == pytest.approx(left, abs=1e-9)
    assert res.right == pytest.approx(right, abs=1e-9)
    assert res.mean == pytest.approx((left + right) / 2, abs=1e-9)
    # the lines are the flanks: slope tan(angle), through the apex at x = 0
    (sl, il), (sr, ir) = res.lines
    assert sl == pytest.approx(math.tan(math.radians(left)), rel=1e-9)
    assert sr == pytest.approx(-math.tan(math.radians(right)), rel=1e-9)
    assert il == pytest.approx(apex, rel=1e-9) and ir == pytest.approx(apex, rel=1e-9)


@pytest.mark.parametrize("left,right", [(30.0, 30.0), (20.0, 35.0)])
def test_a_packed_triangle_of_discs_measures_its_flanks_within_two_degrees(left, right):
    pts = _packed_triangle(left, right)
    res = repose_angle(pts, 0.5)  # floor: the lowest point of the surface
    assert abs(res.left - left) < 2.0 and abs(res.right - right) < 2.0, res
    # shifted up and sideways: the same heap
    moved = repose_angle(pts + [7.3, 4.1], 0.5)
    assert moved.left == pytest.approx(res.left, abs=1.0)
    assert moved.right == pytest.approx(res.right, abs=1.0)


def test_two_summits_are_measured_on_their_outer_flanks():
    a = _packed_triangle(25.0, 25.0)  # from x = -20 to 20
    b = a + [32.0, 0.0]  # two heaps whose inner flanks meet in a valley at x = 16
    res = repose_angle(np.concatenate([a, b]), 0.5)
    assert abs(res.left - 25.0) < 2.0 and abs(res.right - 25.0) < 2.0, res
    # the outer flanks' lines: they meet the floor left of the first summit and right of the second
    (sl, il), (sr, ir) = res.lines
    assert -il / sl < 0.0 and -ir / sr > 32.0


def test_a_flat_layer_has_no_flank():
    x = np.column_stack([np.arange(0.0, 20.0), np.full(20, 0.5)])
    res = repose_angle(x, 0.5)
    assert math.isnan(res.left) and math.isnan(res.right) and math.isnan(res.mean)
    assert all(math.isnan(v) for line in res.lines for v in line)
    empty = repose_angle(np.zeros((0, 2)), 0.5)
    assert math.isnan(empty.left) and math.isnan(empty.right)


@pytest.mark.parametrize(
    "args,kwargs,match",
    [
        ((np.zeros((3, 3)), 0.5), {}, "positions must have shape"),
        ((np.array([[0.0, math.nan]]), 0.5), {}, "finite"),
        ((np.zeros((2, 2)), -0.5), {}, "radius"),
        ((np.zeros((2, 2)), 0.5), {"bin_width": 0.0}, "bin_width"),
        ((np.zeros((2, 2)), 0.0), {}, "bin_width"),
    ],
)
def test_bad_input_is_named(args, kwargs, match):
    with pytest.raises(ValueError, match=match):
        repose_angle(*args, **kwargs)
