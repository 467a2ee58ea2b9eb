"""Outlines of lines and quadratic Beziers, SVG path data and text as exact SDFs."""

import numpy as np
import pytest

import fastsdf as sdf
from fastsdf.backends.kernel import prims as P
from fastsdf.expr import prims_ref as R
from fastsdf.geometry.outline import SvgFile, SvgPath, Text, cubic_to_quadratics, path_segments
from fastsdf.shapes import Outline
from fastsdf.shapes.primitives import outline_table

# A square with a quadratic bulge on top and a square hole (clockwise).
SEGMENTS = [
    (0, -1, -1, 0, 0, 1, -1),
    (0, 1, -1, 0, 0, 1, 1),
    (1, 1, 1, 0, 2, -1, 1),
    (0, -1, 1, 0, 0, -1, -1),
    (0, -0.3, -0.3, 0, 0, -0.3, 0.3),
    (0, -0.3, 0.3, 0, 0, 0.3, 0.3),
    (0, 0.3, 0.3, 0, 0, 0.3, -0.3),
    (0, 0.3, -0.3, 0, 0, -0.3, -0.3),
]


def _kernel(table, x, y):
    out = np.array([P.outline_vg(a, b, table) for a, b in zip(x, y, strict=True)])
    return out[:, 0], out[:, 1:]


@pytest.mark.parametrize("rule", ["nonzero", "evenodd"])
def test_compiled_outline_matches_the_reference(rule):
    table = outline_table(SEGMENTS, rule)
    x, y = np.random.default_rng(1).uniform(-1.6, 1.9, (2, 600))
    d, g = _kernel(table, x, y)
    dr, gu, gv = R.evaluate("outline", table, x, y, [])
    np.testing.assert_allclose(d, dr, atol=1e-13)
    ok = np.abs(d) > 1e-6
    np.testing.assert_allclose(g[ok, 0], gu[ok], atol=1e-7)
    np.testing.assert_allclose(g[ok, 1], gv[ok], atol=1e-7)
    # analytic values: inside the hole (outside), in the solid, the bulge's top at y = 1.5
    d, _ = _kernel(table, [0.0, 0.6, 0.0, 0.0], [0.0, 0.0, 1.49, 1.6])
    np.testing.assert_allclose(d, [0.3, -0.3, -0.01, 0.1], atol=1e-14)


def test_fill_rules_differ_on_a_doubly_wound_loop():
    inner_ccw = [
        (0, -0.3, -0.3, 0, 0, 0.3, -0.3),
        (0, 0.3, -0.3, 0, 0, 0.3, 0.3),
        (0, 0.3, 0.3, 0, 0, -0.3, 0.3),
        (0, -0.3, 0.3, 0, 0, -0.3, -0.3),
    ]
    segs = SEGMENTS[:4] + inner_ccw  # the inner square wound the same way as the outer
    nz = _kernel(outline_table(segs, "nonzero"), [0.0], [0.0])[0][0]
    eo = _kernel(outline_table(segs, "evenodd"), [0.0], [0.0])[0][0]
    assert nz == pytest.approx(-0.3) and eo == pytest.approx(0.3)


def test_quadratic_closest_point_against_brute_force():
    rng = np.random.default_rng(2)
    t = np.linspace(0, 1, 200001)
    for _ in range(30):
        p0, p1, p2 = rng.uniform(-1, 1, (3, 2))
        u, v = rng.uniform(-1.5, 1.5, 2)
        curve = (
            ((1 - t) ** 2)[:, None] * p0 + (2 * t * (1 - t))[:, None] * p1 + (t**2)[:, None] * p2
        )
        brute = np.hypot(curve[:, 0] - u, curve[:, 1] - v).min()
        _, dd = P.quad_closest(u, v, *p0, *p1, *p2)
        # the brute force overestimates by at most (step * speed)^2 / (8 d): tiny here
        assert np.sqrt(dd) <= brute + 1e-15
        assert np.sqrt(dd) == pytest.approx(brute, abs=1e-9)


def test_outline_gradient_is_the_finite_difference():
    f = Outline(SEGMENTS)
    f.backend = "numpy"
    x, y = np.random.default_rng(3).uniform(-1.5, 1.8, (2, 200))
    d, g = f(x, y, compute_gradient=True)
    h = 1e-6
    fd = np.stack(
        [(f(x + h, y) - f(x - h, y)) / (2 * h), (f(x, y + h) - f(x, y - h)) / (2 * h)], -1
    )
    smooth = np.abs(np.linalg.norm(fd, axis=1) - 1) < 1e-4  # off the medial axis
    assert smooth.mean() > 0.9
    np.testing.assert_allclose(g[smooth], fd[smooth], atol=1e-5)


