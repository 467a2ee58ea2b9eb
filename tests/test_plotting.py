"""Plotting and particle rendering: plot_sdf, density_image, draw_particles, render_frame."""

import itertools

import matplotlib

matplotlib.use("Agg")

import matplotlib.image as mpimg
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.collections import EllipseCollection
from matplotlib.colors import to_rgb, to_rgba
from matplotlib.figure import Figure
from matplotlib.image import AxesImage

import fastsdf as sdf
from fastsdf.viz import plotting, render
from fastsdf.viz.plotting import BACKGROUND_COLOR, SOLID_COLOR, SURFACE_COLOR, plot_sdf
from fastsdf.viz.render import ParticleLayer, density_image, draw_particles, render_frame

BOUNDS = [(-2, 2), (-2, 2)]


@pytest.fixture(scope="module")
def circle():
    return sdf.Circle(center=[0.3, -0.2], radius=1.0)


@pytest.fixture(scope="module")
def world():
    """A floor (y < -1.5) with a disc on it: solid at the bottom, free space above."""
    return sdf.Halfspace(normal=[0, 1], d=-1.5) | sdf.Circle(center=[1.2, -1.2], radius=0.4)


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


@pytest.mark.parametrize(
    "isolines,quiver,labels,filled",
    list(
        itertools.product(["all", "zero", None, False], [True, False], [True, False], [True, False])
    ),
)
def test_plot_sdf_every_option_creates_expected_artists(circle, isolines, quiver, labels, filled):
    fig, ax = new_axes()
    out = plot_sdf(
        fig,
        ax,
        circle,
        bounds=BOUNDS,
        samples=40,
        show_quiver=quiver,
        show_isolines=isolines,
        show_isolabels=labels,
        filled=filled,
    )
    expected = {"ax"}
    assert out["ax"] is ax
    if isolines:
        expected.add("contour")
        if labels:
            expected.add("labels")
    if isolines == "all":
        expected.add("surface")  # the zero contour, over the coloured lines
    if quiver:
        expected.add("quiver")
    if filled:
        expected.add("fill")
    if isolines == "all" or quiver:
        expected.add("colorbar")  # by default where something is coloured by the distance
    assert set(out) == expected
    # A figure to keep by default: limits = bounds, equal aspect, ticks labelled x and y.
    assert ax.get_xlim() == (-2, 2) and ax.get_ylim() == (-2, 2)
    assert ax.get_aspect() == 1.0
    fig.canvas.draw()
    assert any(t.get_text() for t in ax.get_xticklabels())
    assert (ax.get_xlabel(), ax.get_ylabel()) == ("x", "y")
    surface = out.get("surface" if isolines == "all" else "contour") if isolines else None
    if surface is not None:  # the zero contour: a thick black line
        assert list(surface.levels) == [0.0]
        assert np.allclose(surface.get_edgecolor()[0], to_rgba(SURFACE_COLOR))
        assert surface.get_linewidth()[0] > 1.25 * matplotlib.rcParams["lines.linewidth"]
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
    cs = plot_sdf(fig, ax, circle, samples=samples, show_quiver=False, show_isolines="zero")[
        "contour"
    ]
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
    assert set(out) == {"ax", "contour", "surface", "quiver", "fill", "colorbar"}
    fig.canvas.draw()


def test_plot_sdf_nothing_to_show_does_not_evaluate():
    def boom(x, y, compute_gradient=False):
        raise AssertionError("evaluated")

    fig, ax = new_axes()
    assert plot_sdf(fig, ax, boom, show_quiver=False, show_isolines=None) == {"ax": ax}
    assert ax.get_xlim() == (-2, 2)


