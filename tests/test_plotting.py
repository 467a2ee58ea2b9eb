"""Plotting SDFs: plot_sdf."""

import itertools

import matplotlib

matplotlib.use("Agg")

import numpy as np  # noqa: E402
import pytest  # noqa: E402
from matplotlib.backends.backend_agg import FigureCanvasAgg  # noqa: E402
from matplotlib.colors import to_rgba  # noqa: E402
from matplotlib.figure import Figure  # noqa: E402

import fastsdf as sdf  # noqa: E402
from fastsdf import plotting  # noqa: E402
from fastsdf.plotting import BACKGROUND_COLOR, SOLID_COLOR, plot_sdf  # noqa: E402

BOUNDS = [(-2, 2), (-2, 2)]


@pytest.fixture(scope="module")
def circle():
    return sdf.Circle(center=[0.3, -0.2], radius=1.0)


def new_axes(figsize=(4, 4)):
    fig = Figure(figsize=figsize, dpi=50)
    FigureCanvasAgg(fig)
    return fig, fig.add_subplot()


class NumpyCircle:
    """A duck-typed SDF (like a GridSDF): callable, returns flat arrays, not a Function."""

    def __call__(self, x, y, compute_gradient=False):
        x, y = np.ravel(x), np.ravel(y)
        r = np.hypot(x, y)
        d = r - 1.0
        if compute_gradient:
            safe = np.where(r > 0, r, 1.0)
            return d, np.stack([x / safe, y / safe], axis=-1)
        return d


# ---------------------------------------------------------------------------------------------
# plot_sdf

@pytest.mark.parametrize("isolines,quiver,labels,filled", list(itertools.product(
    ["all", "zero", None, False], [True, False], [True, False], [True, False])))
def test_plot_sdf_every_option_creates_expected_artists(circle, isolines, quiver, labels, filled):
    fig, ax = new_axes()
    out = plot_sdf(fig, ax, circle, bounds=BOUNDS, samples=40, show_quiver=quiver,
                   show_isolines=isolines, show_isolabels=labels, filled=filled)
    expected = set()
    if isolines:
        expected.add("contour")
        if labels:
            expected.add("labels")
    if quiver:
        expected.add("quiver")
    if filled:
        expected.add("fill")
    assert set(out) == expected
    # The notebook's look: limits = bounds, equal aspect, no tick labels.
    assert ax.get_xlim() == (-2, 2) and ax.get_ylim() == (-2, 2)
    assert ax.get_aspect() == 1.0
    fig.canvas.draw()
    assert all(not t.get_visible() or t.get_text() == "" for t in ax.get_xticklabels())
    assert all(not t.get_visible() or t.get_text() == "" for t in ax.get_yticklabels())
    if isolines == "zero":
        assert list(out["contour"].levels) == [0.0]
    if isolines == "all":
        assert len(out["contour"].levels) > 3
    if "labels" in out:
        assert len(out["labels"]) > 0
    if quiver:
        assert out["quiver"].N == 20 * 20  # every 2nd of 40 samples per axis
    if filled:
        fill = out["fill"]
        assert np.allclose(fill.get_facecolor(), [to_rgba(SOLID_COLOR), to_rgba(BACKGROUND_COLOR)])
        assert fill.get_zorder() < 2  # beneath the lines


def test_zero_contour_lies_on_the_surface(circle):
    fig, ax = new_axes()
    samples = 200
    spacing = 4.0 / (samples - 1)
    cs = plot_sdf(fig, ax, circle, samples=samples, show_quiver=False,
                  show_isolines="zero")["contour"]
    verts = np.concatenate([p.vertices for p in cs.get_paths() if len(p.vertices)])
    assert len(verts) > 100
    d = circle(verts[:, 0], verts[:, 1])
    assert np.max(np.abs(d)) < 0.1 * spacing
    # ... and go all the way round the circle.
    angles = np.arctan2(verts[:, 1] + 0.2, verts[:, 0] - 0.3)
    assert np.ptp(angles) > 6.0


