"""Hard cases: damaged kernel caches, gradients exactly on boundaries and spines, subnormal and
extreme coordinates, degenerate parameters; the boundary, spine and range cases on the CPU
kernel and on the CUDA target."""

import math
import os
import subprocess
import sys
import textwrap

import numpy as np
import pytest
from conftest import HAS_NUMBA_CUDA

import fastsdf as sdf

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))

# ---------------------------------------------------------------------------------------------
# The kernel cache: any damaged file is detected, repaired once, and never crashes a process.

_CACHE_SCRIPT = textwrap.dedent("""
    import sys, warnings
    import numpy as np
    warnings.simplefilter("always")
    import fastsdf as sdf
    f = sdf.Circle([0.1, 0.0], 0.5) | sdf.Box([0.0, 0.0], [1.0, 1.0])
    d, g = f(np.array([0.3]), np.array([0.2]), compute_gradient=True, backend="kernel")
    k = f.compiled.blocks._block_vg
    f.point_fn(0.3, 0.2)  # a second cached function of the scene
    print("RESULT", repr(float(d[0])), repr(float(g[0, 0])), repr(float(g[0, 1])),
          sum(k.stats.cache_hits.values()), sum(k.stats.cache_misses.values()))
""")


def _run_cache_script(cache, background=False):
    env = dict(os.environ, FASTSDF_CACHE_DIR=str(cache), PYTHONPATH=ROOT, PYTHONWARNINGS="always")
    args = [sys.executable, "-c", _CACHE_SCRIPT]
    if background:
        return subprocess.Popen(
            args, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True
        )
    return subprocess.run(args, env=env, capture_output=True, text=True, timeout=600)


def _parse(proc):
    out, err = proc.stdout, proc.stderr
    assert proc.returncode == 0, err[-3000:]
    line = [s for s in out.splitlines() if s.startswith("RESULT")][-1].split()
    return (
        tuple(float(v) for v in line[1:4]),
        int(line[4]),
        int(line[5]),
        err.count("fastsdf: kernel cache:"),
    )


def _cache_files(cache):
    files = sorted(
        p for p in cache.rglob("*") if p.is_file() and p.suffix in (".py", ".nbi", ".nbc")
    )
    assert any(p.suffix == ".nbi" for p in files) and any(p.suffix == ".nbc" for p in files)
    return files


