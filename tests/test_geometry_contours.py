"""Contours by marching squares refined on the SDF; SVG and DXF files out."""

import os
import re
import xml.etree.ElementTree as ET

import numpy as np
import pytest

import fastsdf as sdf
from fastsdf.geometry.contours import Contour, contours
from fastsdf.geometry.vector import to_dxf, to_svg

BOUNDS = [(-2, 2), (-2, 2)]


def _numpy(f):
    """Evaluate with NumPy (no kernel compilation: keeps these tests cheap)."""
    f.backend = "numpy"
    return f


def _area(points):
    x, y = points.T
    return 0.5 * np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y)


def _smooth_union():
    with sdf.smoothness(0.2, kind="quadratic"):
        return _numpy(sdf.Circle([-0.3, 0.0], 0.5) | sdf.Circle([0.4, 0.1], 0.4))


SCENES = {
    "circle": lambda: _numpy(sdf.Circle([0.1, -0.2], 0.6)),
    "box": lambda: _numpy(sdf.Box([-0.5, -0.3], [0.7, 0.4])),
    "smooth union": _smooth_union,
}


@pytest.mark.parametrize("name", SCENES)
def test_vertices_lie_on_the_zero_set(name):
    f = SCENES[name]()
    cs = contours(f, bounds=BOUNDS, resolution=(61, 47))
    assert len(cs) == 1 and cs[0].closed
    p = cs[0].points
    # an exact SDF's |value| is the distance to the zero set
    assert np.abs(f(p[:, 0], p[:, 1])).max() <= 1e-12
    assert _area(p) > 0  # counter-clockwise around the solid
    # the unrefined (linear interpolation) vertices are visibly off where the set curves
    raw = contours(f, bounds=BOUNDS, resolution=(61, 47), refine=False)[0].points
    if name != "box":
        assert np.abs(f(raw[:, 0], raw[:, 1])).max() > 1e-5


def test_circle_polygon_area_converges():
    r = 0.6
    for n in (33, 129):
        p = contours(_numpy(sdf.Circle([0, 0], r)), bounds=BOUNDS, resolution=n)[0].points
        np.testing.assert_allclose(np.hypot(p[:, 0], p[:, 1]), r, atol=1e-12)
        # an inscribed polygon: area below pi r^2 by at most the chord sagittas
        h = 4.0 / (n - 1)
        assert 0 < np.pi * r * r - _area(p) < 2 * np.pi * r * h**2


def test_topology_disjoint_shapes_and_holes():
    ring = sdf.Circle([0, 0], 0.8) - sdf.Circle([0, 0], 0.4)
    world = _numpy(ring | sdf.Box([1.2, -0.5], [1.8, 0.5]) | sdf.Circle([-1.4, 1.4], 0.3))
    cs = contours(world, bounds=BOUNDS, resolution=120)
    assert len(cs) == 4 and all(c.closed for c in cs)
    areas = sorted(_area(c.points) for c in cs)
    assert areas[0] < 0 and all(a > 0 for a in areas[1:])  # one hole, clockwise
    assert areas[0] == pytest.approx(-np.pi * 0.16, rel=5e-3)


def test_open_contours_end_on_the_bounds():
    cs = contours(_numpy(sdf.Halfspace([0, 1], 0.1)), bounds=[(-1, 1), (-1, 1)], resolution=20)
    assert len(cs) == 1 and not cs[0].closed
    p = cs[0].points
    np.testing.assert_allclose(p[:, 1], 0.1, atol=1e-12)
    assert p[0, 0] == pytest.approx(1.0) and p[-1, 0] == pytest.approx(-1.0)  # inside on left