@pytest.mark.parametrize(
    "kwargs,name",
    [
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
        (dict(levels=0), "levels"),
        (dict(levels=[0.5, 0.1]), "levels"),
        (dict(levels=[[0.1, 0.2]]), "levels"),
        (dict(levels=[0.0, np.inf]), "levels"),
        (dict(levels="many"), "levels"),
        (dict(levels=[0.1], show_isolines="zero"), "levels"),
    ],
)
def test_plot_sdf_rejects_bad_arguments(kwargs, name):
    fig, ax = new_axes()
    with pytest.raises((ValueError, TypeError), match=name) as info:  # (malformed: a TypeError)
        plot_sdf(fig, ax, NumpyCircle(), **kwargs)
    assert repr(next(iter(kwargs.values())))[:3] in str(info.value)


def test_plot_sdf_call_forms_agree(circle):
    """plot_sdf(f), plot_sdf(f, ax=ax), plot_sdf(fig, ax, f) and plot_sdf(None, ax, f) draw the
    same contour; f(x, y) and f(p) plain callables match the Function (gradient by differences)."""
    import matplotlib.pyplot as plt

    def levels_and_quiver(out):
        return np.asarray(out["contour"].levels), np.column_stack(
            [out["quiver"].U, out["quiver"].V]
        )

    fig, ax = new_axes()
    ref = levels_and_quiver(plot_sdf(fig, ax, circle, samples=40))
    try:
        out = plot_sdf(circle, samples=40)  # a new pyplot figure
        assert out["ax"] is plt.gca()
        got = levels_and_quiver(out)
    finally:
        plt.close("all")
    np.testing.assert_array_equal(got[0], ref[0])
    np.testing.assert_allclose(got[1], ref[1])
    for call in (
        lambda a: plot_sdf(circle, ax=a, samples=40),
        lambda a: plot_sdf(None, a, circle, samples=40),
        lambda a: plot_sdf(lambda x, y: circle(x, y), ax=a, samples=40),
        lambda a: plot_sdf(lambda p: circle(p[:, 0], p[:, 1]), ax=a, samples=40),
    ):
        fig, ax = new_axes()
        got = levels_and_quiver(call(ax))
        np.testing.assert_array_equal(got[0], ref[0])
        np.testing.assert_allclose(got[1], ref[1], atol=1e-6)


def test_plot_sdf_colorbar_and_ticks(circle):
    fig, ax = new_axes()
    out = plot_sdf(circle, ax=ax, samples=40, colorbar=True, ticks=True, show_quiver=False)
    cb = out["colorbar"]
    d = circle(*np.meshgrid(np.linspace(-2, 2, 40), np.linspace(-2, 2, 40)))
    assert cb.mappable is out["contour"]
    assert np.isclose(cb.norm.vmin, d.min()) and np.isclose(cb.norm.vmax, d.max())
    assert "distance" in cb.ax.get_ylabel()
    fig.canvas.draw()
    assert ax.get_xlabel() == "x" and any(t.get_text() for t in ax.get_xticklabels())
    # Lines and arrows share the colour bar's scale.
    fig, ax = new_axes()
    out = plot_sdf(circle, ax=ax, samples=40, colorbar=True)
    assert out["quiver"].norm is out["contour"].norm
    with pytest.raises(ValueError, match="colorbar"):
        plot_sdf(circle, ax=ax, colorbar=True, show_quiver=False, show_isolines="zero")
    with pytest.raises(TypeError, match="f must be a callable"):
        plot_sdf(fig, ax, None)
    with pytest.raises(TypeError, match="f must be a callable"):
        plot_sdf(42, ax=ax)


