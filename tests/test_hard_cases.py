"""Hard cases: damaged kernel caches, gradients exactly on boundaries and spines, subnormal and
extreme coordinates, degenerate parameters."""

import math
import os
import subprocess
import sys
import textwrap

import numpy as np
import pytest

import fastsdf as sdf

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))

# ---------------------------------------------------------------------------------------------
# The kernel cache: any damaged file is detected, repaired once, and never crashes a process.

_CACHE_SCRIPT = textwrap.dedent("""
    import sys, warnings
    import numpy as np
    warnings.simplefilter("always")

    f = sdf.Circle([0.1, 0.0], 0.5) | sdf.Box([0.0, 0.0], [1.0, 1.0])
    d, g = f(np.array([0.3]), np.array([0.2]), compute_gradient=True)
    k = f.compiled.module.batch_vg_ser
    print("RESULT", repr(float(d[0])), repr(float(g[0, 0])), repr(float(g[0, 1])),
          sum(k.stats.cache_hits.values()), sum(k.stats.cache_misses.values()))
""")


def _run_cache_script(cache, background=False):
    env = dict(os.environ, FASTSDF_CACHE_DIR=str(cache), PYTHONPATH=ROOT,
               PYTHONWARNINGS="always")
    args = [sys.executable, "-c", _CACHE_SCRIPT]
    if background:
        return subprocess.Popen(args, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                                text=True)
    return subprocess.run(args, env=env, capture_output=True, text=True, timeout=600)


def _parse(proc):
    out, err = proc.stdout, proc.stderr
    assert proc.returncode == 0, err[-3000:]
    line = [s for s in out.splitlines() if s.startswith("RESULT")][-1].split()
    return (tuple(float(v) for v in line[1:4]), int(line[4]), int(line[5]),
            err.count("fastsdf: kernel cache:"))


def _cache_files(cache):
    files = sorted(p for p in cache.rglob("*") if p.is_file() and p.suffix in (".py", ".nbi",
                                                                                ".nbc"))
    assert any(p.suffix == ".nbi" for p in files) and any(p.suffix == ".nbc" for p in files)
    return files


