"""Masks and images to signed distance grids: exact transform, layout, analytic shapes."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays
from scipy import ndimage

import fastsdf as sdf
from fastsdf.geometry.edt import distance_transform, signed_distance_transform
from fastsdf.geometry.mask import edge_offset, from_image, from_mask

masks = arrays(np.bool_, st.tuples(st.integers(1, 24), st.integers(1, 24)))
spacings = st.tuples(st.floats(0.1, 3.0), st.floats(0.1, 3.0))


def _same(d, ref, sampling):
    """Bit for bit with unit spacing (square roots of the same integers); with other spacings
    two different pixels can tie in exact arithmetic and differ in the last bit."""
    if sampling is None:
        np.testing.assert_array_equal(d, ref)
    else:
        np.testing.assert_allclose(d, ref, rtol=1e-15, atol=0)


@settings(max_examples=60, deadline=None)
@given(masks, st.one_of(st.none(), spacings))
def test_distance_transform_equals_scipy(mask, sampling):
    d, ind = distance_transform(mask, sampling, return_indices=True)
    ref = (
        ndimage.distance_transform_edt(mask, sampling=sampling)
        if (~mask).any()
        else np.full(mask.shape, np.inf)
    )
    _same(d, ref, sampling)
    if (~mask).any():
        assert not mask[ind[0], ind[1]].any()  # the features are False pixels
        hi, hj = (1.0, 1.0) if sampling is None else sampling
        ii, jj = np.indices(mask.shape)
        np.testing.assert_allclose(np.hypot((ii - ind[0]) * hi, (jj - ind[1]) * hj), d, rtol=1e-14)


@settings(max_examples=60, deadline=None)
@given(masks, st.one_of(st.none(), spacings))
def test_signed_transform_is_the_two_scipy_transforms(mask, sampling):
    if mask.all() or not mask.any():
        return
    s, ind = signed_distance_transform(mask, sampling, return_indices=True)
    half = 0.5 * (1.0 if sampling is None else min(sampling))
    ref = np.where(
        mask,
        half - ndimage.distance_transform_edt(mask, sampling=sampling),
        ndimage.distance_transform_edt(~mask, sampling=sampling) - half,
    )
    _same(s, ref, sampling)
    assert (mask[ind[0], ind[1]] != mask).all()  # the nearest pixel of the other phase


def test_brute_force_on_a_small_mask(rng):
    mask = rng.random((9, 13)) < 0.3
    ii, jj = np.indices(mask.shape)
    pts = np.stack([ii.ravel(), jj.ravel()], 1) * [0.7, 1.3]
    inside, outside = pts[mask.ravel()], pts[~mask.ravel()]
    d = signed_distance_transform(mask, (0.7, 1.3)).ravel()
    for k, p in enumerate(pts):
        other = outside if mask.ravel()[k] else inside
        brute = np.sqrt(((other - p) ** 2).sum(1)).min() - 0.35
        assert d[k] == pytest.approx(-brute if mask.ravel()[k] else brute, abs=1e-14)


def _raster(f, n, supersample=1):
    """Coverage of ``f < 0`` per pixel of an n x n image of [-1, 1]^2 (row 0 at the top)."""
    px = 2.0 / n
    xc = -1 + (np.arange(n) + 0.5) * px
    X, Y = np.meshgrid(xc, xc[::-1])
    sub = (np.arange(supersample) + 0.5) / supersample - 0.5
    cov = np.zeros((n, n))
    for dy in sub:
        for dx in sub:
            cov += f(X + dx * px, Y + dy * px) < 0
    return cov / supersample**2


SHAPES = {"circle": sdf.Circle([0.1, -0.2], 0.6), "box": sdf.Box([-0.7, -0.5], [0.5, 0.3])}


@pytest.mark.parametrize("name", SHAPES)
def test_mask_of_analytic_shape_is_within_a_pixel(name):
    f = SHAPES[name]
    for n in (32, 128):
        g = from_mask(_raster(f, n) > 0.5, [(-1, 1), (-1, 1)])
        px = 2.0 / n
        ax, ay = g.axes
        assert ax[0] == pytest.approx(-1 + px / 2) and ay[-1] == pytest.approx(1 - px / 2)
        X, Y = np.meshgrid(ax, ay, indexing="ij")
        err = np.abs(g.values - f(X, Y))
        # A node's true distance and the half-pixel boundary differ by at most half a diagonal.
        assert err.max() <= px * np.sqrt(0.5) + 1e-12
        # the grid answers queries like any GridSDF: values and gradients
        d, grad = g(np.array([0.1, 0.95]), np.array([-0.2, 0.9]), compute_gradient=True)
        assert d[0] == pytest.approx(f(0.1, -0.2), abs=px)
        assert np.isfinite(grad).all()


def test_origin_and_orientation():
    mask = np.zeros((4, 6), bool)
    mask[0, 0] = True  # top-left pixel
    g = from_mask(mask, [(0, 6), (0, 4)])
    assert g.shape == (6, 4)
    assert g(0.5, 3.5) == pytest.approx(-0.5)  # its centre, top left in (x, y)
    assert g(0.5, 0.5) > 2.0
    low = from_mask(mask, [(0, 6), (0, 4)], origin="lower")
    assert low(0.5, 0.5) == pytest.approx(-0.5)


def test_edge_offset_of_straight_edges():
    # axis-aligned edge: offset is 0.5 - coverage
    np.testing.assert_allclose(edge_offset(1.0, 0.0, [0.0, 0.25, 0.5, 1.0]), [0.5, 0.25, 0.0, -0.5])
    # a diagonal edge through the centre covers half; one through a corner covers nothing
    assert edge_offset(1.0, 1.0, 0.5) == pytest.approx(0.0)
    assert edge_offset(1.0, 1.0, 0.0) == pytest.approx(np.sqrt(0.5))
    # exact coverage of the unit pixel by {u . p < -t} (the square clipped by the half-plane)
    rng = np.random.default_rng(3)
    for _ in range(50):
        ang, t = rng.uniform(0, 2 * np.pi), rng.uniform(-0.7, 0.7)
        u = np.array([np.cos(ang), np.sin(ang)])
        cov = _clipped_area(u, t)
        if 0.0 < cov < 1.0:
            assert edge_offset(u[0], u[1], cov) == pytest.approx(t, abs=1e-12)


def _clipped_area(u, t):
    """Area of the unit pixel [-1/2, 1/2]^2 where u . p < -t (Sutherland-Hodgman, shoelace)."""
    square = [(-0.5, -0.5), (0.5, -0.5), (0.5, 0.5), (-0.5, 0.5)]
    out = []
    for k, p in enumerate(square):
        q = square[(k + 1) % 4]
        sp, sq = u @ p + t, u @ q + t
        if sp < 0:
            out.append(p)
        if (sp < 0) != (sq < 0):
            w = sp / (sp - sq)
            out.append((p[0] + w * (q[0] - p[0]), p[1] + w * (q[1] - p[1])))
    if len(out) < 3:
        return 0.0
    x, y = np.array(out).T
    return 0.5 * abs(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1)))


@pytest.mark.parametrize("name", SHAPES)
def test_anti_aliased_image_places_edges_within_a_tenth_of_a_pixel(name):
    f = SHAPES[name]
    n = 64
    px = 2.0 / n
    cov = _raster(f, n, supersample=16)
    g = from_image((cov * 255).round().astype(np.uint8), [(-1, 1), (-1, 1)])
    X, Y = np.meshgrid(*g.axes, indexing="ij")
    exact = f(X, Y)
    near = np.abs(exact) < 2 * px
    if name == "box":  # the straight-edge model does not hold at corners: leave them out
        corners = np.array([[-0.7, -0.5], [-0.7, 0.3], [0.5, -0.5], [0.5, 0.3]])
        to_corner = np.hypot(X[..., None] - corners[:, 0], Y[..., None] - corners[:, 1])
        near &= to_corner.min(-1) > 3 * px
    err = np.abs(g.values - exact)
    binary = np.abs(from_mask(cov > 0.5, [(-1, 1), (-1, 1)]).values - exact)
    assert err[near].max() < 0.12 * px
    assert err[near].max() < 0.5 * binary[near].max()
    # farther out: the nearest edge point found by propagation (corners aside)
    assert err.max() < (0.3 if name == "circle" else 1.0) * px


def test_dark_inside_and_levels():
    img = np.full((8, 8), 255.0)  # a hard black and white image: no sub-pixel edges
    img[2:5, 2:6] = 0.0
    a = from_image(img, [(0, 8), (0, 8)], levels=(0, 255), dark_inside=True)
    b = from_mask(img < 100, [(0, 8), (0, 8)])
    np.testing.assert_array_equal(a.values, b.values)


def test_particles_accept_a_mask_world():
    import fastsdf.particles as phys

    n = 48
    mask = np.zeros((n, n), bool)
    mask[-8:] = True  # a floor along the bottom rows
    mask[-20:, :6] = True  # and a wall on the left
    g = from_mask(mask, [(-1, 1), (-1, 1)])
    sim = phys.ParticleSimulation(g, n=40, seed=0)
    sim.force_generators += [phys.Gravity()]
    xs, ys = np.random.default_rng(1).uniform(-1.2, 1.2, (2, 200))
    d, grad = sim.query(xs, ys)
    d1, g1 = g(xs, ys, compute_gradient=True)
    np.testing.assert_allclose(d, d1, atol=1e-12)
    np.testing.assert_allclose(grad, g1, atol=1e-12)
    sim.run(90)
    x = sim.p["x"]
    assert np.isfinite(x).all()
    assert (g(x[:, 0], x[:, 1]) - sim.p["r"] > -0.02).all()  # none sank into the floor


@pytest.mark.parametrize(
    "bad, err",
    [
        (dict(mask=np.zeros((3, 3, 3))), ValueError),
        (dict(mask=np.zeros((5, 5), bool)), ValueError),
        (dict(mask=np.array([["a", "b"], ["c", "d"]])), TypeError),
        (dict(bounds=[(1, 0), (0, 1)]), ValueError),
        (dict(origin="middle"), ValueError),
    ],
)
def test_bad_input(bad, err):
    args = dict(mask=np.eye(5, dtype=bool), bounds=[(0, 1), (0, 1)])
    args.update(bad)
    with pytest.raises(err):
        from_mask(**args)
    with pytest.raises(ValueError, match="threshold"):
        from_image(np.eye(5), [(0, 1), (0, 1)], threshold=1.5)


def _disc_image(size=40):
    """An anti-aliased white disc on black, 8-bit grey levels."""
    c = (np.arange(size) + 0.5) / size * 2 - 1
    x, y = np.meshgrid(c, c)
    cov = np.clip((0.6 - np.hypot(x, y)) * size / 2 + 0.5, 0, 1)
    return (cov * 255).round().astype(np.uint8)


def test_from_image_reads_a_png_or_jpeg_file_as_its_pixels(tmp_path):
    """A path is read with the installed image readers: a PNG gives the grid of its pixels
    (bit for bit, grey or RGB or with an opaque alpha), a JPEG that of its pixels within a
    pixel (JPEG is lossy)."""
    image = pytest.importorskip("PIL.Image")
    grey = _disc_image()
    bounds = [(-1, 1), (-1, 1)]
    want = from_image(grey, bounds)
    for mode, pixels in (
        ("L", grey),
        ("RGB", np.repeat(grey[..., None], 3, axis=-1)),
        ("RGBA", np.dstack([grey, grey, grey, np.full_like(grey, 255)])),
    ):
        path = tmp_path / f"disc_{mode}.png"
        image.fromarray(pixels, mode).save(path)
        for source in (path, str(path)):
            got = from_image(source, bounds)
            np.testing.assert_array_equal(got.values, want.values)
    path = tmp_path / "disc.jpg"
    image.fromarray(grey, "L").save(path, quality=95)
    # (JPEG's ringing leaves levels a little off black or white far from the disc, which
    # sub-pixel placement would read as edges: compare the thresholded images)
    got = from_image(path, bounds, subpixel=False)
    sharp = from_image(grey, bounds, subpixel=False)
    assert np.abs(got.values - sharp.values).max() <= 0.05 + 1e-12  # a pixel is 0.05 wide


def test_from_image_lays_a_transparent_image_over_white(tmp_path):
    """A black disc on a transparent background: transparent pixels are white."""
    grey = 255 - _disc_image()
    rgba = np.dstack([np.zeros_like(grey)] * 3 + [grey])  # black, opaque where the disc is
    bounds = [(-1, 1), (-1, 1)]
    want = from_image(255 - grey, bounds, dark_inside=True)
    np.testing.assert_allclose(
        from_image(rgba, bounds, dark_inside=True).values, want.values, atol=1e-12
    )


def test_from_image_names_a_missing_file_and_a_wrong_type(tmp_path):
    missing = tmp_path / "missing.png"
    with pytest.raises(FileNotFoundError, match="missing.png") as caught:
        from_image(missing, [(0, 1), (0, 1)])
    assert caught.value.filename == str(missing)
    for bad in (42, None, {"a": 1}):
        with pytest.raises(TypeError, match="image must be a path"):
            from_image(bad, [(0, 1), (0, 1)])
    with pytest.raises(ValueError, match=r"got shape \(5, 5, 7\)"):
        from_image(np.zeros((5, 5, 7)), [(0, 1), (0, 1)])
    not_an_image = tmp_path / "notes.png"
    not_an_image.write_text("not a picture")
    with pytest.raises(ValueError, match="could not be read as an image"):
        from_image(not_an_image, [(0, 1), (0, 1)])