def test_plot_sdf_axes_draws_a_figure_to_keep():
    """axes=True: ticks, axis labels, title and a labelled colour bar, every isoline label on its
    line and inside the axes, and the figure's margins tight around what it shows."""
    import matplotlib.pyplot as plt

    # a funnel's floor and a disc: lines that run into the axes' edges, as in the README
    f = sdf.Halfspace(normal=[0, 1], d=-1.5) | sdf.Circle(center=[0.0, 0.2], radius=0.5)
    out = plot_sdf(f, show_isolabels=True, colorbar=True, axes=True, title="a title", samples=80)
    ax, fig = out["ax"], out["ax"].figure
    try:
        fig.canvas.draw()
        assert ax.get_title() == "a title" and (ax.get_xlabel(), ax.get_ylabel()) == ("x", "y")
        assert any(t.get_text() for t in ax.get_xticklabels())
        assert any(t.get_text() for t in ax.get_yticklabels())
        assert "distance" in out["colorbar"].ax.get_ylabel()
        assert len(out["labels"]) >= 3
        box = ax.get_window_extent()
        for label in out["labels"]:
            ext = label.get_window_extent()
            assert box.x0 <= ext.x0 and ext.x1 <= box.x1 and box.y0 <= ext.y0 and ext.y1 <= box.y1
            x, y = label.get_position()
            # on its line: the distance there is the label's value (bilinear contouring of 80
            # samples over 4 units: within a fraction of a sample spacing)
            assert abs(float(f(x, y)) - float(label.get_text())) < 0.02
        # tight: what the figure shows (axes, bar, labels) spans nearly all of it
        shown = fig.get_tightbbox(fig.canvas.get_renderer())
        w, h = fig.get_size_inches()
        assert shown.width > 0.9 * w and shown.height > 0.9 * h
        assert shown.x0 >= 0 and shown.y0 >= 0 and shown.x1 <= w and shown.y1 <= h
        # the colour bar is as tall as the axes beside it (compressed layout)
        bar = out["colorbar"].ax.get_window_extent()
        assert abs(bar.height - box.height) < 0.05 * box.height
    finally:
        plt.close(fig)
    # axes=False: the notebook's look, no ticks, no labels, no colour bar
    fig, ax = new_axes()
    out = plot_sdf(f, ax=ax, samples=40, show_quiver=False, axes=False, colorbar=False)
    fig.canvas.draw()
    assert ax.get_xlabel() == "" and ax.get_title() == "" and "colorbar" not in out
    assert all(not t.get_visible() or t.get_text() == "" for t in ax.get_xticklabels())


def test_plot_sdf_levels_are_the_lines_drawn():
    fig, ax = new_axes()
    out = plot_sdf(NumpyCircle(), ax=ax, samples=60, levels=[-0.5, 0.0, 0.25], show_quiver=False)
    np.testing.assert_array_equal(out["contour"].levels, [-0.5, 0.0, 0.25])
    # each line is the circle of radius 1 + level
    for level, segs in zip(out["contour"].levels, out["contour"].allsegs, strict=True):
        pts = np.concatenate(segs)
        np.testing.assert_allclose(np.hypot(*pts.T), 1.0 + level, atol=0.01)
    fig, ax = new_axes()
    out = plot_sdf(NumpyCircle(), ax=ax, samples=60, levels=4, show_quiver=False)
    # a count: matplotlib picks that many round values (or about as many)
    xs, ys, d = plotting.sdf_grid(NumpyCircle(), BOUNDS, 60)
    np.testing.assert_array_equal(out["contour"].levels, ax.contour(xs, ys, d, levels=4).levels)


def test_plotting_does_not_import_render():
    import ast
    import inspect as _inspect

    tree = ast.parse(_inspect.getsource(plotting))
    names = {getattr(n, "module", None) for n in ast.walk(tree) if isinstance(n, ast.ImportFrom)}
    names |= {a.name for n in ast.walk(tree) if isinstance(n, ast.Import) for a in n.names}
    assert not any(m and "render" in m for m in names), names


def test_plot_sdf_is_exported():
    assert sdf.plot_sdf is plotting.plot_sdf
    assert "plot_sdf" in sdf.__all__


# ---------------------------------------------------------------------------------------------
# density_image