def _truncate(p):
    data = p.read_bytes()
    p.write_bytes(data[: len(data) // 2])


def _flip(p):
    data = bytearray(p.read_bytes())
    data[len(data) * 2 // 3] ^= 0x40
    p.write_bytes(bytes(data))


@pytest.mark.slow
def test_damaged_cache_files_are_repaired_once(tmp_path):
    """Truncated, altered, emptied and foreign files: every process gets the right answer, the
    first one repairs and reports each damaged entry once, the next one loads cleanly; then the
    same with three processes racing on a damaged cache."""
    cache = tmp_path / "cache"
    value, hits, misses, reports = _parse(_run_cache_script(cache))
    assert (hits, misses, reports) == (0, 1, 0)
    files = _cache_files(cache)
    modules = [p for p in files if p.suffix == ".py"]  # the scene's and its structure's
    blocks = [p for p in modules if p.name.startswith("fastsdf_blocks_")]
    point = [p for p in files if "._block_vg-" in p.name]
    batch = [p for p in files if ".point_vg-" in p.name]
    assert len(modules) == 2 and len(blocks) == 1 and len(point) == 2 and len(batch) == 2
    _truncate(blocks[0])
    for p in point:  # a valid index in front of an altered data file
        if p.suffix == ".nbc":
            _flip(p)
    for p in batch:  # an empty index, a data file that is not a pickle at all
        p.write_bytes(b"" if p.suffix == ".nbi" else b"\x80\x05garbage" * 5)
    repaired = _parse(_run_cache_script(cache))
    assert repaired[0] == value  # the same answer, computed afresh
    assert repaired[2:] == (1, 3)  # recompiled; blocks module, _block_vg, point_vg reported once
    again = _parse(_run_cache_script(cache))
    assert again == (value, 1, 0, 0)  # loaded from the repaired cache, nothing to report

    for p in _cache_files(cache):
        _truncate(p)
    procs = [_run_cache_script(cache, background=True) for _ in range(3)]
    for p in procs:
        p.wait(timeout=600)
        p.stdout, p.stderr = p.stdout.read(), p.stderr.read()
        assert _parse(p)[0] == value
    assert _parse(_run_cache_script(cache)) == (value, 1, 0, 0)
    assert not [p.name for p in cache.rglob("*") if ".tmp" in p.name]  # no temporary leftovers


# ---------------------------------------------------------------------------------------------
# A catalogue of every primitive, each with samplers of its boundary (points and the analytic
# outward normal) and of its spine (centre, medial axis), in local coordinates of size ~1.


def _on_edges(vertices, rng, k=12, closed=True, margin=0.02):
    """Random points on each edge (away from the vertices) and the outward normals of a
    counter-clockwise polygon (for a polyline: the left normals)."""
    v = np.asarray(vertices, dtype=float)
    pairs = list(zip(v, np.roll(v, -1, axis=0))) if closed else list(zip(v[:-1], v[1:]))
    pts, nrm = [], []
    for a, b in pairs:
        e = b - a
        s = rng.uniform(margin, 1 - margin, k)
        pts.append(a + s[:, None] * e)
        n = np.array([e[1], -e[0]]) / np.hypot(*e)
        nrm.append(np.repeat(n[None], k, 0) * (1 if closed else -1))
    return np.concatenate(pts), np.concatenate(nrm)


def _on_circle(c, r, rng, k=24, t0=0.0, t1=2 * math.pi, outward=1.0):
    t = rng.uniform(t0, t1, k)
    n = np.stack([np.cos(t), np.sin(t)], -1)
    return np.asarray(c) + r * n, outward * n


def _ccw(v):
    v = np.asarray(v, dtype=float)
    a = np.sum(v[:, 0] * np.roll(v[:, 1], -1) - np.roll(v[:, 0], -1) * v[:, 1])
    return v if a > 0 else v[::-1]


def _catalogue(s):
    """(name, build, boundary(rng) -> (points, normals), spine(rng) -> points) for every
    primitive, with every length multiplied by ``s``."""
    out = []

    def add(name, build, boundary, spine=None):
        out.append((name, build, boundary, spine or (lambda rng: np.zeros((0, 2)))))

    def scaled(pts_normals):
        p, n = pts_normals
        return p * s, n

    add(
        "circle",
        lambda: sdf.Circle([0.3 * s, -0.2 * s], 0.7 * s),
        lambda rng: scaled(_on_circle([0.3, -0.2], 0.7, rng)),
        lambda rng: np.array([[0.3, -0.2]]) * s,
    )
    box = [(-1.0, -0.5), (1.5, -0.5), (1.5, 1.0), (-1.0, 1.0)]

    def box_spine(rng):
        u = rng.uniform(0.0, 0.7, 8)
        c = np.array([0.25, 0.25])
        return (
            np.concatenate(
                [c[None], np.stack([1.5 - u, 1.0 - u], -1), np.stack([-1.0 + u, -0.5 + u], -1)]
            )
            * s
        )

    add(
        "box",
        lambda: sdf.Box([-1 * s, -0.5 * s], [1.5 * s, 1 * s]),
        lambda rng: scaled(_on_edges(box, rng)),
        box_spine,
    )

    def rbox_boundary(rng):
        p, n = _on_edges([(-0.5, -0.5), (0.5, -0.5), (0.5, 0.5), (-0.5, 0.5)], rng, margin=0.35)
        q, m = _on_circle([0.3, 0.3], 0.2, rng, 8, 0.05, math.pi / 2 - 0.05)
        return np.concatenate([p, q]) * s, np.concatenate([n, m])

    add(
        "rounded_box",
        lambda: sdf.RoundedBox(
            [-0.5 * s, -0.5 * s], [0.5 * s, 0.5 * s], [0.2 * s, 0.1 * s, 0.0, 0.15 * s]
        ),
        rbox_boundary,
        lambda rng: np.zeros((1, 2)),
    )
    a, b, th = np.array([-0.5, 0.2]), np.array([0.8, 0.6]), 0.4
    d = (b - a) / np.hypot(*(b - a))
    nn = np.array([-d[1], d[0]]) * th / 2
    obox = [a - nn, b - nn, b + nn, a + nn]
    add(
        "oriented_box",
        lambda: sdf.OrientedBox(a * s, b * s, th * s),
        lambda rng: scaled(_on_edges(obox, rng)),
        lambda rng: (a + th / 2 * d + rng.uniform(0, 1, (6, 1)) * (b - a - th * d)) * s,
    )
    tri = [(-0.5, -0.4), (1.0, 0.1), (0.1, 0.9)]
    t = np.array(tri)
    sides = np.hypot(*(np.roll(t, -1, 0) - np.roll(t, 1, 0)).T)
    add(
        "triangle",
        lambda: sdf.Triangle(*(np.array(tri) * s)),
        lambda rng: scaled(_on_edges(_ccw(tri), rng)),
        lambda rng: (sides @ t / sides.sum())[None] * s,
    )
    hexv = np.stack(
        [
            0.8 * np.cos(math.pi / 2 + np.arange(6) * math.pi / 3),
            0.8 * np.sin(math.pi / 2 + np.arange(6) * math.pi / 3),
        ],
        -1,
    )
    add(
        "regular_polygon",
        lambda: sdf.RegularPolygon([0, 0], 0.8 * s, 6),
        lambda rng: scaled(_on_edges(hexv, rng)),
        lambda rng: np.zeros((1, 2)),
    )
    tri3 = np.stack(
        [
            0.8 * np.cos(math.pi / 2 + np.arange(3) * 2 * math.pi / 3),
            0.8 * np.sin(math.pi / 2 + np.arange(3) * 2 * math.pi / 3),
        ],
        -1,
    )
    add(
        "equilateral_triangle",
        lambda: sdf.EquilateralTriangle([0, 0], 0.8 * s),
        lambda rng: scaled(_on_edges(tri3, rng)),
        lambda rng: np.zeros((1, 2)),
    )
    poly = [(-1.0, -0.6), (1.0, -0.6), (1.0, 0.9), (0.0, 0.1), (-1.0, 0.9)]
    add(
        "polygon",
        lambda: sdf.Polygon(np.array(poly) * s),
        lambda rng: scaled(_on_edges(_ccw(poly), rng)),
        lambda rng: np.array([[-0.6, -0.2], [0.6, -0.2]]) * s,
    )
    tt = math.pi / 2 + math.pi * np.arange(10) / 5
    rr = np.where(np.arange(10) % 2 == 0, 1.0, 0.45)
    star = np.stack([rr * np.cos(tt), rr * np.sin(tt)], -1)
    add(
        "star",
        lambda: sdf.Star([0, 0], 1.0 * s, 5, 0.45 * s),
        lambda rng: scaled(_on_edges(star, rng)),
        lambda rng: np.zeros((1, 2)),
    )
    sa, sb = np.array([-0.3, 0.1]), np.array([0.6, 0.5])
    e = (sb - sa) / np.hypot(*(sb - sa))
    left = np.array([-e[1], e[0]])

    def on_spine(rng):
        return (sa + rng.uniform(0.02, 0.98, (12, 1)) * (sb - sa)) * s

    add(
        "segment",
        lambda: sdf.Segment(sa * s, sb * s),
        lambda rng: (on_spine(rng), np.repeat(left[None], 12, 0)),
    )

    def capsule_boundary(rng):
        p = sa + rng.uniform(0.02, 0.98, (12, 1)) * (sb - sa)
        side = np.where(rng.uniform(size=(12, 1)) < 0.5, -1.0, 1.0)
        ang = math.atan2(e[1], e[0])  # the cap at b faces along e
        q, m = _on_circle(sb, 0.25, rng, 8, ang - math.pi / 2 + 0.05, ang + math.pi / 2 - 0.05)
        return np.concatenate([p + 0.25 * side * left, q]) * s, np.concatenate([side * left, m])

    add("capsule", lambda: sdf.Capsule(sa * s, sb * s, 0.25 * s), capsule_boundary, on_spine)
    ea, eb = 1.0, 0.4

    def ellipse_boundary(rng):
        t = rng.uniform(0, 2 * math.pi, 24)
        p = np.stack([ea * np.cos(t), eb * np.sin(t)], -1)
        n = np.stack([np.cos(t) / ea, np.sin(t) / eb], -1)
        return p * s, n / np.hypot(*n.T)[:, None]

    add(
        "ellipse",
        lambda: sdf.Ellipse([0, 0], [ea * s, eb * s]),
        ellipse_boundary,
        lambda rng: (
            np.concatenate(
                [
                    np.zeros((1, 2)),
                    np.stack([rng.uniform(-0.8, 0.8, 6) * (ea - eb * eb / ea), np.zeros(6)], -1),
                ]
            )
            * s
        ),
    )

    def ring_boundary(rng):
        p, n = _on_circle([0, 0], 0.8, rng, 12)
        q, m = _on_circle([0, 0], 0.6, rng, 12, outward=-1.0)
        return np.concatenate([p, q]) * s, np.concatenate([n, m])

    add(
        "ring",
        lambda: sdf.Ring([0, 0], 0.7 * s, 0.2 * s),
        ring_boundary,
        lambda rng: np.concatenate([np.zeros((1, 2)), _on_circle([0, 0], 0.7, rng, 8)[0]]) * s,
    )

    def arc_boundary(rng):  # aperture pi about +y: the upper half circle
        p, n = _on_circle([0, 0], 0.8, rng, 12, 0.05, math.pi - 0.05)
        q, m = _on_circle([0, 0], 0.6, rng, 12, 0.05, math.pi - 0.05, outward=-1.0)
        return np.concatenate([p, q]) * s, np.concatenate([n, m])

    add(
        "arc",
        lambda: sdf.Arc([0, 0], 0.7 * s, math.pi, 0.2 * s),
        arc_boundary,
        lambda rng: _on_circle([0, 0], 0.7, rng, 8, 0.0, math.pi)[0] * s,
    )

    def half_boundary(rng):
        n = np.array([0.3, -1.0]) / np.hypot(0.3, 1.0)
        return (n * -20.0 + rng.uniform(-3, 3, (12, 1)) * np.array([-n[1], n[0]])) * s, np.repeat(
            n[None], 12, 0
        )

    add("halfspace", lambda: sdf.Halfspace([0.3, -1.0], -20.0 * s), half_boundary)
    return out


_CELL = 4.0  # primitives sit 4 units apart: each one's samples see only itself


def _cells(n):
    cols = 4
    return [np.array([(i % cols) * _CELL, (i // cols) * _CELL]) for i in range(n)]


_WORLDS = {}


def _world(s, tf=None):
    """The union of every primitive (each placed in its own cell, the half-plane far below),
    built at scale ``s`` under the transform ``tf`` = (angle, offset at unit scale), with the
    world samples: (f, [(name, boundary points, normals, spine points)], map to world)."""
    key = (s, tf)
    if key in _WORLDS:
        return _WORLDS[key]
    rng = np.random.default_rng(7)
    cat = _catalogue(s)
    angle, offset = tf if tf is not None else (0.0, (0.0, 0.0))
    c, sn = math.cos(angle), math.sin(angle)
    rot = np.array([[c, -sn], [sn, c]])
    f, samples = None, []
    for (name, build, boundary, spine), cell in zip(cat, _cells(len(cat))):
        place = np.zeros(2) if name == "halfspace" else cell

        def to_world(p, place=place):
            return (p + place * s) @ rot.T + np.asarray(offset) * s

        with (
            sdf.transform(angle=angle, offset=tuple(np.asarray(offset) * s)),
            sdf.transform(offset=tuple(place * s)),
        ):
            g = build()
        f = g if f is None else f | g
        pts, nrm = boundary(rng)
        samples.append((name, to_world(pts), nrm @ rot.T, to_world(spine(rng))))
    _WORLDS[key] = f, samples
    return f, samples


#: The compiled kernel, and the CUDA target (under numba-cuda's simulator without a GPU).
TARGETS = ["kernel", "cuda"] if HAS_NUMBA_CUDA else ["kernel"]


@pytest.mark.parametrize("backend", TARGETS)
@pytest.mark.parametrize(
    "s,tf", [(1.0, None), (1.0, (0.7, (0.3, -0.2))), (1e-149, None), (4e148, (-2.1, (1.0, 2.0)))]
)
def test_unit_normals_on_every_boundary_and_spine(s, tf, backend):
    """Every primitive, on random points of each edge (within rounding of it, or exactly on
    it where the coordinates are representable) and on its spine and centre: the gradient
    is the analytic outward normal (so of unit length) to 1e-12; at unit scale and at both ends
    of the supported range (the smallest lengths 1e-150, the largest coordinates 1e150)."""
    f, samples = _world(s, tf)
    for name, pts, nrm, spine in samples:
        d, g = f(pts[:, 0], pts[:, 1], compute_gradient=True, backend=backend)
        assert np.all(np.abs(d) <= 1e-12 * 25 * s), (name, np.abs(d).max() / s)
        err = np.abs(g - nrm).max(axis=1)
        if name == "segment":  # unsigned: within rounding of it either side's normal is right
            err = np.minimum(err, np.abs(g + nrm).max(axis=1))
        assert np.all(err <= 1e-12), (name, err.max(), pts[np.argmax(err)])
        if len(spine):
            d, g = f(spine[:, 0], spine[:, 1], compute_gradient=True, backend=backend)
            assert np.all(np.isfinite(d)), name
            unit = np.abs(np.hypot(g[:, 0], g[:, 1]) - 1.0)
            assert np.all(unit <= 1e-12), (name, unit.max(), spine[np.argmax(unit)])


@pytest.mark.parametrize("backend", TARGETS)
@pytest.mark.parametrize("s", [2.0**-494, 2.0**493])
def test_values_at_the_ends_of_the_range_are_the_unit_values_scaled(s, backend):
    """The whole catalogue at a power-of-two scale near each end of the supported range: at
    random points around every primitive, value / s and gradient equal the unit-scale ones to
    rounding (no silent over- or underflow anywhere in between)."""
    f1, samples = _world(1.0)
    fs, _ = _world(s)
    rng = np.random.default_rng(3)
    pts = np.concatenate(
        [np.asarray(cell) + rng.uniform(-2.0, 2.0, (60, 2)) for cell in _cells(len(samples))]
    )
    d1, g1 = f1(pts[:, 0], pts[:, 1], compute_gradient=True)
    ds, gs = fs(pts[:, 0] * s, pts[:, 1] * s, compute_gradient=True, backend=backend)
    np.testing.assert_allclose(ds / s, d1, rtol=1e-12, atol=1e-13)
    same = np.abs(gs - g1).max(axis=1)
    # a gradient may flip only where the point is on a kink (a medial axis) to rounding
    near_kink = np.zeros(len(pts), bool)
    for h in (1e-9, -1e-9):
        _, gh = f1(pts[:, 0] + h, pts[:, 1] + h, compute_gradient=True)
        near_kink |= np.abs(gh - g1).max(axis=1) > 1e-6
    assert np.all(same[~near_kink] <= 1e-12), same[~near_kink].max()
    assert near_kink.mean() < 0.02


@pytest.mark.parametrize(
    "make,words",
    [
        (lambda: sdf.Circle([0, 0], 1e-151), "radius"),
        (lambda: sdf.Circle([0, 0], 1e151), "radius"),
        (lambda: sdf.Circle([2e150, 0], 1.0), "center"),
        (lambda: sdf.Halfspace([0, 1], 1e151), "d"),
        (lambda: sdf.Box([0, 0], [1e-151, 1]), "maxc - minc"),
        (lambda: sdf.Box([-1e151, 0], [1, 1]), "minc"),
        (lambda: sdf.Segment([0, 0], [1e-151, 0]), "segment length"),
        (lambda: sdf.Capsule([0, 0], [1, 0], 1e-160), "radius"),
        (lambda: sdf.OrientedBox([0, 0], [1, 0], 1e-151), "thickness"),
        (lambda: sdf.RoundedBox([0, 0], [1, 1], 1e-200), "radii"),
        (lambda: sdf.Triangle([0, 0], [1e-151, 0], [0, 1e-151]), "triangle"),
        (lambda: sdf.Polygon(np.array([[0, 0], [1, 0], [1, 1], [0, 1]]) * 1e160), "vertices"),
        (lambda: sdf.Polygon(np.array([[0, 0], [1, 0], [1, 1], [0, 1]]) * 1e-160), "polygon"),
        (lambda: sdf.RegularPolygon([0, 0], 1e-160, 5), "radius"),
        (lambda: sdf.Star([0, 0], 1.0, 5, 1e-160), "inner_radius"),
        (lambda: sdf.Ellipse([0, 0], [1e-160, 1]), "axes"),
        (lambda: sdf.Ellipse([0, 0], [1e-60, 1e60]), "axes"),
        (lambda: sdf.Ring([0, 0], 1.0, 1e-160), "thickness"),
        (lambda: sdf.Arc([0, 0], 1e151, 1.0, 1.0), "radius"),
        (lambda: sdf.Circle().round(1e-160), "r"),
        (lambda: sdf.Circle().shell(1e160), "thickness"),
        (lambda: sdf.Circle().scale(1e-151), "s"),
        (lambda: sdf.Circle().translate([0, 1e151]), "offset"),
        (lambda: sdf.Circle().repeat(1e-151, 3), "spacing"),
        (lambda: sdf.transform(offset=[1e151, 0]), "offset"),
        (lambda: sdf.smoothness(1e-151), "smoothness k"),
        (lambda: sdf.smoothness(1e151, kind="quadratic"), "smoothness k"),
        (lambda: sdf.Circle().union(sdf.Box(), 1e-310, "quadratic"), "k"),
        (lambda: sdf.Circle().intersection(sdf.Box(), 1e-310, "cubic"), "k"),
        (lambda: sdf.Circle().union(sdf.Box(), 1e-310), "k"),
    ],
)
def test_outside_the_supported_range_is_a_clear_error(make, words):
    with pytest.raises(ValueError, match="1e-150 to 1e150|too small|factor") as info:
        make()
    assert words in str(info.value)


def test_graph_blends_reject_widths_whose_inverse_overflows():
    from fastsdf.expr.graph import Symbol, sym_cmin, sym_qmin, sym_smin

    x = Symbol("x")
    for op in (sym_qmin, sym_cmin, sym_smin):
        with pytest.raises(ValueError, match="too small"):
            op(x, -x, 1e-310)
    f = sdf.Circle().union(sdf.Box([0.5, -1], [2, 1]), 1e-150, "quadratic")  # smallest width
    d = f(np.array([0.75, 3.0]), np.array([0.0, 0.0]))
    assert np.all(np.isfinite(d)) and d[1] == pytest.approx(1.0)


def test_subnormal_and_zero_radius_gradients():
    """1/r overflowed for subnormal r: unit gradients, compiled and in the NumPy reference,
    at subnormal offsets from every centre (circle, ring, arc, ellipse, polygon vertex)."""
    from fastsdf.expr.graph import evaluate_numpy

    tiny = np.array(
        [
            [5e-324, 0.0],
            [0.0, -5e-324],
            [1e-323, 1.5e-323],
            [-4e-320, 2e-321],
            [1e-310, -1e-310],
            [0.0, 0.0],
            [3e-200, 4e-200],
        ]
    )
    fs = [
        sdf.Circle([0, 0], 1.0),
        sdf.Ring([0, 0], 1.0, 0.2),
        sdf.Arc([0, 0], 1.0),
        sdf.Ellipse([0, 0], [1.0, 1.0]),
        sdf.Capsule([0, 0], [0, 0], 0.5),
        sdf.Polygon([[0, 0], [1, 0], [0, 1]]),
    ]
    for f in fs:
        d, g = f(tiny[:, 0], tiny[:, 1], compute_gradient=True)
        assert np.all(np.isfinite(d)) and np.all(np.isfinite(g)), (f, g)
        np.testing.assert_allclose(np.hypot(g[:, 0], g[:, 1]), 1.0, atol=1e-12)
        if type(f).__name__ in ("Circle", "Ellipse", "Capsule"):
            nz = np.any(tiny != 0, axis=1)  # away from the centre: the exact radial direction
            scaled = np.hypot(tiny[nz, 0] * 2.0**600, tiny[nz, 1] * 2.0**600)
            want = tiny[nz] / scaled[:, None] * 2.0**600
            np.testing.assert_allclose(g[nz], want, atol=1e-15)
        if type(f).__name__ not in ("Polygon", "Ellipse"):  # graph-built: the NumPy reference
            dr, gr = evaluate_numpy(f.f, {"x": tiny[:, 0], "y": tiny[:, 1]}, compute_gradient=True)
            np.testing.assert_array_equal(dr, d)
            np.testing.assert_array_equal(np.stack(gr, -1), g)


def _ellipse_far_reference(p, a, b):
    """Distance to the ellipse far away, in closed form to O((max(a,b)/|p|)**2): |p| minus the
    support function in the direction of p."""
    r = math.hypot(*p)
    n = np.array(p) / r
    return r - math.hypot(a * n[0], b * n[1])


def test_ellipse_subnormal_near_axis_and_far_away():
    e = sdf.Ellipse([0, 0], [1.0, 0.5])
    pts = np.array(
        [
            [0.1, 1e-320],
            [0.1, 0.0],
            [0.1, -1e-320],
            [1e-310, 1e-310],
            [0.0, 0.0],
            [2.0, 1e-300],
            [2.0, 0.0],
            [1e-320, 0.3],
            [0.0, 0.3],
        ]
    )
    d, g = e(pts[:, 0], pts[:, 1], compute_gradient=True)
    assert d[0] == d[1] == d[2]  # a subnormal y changes nothing (it is below rounding)
    assert g[0, 1] == -g[2, 1] and np.all(g[[0, 1, 2], 0] == g[1, 0])
    assert d[3] == pytest.approx(-0.5, abs=1e-15) and d[4] == -0.5
    assert d[5] == d[6] == 1.0 and d[7] == d[8] == pytest.approx(-0.2, abs=1e-15)
    np.testing.assert_allclose(np.hypot(g[:, 0], g[:, 1]), 1.0, atol=1e-12)
    far = [
        ((1.0, 1e-9), (1e290, 1.0)),
        ((1e9, 1.0), (1e300, 1e300)),
        ((1.0, 0.5), (3e307, -3e307)),
        ((1.0, 0.5), (1e12, 3e11)),
        ((1.0, 0.5), (-7e20, 2e21)),
        ((2.0, 3.0), (1e150, -1e150)),
    ]
    for axes, p in far:
        f = sdf.Ellipse([0, 0], axes)
        d, g = f(np.array([p[0]]), np.array([p[1]]), compute_gradient=True)
        want = _ellipse_far_reference(p, *axes)
        assert d[0] == pytest.approx(want, rel=1e-14), (axes, p)
        np.testing.assert_allclose(g[0], np.array(p) / math.hypot(*p), atol=1e-12)
    # just inside the far-field switch and just outside it: the two formulas agree
    f = sdf.Ellipse([0, 0], [1.0, 0.25])
    r0 = 2.0**30 * 4.0
    t = np.linspace(0.1, 1.4, 7)
    pts = np.concatenate(
        [
            np.stack([r0 * 0.999 * np.cos(t), r0 * 0.999 * np.sin(t)], -1),
            np.stack([r0 * 1.001 * np.cos(t), r0 * 1.001 * np.sin(t)], -1),
        ]
    )
    d, g = f(pts[:, 0], pts[:, 1], compute_gradient=True)
    want = [_ellipse_far_reference(p, 1.0, 0.25) for p in pts]
    np.testing.assert_allclose(d, want, rtol=1e-15)


def test_particles_started_on_boundaries_and_spines_are_out_after_one_step():
    """A particle at rest exactly on any primitive's boundary or spine (within rounding) is
    pushed out of the solid by the first step (before, a box's face or a capsule's spine gave a
    zero gradient and the particle stayed inside for good)."""
    import fastsdf.particles as phys

    f, samples = _world(1.0, (0.7, (0.3, -0.2)))
    pts = np.concatenate([np.concatenate([p, s]) for _, p, _, s in samples])
    names = np.concatenate([[name] * (len(p) + len(s)) for name, p, _, s in samples])
    r = 0.01
    d0 = f(pts[:, 0], pts[:, 1])
    contact = d0 - r < 0  # all but the centre of the ring's hole
    assert contact.sum() == len(pts) - 1
    pts, names = pts[contact], names[contact]
    sim = phys.ParticleSimulation(f, n=len(pts), timestep=1e-3, seed=0, cr=0.5, cf=0.0)
    sim.p["x"] = pts
    sim.p["v"] = 0.0
    sim.p["r"] = r
    sim.run(1)
    x = np.asarray(sim.p["x"])
    d = f(x[:, 0], x[:, 1])
    bad = d - r < -1e-12
    assert not np.any(bad), sorted(set(names[bad]))