def _truncate(p):
    data = p.read_bytes()
    p.write_bytes(data[:len(data) // 2])


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
    module = [p for p in files if p.suffix == ".py"]
    point = [p for p in files if ".point_vg-" in p.name]
    batch = [p for p in files if ".batch_vg_ser-" in p.name]
    assert len(module) == 1 and len(point) == 2 and len(batch) == 2
    _truncate(module[0])
    for p in point:  # a valid index in front of an altered data file
        if p.suffix == ".nbc":
            _flip(p)
    for p in batch:  # an empty index, a data file that is not a pickle at all
        p.write_bytes(b"" if p.suffix == ".nbi" else b"\x80\x05garbage" * 5)
    repaired = _parse(_run_cache_script(cache))
    assert repaired[0] == value  # the same answer, computed afresh
    assert repaired[2:] == (1, 3)  # recompiled; module, point_vg, batch_vg_ser reported once
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

    add("circle", lambda: sdf.Circle([0.3 * s, -0.2 * s], 0.7 * s),
        lambda rng: scaled(_on_circle([0.3, -0.2], 0.7, rng)),
        lambda rng: np.array([[0.3, -0.2]]) * s)
    box = [(-1.0, -0.5), (1.5, -0.5), (1.5, 1.0), (-1.0, 1.0)]

    def box_spine(rng):
        u = rng.uniform(0.0, 0.7, 8)
        c = np.array([0.25, 0.25])
        return np.concatenate([c[None], np.stack([1.5 - u, 1.0 - u], -1),
                               np.stack([-1.0 + u, -0.5 + u], -1)]) * s
    add("box", lambda: sdf.Box([-1 * s, -0.5 * s], [1.5 * s, 1 * s]),
        lambda rng: scaled(_on_edges(box, rng)), box_spine)

    def rbox_boundary(rng):
        p, n = _on_edges([(-0.5, -0.5), (0.5, -0.5), (0.5, 0.5), (-0.5, 0.5)], rng,
                         margin=0.35)
        q, m = _on_circle([0.3, 0.3], 0.2, rng, 8, 0.05, math.pi / 2 - 0.05)
        return np.concatenate([p, q]) * s, np.concatenate([n, m])
    add("rounded_box", lambda: sdf.RoundedBox([-0.5 * s, -0.5 * s], [0.5 * s, 0.5 * s],
                                              [0.2 * s, 0.1 * s, 0.0, 0.15 * s]),
        rbox_boundary, lambda rng: np.zeros((1, 2)))
    a, b, th = np.array([-0.5, 0.2]), np.array([0.8, 0.6]), 0.4
    d = (b - a) / np.hypot(*(b - a))
    nn = np.array([-d[1], d[0]]) * th / 2
    obox = [a - nn, b - nn, b + nn, a + nn]
    add("oriented_box", lambda: sdf.OrientedBox(a * s, b * s, th * s),
        lambda rng: scaled(_on_edges(obox, rng)),
        lambda rng: (a + th / 2 * d + rng.uniform(0, 1, (6, 1)) * (b - a - th * d)) * s)
    tri = [(-0.5, -0.4), (1.0, 0.1), (0.1, 0.9)]
    t = np.array(tri)
    sides = np.hypot(*(np.roll(t, -1, 0) - np.roll(t, 1, 0)).T)
    add("triangle", lambda: sdf.Triangle(*(np.array(tri) * s)),
        lambda rng: scaled(_on_edges(_ccw(tri), rng)),
        lambda rng: (sides @ t / sides.sum())[None] * s)
    hexv = np.stack([0.8 * np.cos(math.pi / 2 + np.arange(6) * math.pi / 3),
                     0.8 * np.sin(math.pi / 2 + np.arange(6) * math.pi / 3)], -1)
    add("regular_polygon", lambda: sdf.RegularPolygon([0, 0], 0.8 * s, 6),
        lambda rng: scaled(_on_edges(hexv, rng)), lambda rng: np.zeros((1, 2)))
    tri3 = np.stack([0.8 * np.cos(math.pi / 2 + np.arange(3) * 2 * math.pi / 3),
                     0.8 * np.sin(math.pi / 2 + np.arange(3) * 2 * math.pi / 3)], -1)
    add("equilateral_triangle", lambda: sdf.EquilateralTriangle([0, 0], 0.8 * s),
        lambda rng: scaled(_on_edges(tri3, rng)), lambda rng: np.zeros((1, 2)))
    poly = [(-1.0, -0.6), (1.0, -0.6), (1.0, 0.9), (0.0, 0.1), (-1.0, 0.9)]
    add("polygon", lambda: sdf.Polygon(np.array(poly) * s),
        lambda rng: scaled(_on_edges(_ccw(poly), rng)),
        lambda rng: np.array([[-0.6, -0.2], [0.6, -0.2]]) * s)
    tt = math.pi / 2 + math.pi * np.arange(10) / 5
    rr = np.where(np.arange(10) % 2 == 0, 1.0, 0.45)
    star = np.stack([rr * np.cos(tt), rr * np.sin(tt)], -1)
    add("star", lambda: sdf.Star([0, 0], 1.0 * s, 5, 0.45 * s),
        lambda rng: scaled(_on_edges(star, rng)), lambda rng: np.zeros((1, 2)))
    sa, sb = np.array([-0.3, 0.1]), np.array([0.6, 0.5])
    e = (sb - sa) / np.hypot(*(sb - sa))
    left = np.array([-e[1], e[0]])

    def on_spine(rng):
        return (sa + rng.uniform(0.02, 0.98, (12, 1)) * (sb - sa)) * s
    add("segment", lambda: sdf.Segment(sa * s, sb * s),
        lambda rng: (on_spine(rng), np.repeat(left[None], 12, 0)))

    def capsule_boundary(rng):
        p = sa + rng.uniform(0.02, 0.98, (12, 1)) * (sb - sa)
        side = np.where(rng.uniform(size=(12, 1)) < 0.5, -1.0, 1.0)
        ang = math.atan2(e[1], e[0])  # the cap at b faces along e
        q, m = _on_circle(sb, 0.25, rng, 8, ang - math.pi / 2 + 0.05, ang + math.pi / 2 - 0.05)
        return np.concatenate([p + 0.25 * side * left, q]) * s, \
            np.concatenate([side * left, m])
    add("capsule", lambda: sdf.Capsule(sa * s, sb * s, 0.25 * s), capsule_boundary, on_spine)
    ea, eb = 1.0, 0.4

    def ellipse_boundary(rng):
        t = rng.uniform(0, 2 * math.pi, 24)
        p = np.stack([ea * np.cos(t), eb * np.sin(t)], -1)
        n = np.stack([np.cos(t) / ea, np.sin(t) / eb], -1)
        return p * s, n / np.hypot(*n.T)[:, None]
    add("ellipse", lambda: sdf.Ellipse([0, 0], [ea * s, eb * s]), ellipse_boundary,
        lambda rng: np.concatenate([np.zeros((1, 2)), np.stack(
            [rng.uniform(-0.8, 0.8, 6) * (ea - eb * eb / ea), np.zeros(6)], -1)]) * s)

    def ring_boundary(rng):
        p, n = _on_circle([0, 0], 0.8, rng, 12)
        q, m = _on_circle([0, 0], 0.6, rng, 12, outward=-1.0)
        return np.concatenate([p, q]) * s, np.concatenate([n, m])
    add("ring", lambda: sdf.Ring([0, 0], 0.7 * s, 0.2 * s), ring_boundary,
        lambda rng: np.concatenate([np.zeros((1, 2)), _on_circle([0, 0], 0.7, rng, 8)[0]]) * s)

    def arc_boundary(rng):  # aperture pi about +y: the upper half circle
        p, n = _on_circle([0, 0], 0.8, rng, 12, 0.05, math.pi - 0.05)
        q, m = _on_circle([0, 0], 0.6, rng, 12, 0.05, math.pi - 0.05, outward=-1.0)
        return np.concatenate([p, q]) * s, np.concatenate([n, m])
    add("arc", lambda: sdf.Arc([0, 0], 0.7 * s, math.pi, 0.2 * s), arc_boundary,
        lambda rng: _on_circle([0, 0], 0.7, rng, 8, 0.0, math.pi)[0] * s)

    def half_boundary(rng):
        n = np.array([0.3, -1.0]) / np.hypot(0.3, 1.0)
        return (n * -20.0 + rng.uniform(-3, 3, (12, 1)) * np.array([-n[1], n[0]])) * s, \
            np.repeat(n[None], 12, 0)
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
        with sdf.transform(angle=angle, offset=tuple(np.asarray(offset) * s)), \
                sdf.transform(offset=tuple(place * s)):
            g = build()
        f = g if f is None else f | g
        pts, nrm = boundary(rng)
        samples.append((name, to_world(pts), nrm @ rot.T, to_world(spine(rng))))
    _WORLDS[key] = f, samples
    return f, samples


@pytest.mark.parametrize("s,tf", [(1.0, None), (1.0, (0.7, (0.3, -0.2))),
                                  (1e-149, None), (4e148, (-2.1, (1.0, 2.0)))])
def test_unit_normals_on_every_boundary_and_spine(s, tf):
    """Every primitive, on random points of each edge (within rounding of it, or exactly on
    it where the coordinates are representable) and on its spine and centre: the gradient
    is the analytic outward normal (so of unit length) to 1e-12; at unit scale and at both ends
    of the supported range (the smallest lengths 1e-150, the largest coordinates 1e150)."""
    f, samples = _world(s, tf)
    for name, pts, nrm, spine in samples:
        d, g = f(pts[:, 0], pts[:, 1], compute_gradient=True)
        assert np.all(np.abs(d) <= 1e-12 * 25 * s), (name, np.abs(d).max() / s)
        err = np.abs(g - nrm).max(axis=1)
        if name == "segment":  # unsigned: within rounding of it either side's normal is right
            err = np.minimum(err, np.abs(g + nrm).max(axis=1))
        assert np.all(err <= 1e-12), (name, err.max(), pts[np.argmax(err)])
        if len(spine):
            d, g = f(spine[:, 0], spine[:, 1], compute_gradient=True)
            assert np.all(np.isfinite(d)), name
            unit = np.abs(np.hypot(g[:, 0], g[:, 1]) - 1.0)
            assert np.all(unit <= 1e-12), (name, unit.max(), spine[np.argmax(unit)])