def test_density_image_known_pixels_and_edges():
    bounds = [(0, 4), (0, 2)]  # unit pixels: 4 columns along x, 2 rows along y
    pts = {
        (0.0, 0.0): (0, 0),
        (4.0, 2.0): (1, 3),
        (1.0, 0.5): (0, 1),
        (0.999, 0.999): (0, 0),
        (3.999, 1.999): (1, 3),
        (0.5, 1.5): (1, 0),
        (2.0, 1.0): (1, 2),
        (4.0, 0.0): (0, 3),
    }
    for (x, y), (i, j) in pts.items():
        img = density_image([x], [y], bounds, shape=(2, 4))
        expected = np.zeros((2, 4))
        expected[i, j] = 1.0
        assert np.array_equal(img, expected), (x, y)


def test_density_image_drops_outside_and_non_finite_points():
    bounds = [(0, 4), (0, 2)]
    x = np.array([-1e-9, 4 + 1e-9, 1.0, 1.0, np.nan, 1.0, np.inf, -np.inf, 2.0])
    y = np.array([1.0, 1.0, -1e-9, 2 + 1e-9, 1.0, np.nan, 1.0, 1.0, 1.0])
    img = density_image(x, y, bounds, shape=(2, 4))
    assert img.sum() == 1.0 and img[1, 2] == 1.0


@pytest.mark.parametrize("parallel", [None, False, True])
def test_density_image_counts_every_point_inside_once(parallel):
    rng = np.random.default_rng(1)
    n = 50_000
    x, y = rng.uniform(-3, 3, n), rng.normal(0, 1.5, n)
    x[::97] = np.nan
    # Points exactly on pixel edges (multiples of 4/64 are exact in binary).
    x[1::50] = rng.integers(-32, 33, x[1::50].size) / 16.0
    y[1::50] = rng.integers(-32, 33, y[1::50].size) / 16.0
    img = density_image(x, y, BOUNDS, shape=(64, 64), parallel=parallel)
    inside = (x >= -2) & (x <= 2) & (y >= -2) & (y <= 2)
    assert img.sum() == inside.sum()
    ref, _, _ = np.histogram2d(x[inside], y[inside], bins=(64, 64), range=BOUNDS)
    assert np.array_equal(img, ref.T)


def test_density_image_weights_and_shapes():
    x = np.array([[0.1, 0.1], [1.5, -1.5]])
    y = np.array([[0.1, 0.1], [1.5, -1.5]])
    w = np.array([[2.0, 0.5], [1.0, -3.0]])
    img = density_image(x, y, BOUNDS, shape=(4, 4), weights=w)
    assert img[2, 2] == 2.5 and img[3, 3] == 1.0 and img[0, 0] == -3.0
    assert img.sum() == 0.5
    assert density_image([], [], BOUNDS, (3, 5)).shape == (3, 5)


def test_density_image_accepts_strided_views():
    p = np.zeros(1000, dtype=[("x", float, 2), ("r", float)])
    rng = np.random.default_rng(2)
    p["x"] = rng.uniform(-2, 2, (1000, 2))
    img = density_image(p["x"][:, 0], p["x"][:, 1], BOUNDS, (8, 8))
    ref = density_image(p["x"][:, 0].copy(), p["x"][:, 1].copy(), BOUNDS, (8, 8))
    assert np.array_equal(img, ref) and img.sum() == 1000


@settings(max_examples=60, deadline=None)
@given(
    st.lists(st.tuples(st.floats(-3, 3), st.floats(-3, 3)), max_size=40),
    st.integers(1, 9),
    st.integers(1, 9),
)
def test_density_image_is_histogram2d(points, h, w):
    xy = np.array(points, dtype=float).reshape(-1, 2)
    img = density_image(xy[:, 0], xy[:, 1], [(-1, 2), (-2, 1.5)], shape=(h, w))
    ref, _, _ = np.histogram2d(xy[:, 0], xy[:, 1], bins=(w, h), range=[(-1, 2), (-2, 1.5)])
    assert np.array_equal(img, ref.T)