def test_level_and_plain_callables_and_grids():
    circle = _numpy(sdf.Circle([0, 0], 0.5))
    p = contours(circle, level=0.25, bounds=BOUNDS, resolution=40)[0].points
    np.testing.assert_allclose(np.hypot(*p.T), 0.75, atol=1e-12)
    # any callable on arrays
    p = contours(lambda x, y: x * x / 4 + y * y - 1, bounds=[(-3, 3), (-2, 2)], resolution=50)[
        0
    ].points
    np.testing.assert_allclose(p[:, 0] ** 2 / 4 + p[:, 1] ** 2, 1, atol=1e-11)
    # a grid: its bilinear interpolant is linear along edges, so its own zero set is hit
    from fastsdf.geometry import from_mask

    X, Y = np.meshgrid(np.linspace(-2, 2, 40), np.linspace(2, -2, 40))
    g = from_mask(X**2 + Y**2 < 0.25, BOUNDS)
    p = contours(g, bounds=g.bounds, resolution=g.shape)[0].points
    assert np.abs(g(p[:, 0], p[:, 1])).max() <= 1e-12


def test_saddles_follow_the_centre_value():
    # two discs touching at a saddle point: the centre of the saddle cell decides
    def f(x, y):
        return x * y + 0.01

    cs = contours(f, bounds=[(-1, 1), (-1, 1)], resolution=2)  # one saddle cell
    assert len(cs) == 2 and not any(c.closed for c in cs)
    for c in cs:
        assert np.abs(f(*c.points.T)).max() <= 1e-12


def _svg_points(path):
    root = ET.parse(path).getroot()
    ns = {"s": "http://www.w3.org/2000/svg"}
    group = root.find("s:g", ns)
    assert "matrix(1 0 0 -1 0" in group.get("transform")
    out = []
    for p in group.findall("s:path", ns):
        for sub in re.split(r"(?=M )", p.get("d")):
            if not sub.strip():
                continue
            nums = [float(t) for t in re.findall(r"[-+0-9.eE]+", sub)]
            out.append((np.array(nums).reshape(-1, 2), sub.strip().endswith("Z")))
    return out


def test_svg_reads_back_to_the_same_points(tmp_path):
    world = _numpy(
        (sdf.Circle([0, 0], 0.8) - sdf.Circle([0, 0], 0.4)) | sdf.Box([1.2, -0.5], [1.8, 0.5])
    )
    target = tmp_path / "world.svg"
    cs = to_svg(target, world, bounds=BOUNDS, resolution=80)
    back = _svg_points(target)
    assert len(back) == len(cs) == 3
    for c, (pts, closed) in zip(cs, back, strict=True):
        np.testing.assert_array_equal(pts, c.points)  # repr: exact round trip
        assert closed == c.closed
    # filled: one path (even-odd) holding every loop
    to_svg(target, cs, fill="black")
    assert len(_svg_points(target)) == 3
    assert [n for n in os.listdir(tmp_path) if n.startswith(".tmp")] == []


def test_dxf_reads_back(tmp_path):
    import ezdxf

    cs = contours(
        _numpy(sdf.Circle([0, 0], 1.0) - sdf.Circle([0, 0], 0.5)), bounds=BOUNDS, resolution=40
    )
    target = tmp_path / "ring.dxf"
    to_dxf(target, cs)
    polys = list(ezdxf.readfile(target).modelspace().query("LWPOLYLINE"))
    assert len(polys) == 2 and all(p.closed for p in polys)
    got = sorted((np.array([v[:2] for v in p.get_points()]) for p in polys), key=len)
    want = sorted((c.points for c in cs), key=len)
    for g, w in zip(got, want, strict=True):
        np.testing.assert_allclose(g, w, atol=1e-12)


def test_failed_write_leaves_the_old_file(tmp_path):
    target = tmp_path / "keep.svg"
    target.write_text("old")
    with pytest.raises(TypeError):
        to_svg(target, [Contour(np.zeros((2, 2)), False), "not a contour"])
    assert target.read_text() == "old"


@pytest.mark.parametrize(
    "kw, err",
    [
        ({"resolution": 1}, ValueError),
        ({"bounds": [(1, 0), (0, 1)]}, ValueError),
        ({"level": float("nan")}, ValueError),
        ({"resolution": "many"}, TypeError),
    ],
)
def test_bad_input(kw, err):
    args = {"bounds": BOUNDS}
    args.update(kw)
    with pytest.raises(err):
        contours(_numpy(sdf.Circle([0, 0], 1.0)), **args)