def test_cubic_to_quadratics_within_the_bound():
    rng = np.random.default_rng(4)
    t = np.linspace(0, 1, 801)
    for tol in (1e-2, 1e-4):
        for _ in range(4):
            P4 = rng.uniform(-1, 1, (4, 2))
            rows = cubic_to_quadratics(*P4, tol=tol)
            cubic = (
                ((1 - t) ** 3)[:, None] * P4[0]
                + (3 * (1 - t) ** 2 * t)[:, None] * P4[1]
                + (3 * (1 - t) * t**2)[:, None] * P4[2]
                + (t**3)[:, None] * P4[3]
            )
            # every point of the cubic is within tol/2 of the quadratics (and the bound is
            # not vacuous: it is met with n pieces, not far below it)
            dist = np.full(len(t), np.inf)
            for r in rows:
                for k, (u, v) in enumerate(cubic):
                    dist[k] = min(dist[k], np.sqrt(P.quad_closest(u, v, *r[1:7])[1]))
            assert dist.max() <= 0.5 * tol
            assert np.allclose(rows[0, 1:3], P4[0]) and np.allclose(rows[-1, 5:7], P4[3])


def _dense_path(d, n=400):
    """Points densely along every segment of SVG path data (svgelements' own evaluation,
    y flipped) and the subpaths as polygons."""
    from svgelements import Move, Path

    pts, polys = [], []
    for seg in Path(d):
        if isinstance(seg, Move):
            polys.append([])
            continue
        q = np.asarray(seg.npoint(np.linspace(0, 1, n)), dtype=np.float64) * [1, -1]
        pts.append(q)
        polys[-1].extend(q.tolist())
    return pts, polys


def _agrees_with_samples(dist, brute, dense, tol):
    """``dense``: a list of sample arrays, one per segment. A curve sampled at spacing h is
    farther from a point at distance d by at most (1 + d / R) h^2 / (8 d), R its smallest
    radius of curvature (here at least 1); the outline is within tol of the curve."""
    h = max(np.hypot(*np.diff(piece, axis=0).T).max() for piece in dense)
    d = np.maximum(dist, 1e-300)
    assert np.all(dist <= brute + tol)
    assert np.all(brute - dist <= (1 + d) * h * h / (8 * d) + tol)


def test_svg_path_against_shapely_and_brute_force():
    import shapely

    d = "M 10 10 C 20 0 40 0 50 10 A 20 20 0 0 1 10 10 Z M 25 8 Q 30 4 35 8 L 30 12 Z"
    tol = 1e-6
    f = SvgPath(d, fill_rule="evenodd", tol=tol)
    f.backend = "numpy"
    dense, polys = _dense_path(d, n=8000)
    x, y = np.random.default_rng(5).uniform([5, -32], [55, 2], (150, 2)).T
    dist = f(x, y)
    from tests.conftest import brute_distance

    brute = brute_distance(np.stack([x, y], 1), np.concatenate(dense))
    _agrees_with_samples(np.abs(dist), brute, dense, tol)
    region = shapely.Polygon(polys[0]).symmetric_difference(shapely.Polygon(polys[1]))
    inside = np.array([region.contains(shapely.Point(a, b)) for a, b in zip(x, y, strict=True)])
    clear = np.abs(dist) > 1e-3
    np.testing.assert_array_equal((dist < 0)[clear], inside[clear])


def test_svg_open_subpaths_are_closed_and_bad_data_is_refused():
    rows = path_segments("M 0 0 L 1 0 L 1 1")  # closed by a line back to the start
    assert len(rows) == 3 and np.allclose(rows[-1, 5:7], [0, 0])
    with pytest.raises(ValueError):
        SvgPath("M 0 0 L", tol=1e-3)
    with pytest.raises(ValueError, match="tol"):
        SvgPath("M 0 0 L 1 0 L 1 1 Z", tol=0)
    with pytest.raises(ValueError, match="closed loops"):
        Outline([(0, 0, 0, 0, 0, 1, 0), (0, 1, 0, 0, 0, 1, 1)])