@pytest.mark.parametrize(
    "kwargs,name",
    [
        (dict(shape=(0, 4)), "shape"),
        (dict(shape=4), "shape"),
        (dict(shape=(2.0, 4)), "shape"),
        (dict(bounds=[(0, 0), (0, 1)]), "bounds"),
        (dict(weights=[1.0]), "weights"),
    ],
)
def test_density_image_rejects_bad_arguments(kwargs, name):
    args = dict(bounds=BOUNDS, shape=(4, 4))
    args.update(kwargs)
    with pytest.raises(ValueError, match=name):
        density_image([0.0, 1.0], [0.0, 1.0], **args)
    with pytest.raises(ValueError, match="same number"):
        density_image([0.0, 1.0], [0.0], BOUNDS)


# ---------------------------------------------------------------------------------------------
# draw_particles


def test_draw_particles_circles_then_update():
    fig, ax = new_axes()
    plot_sdf(fig, ax, NumpyCircle(), samples=20, show_quiver=False, filled=True)
    x, y = np.array([0.0, 1.0, -1.0]), np.array([1.5, 1.5, 1.5])
    layer = draw_particles(ax, x, y, r=np.array([0.1, 0.2, 0.3]))
    assert isinstance(layer, ParticleLayer) and layer.mode == "circles"
    assert isinstance(layer.artist, EllipseCollection)
    assert np.allclose(layer.artist.get_offsets(), np.column_stack([x, y]))
    assert np.allclose(layer.artist.get_widths(), [0.2, 0.4, 0.6])
    assert np.allclose(layer.artist.get_heights(), [0.2, 0.4, 0.6])
    first = layer.artist
    (artist,) = layer.update(x + 0.5, y - 1.0)  # radii kept
    assert artist is first and artist is layer.artist
    assert np.allclose(artist.get_offsets(), np.column_stack([x + 0.5, y - 1.0]))
    assert np.allclose(artist.get_widths(), [0.2, 0.4, 0.6])
    layer.update(x, y, r=0.5)
    assert layer.artist is first and np.allclose(first.get_widths(), 1.0)
    fig.canvas.draw()
    # Without radii: dots of a fixed size in points.
    dots = draw_particles(ax, x, y)
    assert dots.mode == "circles" and np.allclose(dots.artist.get_widths(), 4.0)


def test_draw_particles_density_image_and_mode_switch():
    fig, ax = new_axes()
    plot_sdf(fig, ax, NumpyCircle(), samples=20, show_quiver=False, filled=True)
    rng = np.random.default_rng(3)
    x, y = rng.normal(0, 0.3, 2000), rng.normal(1.0, 0.3, 2000)
    layer = draw_particles(ax, x, y, max_circles=100, shape=(40, 40))
    assert layer.mode == "density" and isinstance(layer.artist, AxesImage)
    assert np.array_equal(layer.image, density_image(x, y, BOUNDS, (40, 40)))
    data = layer.artist.get_array()
    assert np.array_equal(data.filled(0), density_image(x, y, BOUNDS, (40, 40)))
    assert np.array_equal(np.ma.getmaskarray(data), data.filled(0) == 0)  # empty: transparent
    assert layer.artist.get_extent() == [-2, 2, -2, 2]
    assert layer.artist.get_zorder() > 2  # above the SDF's fill and lines
    image = layer.artist
    layer.update(x + 0.5, y)
    assert layer.artist is image  # updated in place
    assert np.array_equal(
        layer.artist.get_array().filled(0), density_image(x + 0.5, y, BOUNDS, (40, 40))
    )
    assert layer.artist.norm.vmax == layer.image.max()
    fig.canvas.draw()
    # Fewer particles than max_circles: the image goes, circles come.
    layer.update(x[:10], y[:10], r=0.05)
    assert layer.mode == "circles" and len(ax.images) == 0 and layer.artist in ax.collections
    layer.remove()
    assert layer.artist is None and not any(
        isinstance(c, EllipseCollection) for c in ax.collections
    )


def test_draw_particles_default_shape_follows_axes_pixels():
    fig, ax = new_axes(figsize=(4, 4))  # dpi 50: the axes box is ~150 px square
    plot_sdf(fig, ax, NumpyCircle(), samples=10, show_quiver=False, show_isolines=None)
    layer = draw_particles(ax, np.zeros(10), np.zeros(10), max_circles=0)
    box = ax.get_window_extent()
    assert layer.shape == (round(box.height), round(box.width))