def test_zero_contour_of_a_box_and_filled_region_match_the_sign():
    box = sdf.Box(minc=[-1, -0.5], maxc=[0.7, 1.2])
    fig, ax = new_axes()
    out = plot_sdf(fig, ax, box, samples=101, show_quiver=False, show_isolines="zero", filled=True)
    verts = np.concatenate([p.vertices for p in out["contour"].get_paths() if len(p.vertices)])
    assert np.max(np.abs(box(verts[:, 0], verts[:, 1]))) < 1e-9  # piecewise linear: exact
    # The solid (first) fill level's polygons contain the inside points, not outside ones.
    solid = out["fill"].get_paths()[0]
    assert solid.contains_point((0.0, 0.0)) and not solid.contains_point((1.5, 1.5))


def test_quiver_shows_gradient_coloured_by_distance(circle):
    fig, ax = new_axes()
    q = plot_sdf(fig, ax, circle, samples=21, show_isolines=None)["quiver"]
    xy = q.XY
    d, g = circle(xy[:, 0], xy[:, 1], compute_gradient=True)
    assert np.allclose(q.U, g[:, 0]) and np.allclose(q.V, g[:, 1])
    assert np.allclose(q.get_array(), d)


def test_plot_sdf_accepts_any_callable_sdf():
    fig, ax = new_axes()
    f = NumpyCircle()
    out = plot_sdf(fig, ax, f, samples=(60, 50), show_isolines="zero", filled=True)
    verts = np.concatenate([p.vertices for p in out["contour"].get_paths()])
    assert np.max(np.abs(np.hypot(verts[:, 0], verts[:, 1]) - 1.0)) < 0.01
    assert out["quiver"].N == 20 * 25  # every 3rd of 60 along x, every 2nd of 50 along y
    fig.canvas.draw()


def test_plot_sdf_with_nan_values_does_not_fail():
    def holey(x, y, compute_gradient=False):
        d = np.hypot(x, y) - 1.0
        d = np.where(x > 1.5, np.nan, d)
        return (d, np.stack([np.ones_like(d), np.zeros_like(d)], -1)) if compute_gradient else d
    fig, ax = new_axes()
    out = plot_sdf(fig, ax, holey, samples=30, filled=True)
    assert set(out) == {"contour", "quiver", "fill"}
    fig.canvas.draw()


def test_plot_sdf_nothing_to_show_does_not_evaluate():
    def boom(x, y, compute_gradient=False):
        raise AssertionError("evaluated")
    fig, ax = new_axes()
    assert plot_sdf(fig, ax, boom, show_quiver=False, show_isolines=None) == {}
    assert ax.get_xlim() == (-2, 2)


@pytest.mark.parametrize("kwargs,name", [
    (dict(show_isolines="some"), "show_isolines"),
    (dict(show_isolines=True), "show_isolines"),
    (dict(show_isolines=0.0), "show_isolines"),
    (dict(bounds=[(2, -2), (-2, 2)]), "bounds"),
    (dict(bounds=[(-2, 2), (1, 1)]), "bounds"),
    (dict(bounds=[(-2, 2)]), "bounds"),
    (dict(bounds=[(-2, np.nan), (-2, 2)]), "bounds"),
    (dict(bounds="big"), "bounds"),
    (dict(samples=1), "samples"),
    (dict(samples=0), "samples"),
    (dict(samples=2.5), "samples"),
    (dict(samples=True), "samples"),
    (dict(samples=(10, 1)), "samples"),
    (dict(samples=(10, 10, 10)), "samples"),
])
def test_plot_sdf_rejects_bad_arguments(kwargs, name):
    fig, ax = new_axes()
    with pytest.raises(ValueError, match=name) as info:
        plot_sdf(fig, ax, NumpyCircle(), **kwargs)
    assert repr(next(iter(kwargs.values())))[:3] in str(info.value)


def test_plot_sdf_is_exported():
    assert sdf.plot_sdf is plotting.plot_sdf
    assert "plot_sdf" in sdf.__all__