def test_text_is_an_exact_sdf_like_any_other():
    import shapely
    from matplotlib.textpath import TextPath

    word = Text("fastsdf", size=1.0)
    x, y = np.random.default_rng(6).uniform([-0.1, -0.3], [4.0, 1.0], (200, 2)).T
    d = word(x, y)  # the compiled kernel
    np.testing.assert_allclose(d, word(x, y, backend="numpy"), atol=1e-12)
    g = sdf.GridSDF(word, bounds=[(-0.1, 4.0), (-0.3, 1.0)], samples=[120j, 40j])
    assert np.abs(g(x, y) - d).max() < 0.05  # it grids like any SDF
    split = Text("fastsdf", size=1.0, split_glyphs=True)  # a union of glyph outlines
    np.testing.assert_allclose(split(x[:40], y[:40], backend="numpy"), d[:40], atol=1e-12)
    # brute force against matplotlib's own evaluation of the glyphs' Bezier segments
    tp = TextPath((0, 0), "fastsdf", size=1.0)
    tt = np.linspace(0, 1, 100)
    dense = [seg(tt) for seg, _ in tp.iter_bezier() if seg.degree > 0]
    from tests.conftest import brute_distance

    brute = brute_distance(np.stack([x, y], 1), np.concatenate(dense))
    _agrees_with_samples(np.abs(d), brute, dense, 1e-12)
    # sign: shapely, the flattened glyph rings combined by the even-odd rule (holes included;
    # matplotlib's own contains_points fills the counters of 'a' and 'd'); away from the
    # boundary, where the flattening cannot matter
    region = shapely.Polygon()
    for ring in tp.to_polygons(closed_only=True):
        region = region.symmetric_difference(shapely.Polygon(ring))
    inside = np.array([region.contains(shapely.Point(a, b)) for a, b in zip(x, y, strict=True)])
    clear = np.abs(d) > 5e-3
    np.testing.assert_array_equal((d < 0)[clear], inside[clear])
    # it blends and combines like any SDF
    with sdf.smoothness(0.1, kind="quadratic"):
        blended = word | sdf.Circle([2.0, 0.35], 0.2)
    disc = np.hypot(x - 2.0, y - 0.35) - 0.2
    apart = np.abs(d - disc) >= 0.1  # the quadratic blend is the minimum there
    near = np.abs(d - disc) < 0.05  # and below it, by up to k / 4, where they meet
    got = blended(x, y, backend="numpy")
    np.testing.assert_allclose(got[apart], np.minimum(d, disc)[apart], atol=1e-12)
    assert np.all(got[near] < np.minimum(d, disc)[near])
    assert np.all(got >= np.minimum(d, disc) - 0.025 - 1e-12)


def test_svg_file_is_the_union_of_its_paths(tmp_path):
    """Each <path> with its own fill rule and transform; the file's union equals the union of
    the same paths given as data, with the transform applied by hand."""
    square_with_hole = "M 0 0 L 4 0 L 4 4 L 0 4 Z M 1 1 L 3 1 L 3 3 L 1 3 Z"
    triangle = "M 0 0 L 2 0 L 1 2 Z"
    (tmp_path / "drawing.svg").write_text(
        '<svg xmlns="http://www.w3.org/2000/svg" width="20" height="20">'
        f'<path fill-rule="evenodd" d="{square_with_hole}"/>'
        f'<path transform="translate(6 1)" d="{triangle}"/>'
        '<rect x="0" y="0" width="1" height="1"/></svg>'
    )
    f = SvgFile(tmp_path / "drawing.svg")
    moved = "M 6 1 L 8 1 L 7 3 Z"
    g = SvgPath(square_with_hole, fill_rule="evenodd") | SvgPath(moved)
    x, y = np.random.default_rng(3).uniform(-1, 9, (2, 500))
    y = -y / 2.0  # y flipped: the drawing lies below the x axis
    np.testing.assert_allclose(f(x, y), g(x, y), rtol=0, atol=1e-12)
    assert f(2.0, -2.0) > 0 and f(0.5, -0.5) < 0  # the hole is free, the frame solid
    with pytest.raises(ValueError, match="no <path>"):
        (tmp_path / "empty.svg").write_text('<svg xmlns="http://www.w3.org/2000/svg"/>')
        SvgFile(tmp_path / "empty.svg")
    with pytest.raises(ValueError, match="existing SVG file"):
        SvgFile(tmp_path / "missing.svg")