# ---------------------------------------------------------------------------------------------
# render_frame


def pixel(fig, img, x, y):
    """The PNG pixel (RGB) that shows data point (x, y) of the figure's axes."""
    px, py = fig.axes[0].transData.transform((x, y))
    return img[int(img.shape[0] - py), int(px), :3]


@pytest.mark.parametrize("n,max_circles", [(20_000, None), (200, None)])
def test_render_frame_png_shows_solid_and_particles(world, tmp_path, n, max_circles):
    rng = np.random.default_rng(4)
    x, y = rng.normal(-0.5, 0.15, n), rng.normal(0.5, 0.15, n)
    out = tmp_path / "frame.png"
    fig = render_frame(
        world,
        x,
        y,
        r=0.03,
        bounds=BOUNDS,
        out_png=str(out),
        title="frame",
        samples=120,
        max_circles=max_circles,
        figsize=(4, 4),
        dpi=80,
    )
    assert fig.particle_layer.mode == ("density" if n > 5000 else "circles")
    img = mpimg.imread(str(out))
    assert img.shape[:2] == (320, 320)
    assert fig.axes[0].get_title() == "frame"
    # Inside the floor and inside the disc: the solid colour.
    for p in [(0.0, -1.8), (-1.5, -1.9), (1.2, -1.2)]:
        assert np.allclose(pixel(fig, img, *p), to_rgb(SOLID_COLOR), atol=2 / 255), p
    # Free space far from the particles: the background.
    for p in [(1.5, 1.5), (-1.6, 1.7)]:
        assert np.allclose(pixel(fig, img, *p), to_rgb(BACKGROUND_COLOR), atol=2 / 255), p
    # The particles' cluster above the floor: orange-brown, neither background nor solid.
    r, g, b = pixel(fig, img, -0.5, 0.5)
    assert r > g + 0.2 and r > b + 0.3, (r, g, b)


def test_render_frame_without_png_returns_figure(world):
    fig = render_frame(world, [0.0], [0.0], r=0.1, samples=20, figsize=(2, 2), dpi=40)
    assert isinstance(fig, Figure) and fig.particle_layer.mode == "circles"
    assert render.DEFAULT_MAX_CIRCLES == 5000


@pytest.mark.parametrize(
    "bounds, n, title",
    [([(-2, 2), (-1, 1)], 50, "wide"), ([(-1, 1), (-2, 2)], 50, None), (BOUNDS, 20_000, "dense")],
)
def test_render_frame_is_sized_to_its_bounds(world, tmp_path, bounds, n, title):
    """Without a figsize the figure fits its bounds: what it shows (axes, tick labels, title,
    colour bar) spans nearly all of it, with no blank band beside or above the world; a colour
    bar only where the particles are a density image."""
    rng = np.random.default_rng(5)
    x, y = rng.uniform(-0.9, 0.9, n), rng.uniform(-0.9, 0.9, n)
    out = tmp_path / "frame.png"
    fig = render_frame(
        world, x, y, r=0.02, bounds=bounds, samples=60, out_png=str(out), title=title
    )
    FigureCanvasAgg(fig).draw()
    ax = fig.axes[0]
    (x0, x1), (y0, y1) = bounds
    box = ax.get_window_extent()
    assert box.height / box.width == pytest.approx((y1 - y0) / (x1 - x0), rel=0.02)
    drawn = fig.get_tightbbox(fig.canvas.get_renderer())
    w, h = fig.get_size_inches()
    assert drawn.width > 0.9 * w and drawn.height > 0.9 * h, (drawn, w, h)
    assert fig.axes[1].get_visible() == (n > render.DEFAULT_MAX_CIRCLES)
    img = mpimg.imread(str(out))
    assert img.shape[:2] == (round(h * 100), round(w * 100))
