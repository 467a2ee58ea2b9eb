"""The angle of repose measured on synthetic heaps whose slopes are known; flow rates and
Beverloo fits of synthetic discharges whose rates and laws are known."""

import math

import numpy as np
import pytest

from fastsdf.granular import BeverlooFit, beverloo_fit, flow_rate, repose_angle


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


def test_flow_rate_is_the_slope_of_a_staircase_inside_its_window():
    """Grains leaving one by one at rate 7 (a staircase sampled at 0.1), after a start at
    rate 2 and before a tail at rate 1: the window [low, high] of counts sees only the 7, to
    the staircase's rounding."""
    t = np.arange(0.0, 60.0, 0.1)
    flow = np.where(t < 5, 2 * t, np.where(t < 40, 10 + 7 * (t - 5), 255 + (t - 40)))
    counts = np.floor(flow)
    assert flow_rate(t, counts, low=20, high=240) == pytest.approx(7.0, rel=5e-3)
    assert flow_rate(t, counts, after=10.0, high=240) == pytest.approx(7.0, rel=5e-3)
    assert flow_rate(t, counts) < 6.0  # the whole run mixes the three rates


@pytest.mark.parametrize("c,k,b", [(1.1, 1.7, 1.5), (0.6, 2.5, 1.3), (2.0, 1.0, 1.8)])
def test_beverloo_fit_recovers_the_law_it_is_given(c, k, b):
    widths = np.array([4.0, 5.0, 6.5, 8.0, 10.0])
    rates = BeverlooFit(c, k, b).rate(widths, gravity=2.0)
    assert rates == pytest.approx(c * math.sqrt(2.0) * (widths - k) ** b)
    free = beverloo_fit(widths, rates, gravity=2.0)
    assert (free.C, free.k, free.exponent) == pytest.approx((c, k, b), rel=1e-6)
    known_k = beverloo_fit(widths[:3], rates[:3], gravity=2.0, k=k)
    assert (known_k.C, known_k.exponent) == pytest.approx((c, b), rel=1e-9)
    known_b = beverloo_fit(widths[:3], rates[:3], gravity=2.0, exponent=b)
    assert (known_b.C, known_b.k) == pytest.approx((c, k), rel=1e-9)
    # the grains' diameter scales k: slots of 2 diameters' worth at d = 2
    in_d = beverloo_fit(widths * 2.0, rates, gravity=2.0, diameter=2.0, exponent=b)
    assert in_d.k == pytest.approx(k, rel=1e-9)


def test_beverloo_fit_with_a_wrong_k_biases_the_exponent_the_expected_way():
    # a true k of 2.2 fitted with k = 1.5: the slots seem wider, the exponent larger
    widths = np.array([5.0, 6.0, 7.0])
    rates = BeverlooFit(1.0, 2.2, 1.5).rate(widths)
    b = beverloo_fit(widths, rates, k=1.5).exponent
    expected = 1.5 * math.log(4.8 / 2.8) / math.log(5.5 / 3.5)  # two-point slope, nearly linear
    assert b == pytest.approx(expected, rel=2e-2)
    assert b > 1.5


@pytest.mark.parametrize(
    "call,match",
    [
        (lambda: flow_rate([0, 1, 2], [0, 1]), "one length"),
        (lambda: flow_rate([0, 1, 2, 3], [0, 1, 2, 3], low=2), "needs 3 samples"),
        (lambda: beverloo_fit([4, 5, 6], [1, 2, 3]), "needs 4 distinct widths"),
        (lambda: beverloo_fit([4, 5], [1, 0], k=1.5), "rates must be > 0"),
        (lambda: beverloo_fit([4, 5], [1, 2], k=4.5), "no gap"),
    ],
)
def test_bad_flow_input_is_named(call, match):
    with pytest.raises(ValueError, match=match):
        call()