def test_text_placement_follows_the_fonts_metrics():
    """The documented placement: the baseline at y = position[1], the pen at x = position[0],
    ``size`` the em size; checked against the default font's own glyph metrics (read with
    FreeType, independently of the glyph outlines the SDF is built from)."""
    from matplotlib.font_manager import FontProperties, findfont
    from matplotlib.ft2font import FT2Font, LoadFlags

    font = FT2Font(findfont(FontProperties()))
    em = font.units_per_EM

    def metrics(ch: str) -> tuple:
        g = font.load_char(ord(ch), flags=LoadFlags.NO_SCALE)
        return g.horiBearingX / em, g.horiBearingY / em, g.height / em

    size, (px, py) = 2.0, (0.5, -0.25)
    lsb, top, height = metrics("H")
    h = Text("H", size=size, position=(px, py))
    stem = px + size * (lsb + 0.02)  # inside the left stem of the H
    mid = py + 0.5 * size * top
    gap = 0.1  # straight below, above and left of the stem's flat ends and side
    # matplotlib reads glyphs at 100 units per em in FreeType's 1/64 steps: the outline's
    # points are the font's own to within size / 6400
    quantum = size / 6400
    values = h(
        np.array([stem, stem, px + size * lsb - gap]),
        np.array([py - gap, py + size * top + gap, mid]),
        backend="numpy",
    )
    np.testing.assert_allclose(values, gap, atol=quantum)
    assert values[0] == pytest.approx(gap, abs=1e-12)  # the baseline itself: exactly y = py
    assert top == height and 0.72 < top < 0.74  # capitals stand on the baseline, 0.729 em tall
    assert h(stem, py + 1e-6, backend="numpy") < 0 < h(stem, py - 1e-6, backend="numpy")
    # a descender: the stem of 'p' ends size * (height - top) below the baseline
    lsb, top, height = metrics("p")
    p = Text("p", size=size, position=(px, py))
    bottom = py - size * (height - top)
    stem = px + size * (lsb + 0.02)
    np.testing.assert_allclose(p(stem, bottom - gap, backend="numpy"), gap, atol=quantum)
    np.testing.assert_allclose(height - top, 0.208, atol=1e-3)
    # the extent stated in the docstring for Text("fastsdf", size=1.0), on a grid whose rows
    # miss the glyphs' vertices (the compiled kernel, as the test above builds it)
    word = Text("fastsdf", size=1.0)
    xs, ys = np.meshgrid(np.linspace(-0.1, 3.6, 371), np.linspace(-0.1, 0.9, 101) + 1e-7)
    ink = word(xs.ravel(), ys.ravel()).reshape(xs.shape) < 0
    cols, rows = np.flatnonzero(ink.any(axis=0)), np.flatnonzero(ink.any(axis=1))
    dx, dy = xs[0, 1] - xs[0, 0], ys[1, 0] - ys[0, 0]
    # (the docstring's figures are rounded to its digits; the grid resolves one step)
    assert abs(xs[0, cols[0]] - 0.02) <= 1.01 * dx and abs(xs[0, cols[-1]] - 3.40) <= 1.01 * dx
    assert abs(ys[rows[0], 0] - -0.014) <= 1.01 * dy and abs(ys[rows[-1], 0] - 0.76) <= 1.01 * dy


def test_text_sign_on_rays_through_vertices_agrees_with_the_kernel():
    """A point level with a glyph's vertex (its ray towards +x passes through a shared segment
    end, e.g. on the baseline) gets the same sign from the NumPy reference as from the kernel:
    left of an 'H' on its baseline is outside."""
    from fastsdf.geometry.outline import text_segments

    h = Text("H", size=1.0)
    left, right = np.array([-0.5, 2.0]), np.zeros(2)
    np.testing.assert_array_equal(np.sign(h(left, right, backend="numpy")), [1.0, 1.0])
    word = Text("fastsdf", size=1.0)
    segments = np.concatenate(text_segments("fastsdf", 1.0))
    heights = np.unique(np.concatenate([segments[:, 2], segments[:, 6]]))  # every vertex's y
    x = np.random.default_rng(9).uniform(-0.2, 3.6, heights.size)
    d_ref, d_kernel = word(x, heights, backend="numpy"), word(x, heights)
    clear = np.abs(d_kernel) > 1e-9  # off the outline itself
    np.testing.assert_array_equal(np.sign(d_ref[clear]), np.sign(d_kernel[clear]))
    np.testing.assert_allclose(d_ref, d_kernel, atol=1e-12)
