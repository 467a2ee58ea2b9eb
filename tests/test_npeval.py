"""The NumPy path (``backend='numpy'``: the op table's reference formulas, no numba):
agreement with the compiled kernel (values 1e-12 relative, gradients 1e-9) on long
hard unions and intersections, nested chains, random point clouds with far, huge and non-finite
coordinates, parameters and symbol names, and a first answer that never touches numba. (Every
scene of test_reference.py is also checked through the NumPy path, by its ``assert_agree``.)"""

import json
import os
import subprocess
import sys

import numpy as np
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from test_reference import _points, assert_agree

import fastsdf as sdf
import fastsdf.graph as cg
from fastsdf.expr.graph import Symbol, sym_length

X, Y = Symbol("x"), Symbol("y")


def _shape(kind, rng):
    with sdf.transform(angle=rng.uniform(-3, 3), offset=rng.uniform(-1.9, 1.9, 2)):
        if kind == "box":
            return sdf.Box(-rng.uniform(0.02, 0.2, 2), rng.uniform(0.02, 0.2, 2))
        if kind == "circle":
            return sdf.Circle(rng.uniform(-0.1, 0.1, 2), rng.uniform(0.02, 0.2))
        return sdf.Capsule([0, 0], rng.uniform(0.05, 0.3, 2), rng.uniform(0.02, 0.1))


def _union(kinds, seed, intersect=False, raw=False):
    """A hard union (or a big disc minus every shape: a max chain) of shapes of a few kinds;
    ``raw``: circles from graph operations, with no Lipschitz note (interval bounds)."""
    rng = np.random.default_rng(seed)
    f = sdf.Circle([0, 0], 2.2) if intersect else sdf.Halfspace([0, 1], -1.8)
    e = f.f
    for kind in kinds:
        if raw:
            c, r = rng.uniform(-1.9, 1.9, 2), rng.uniform(0.02, 0.2)
            s = sym_length(X - float(c[0]), Y - float(c[1])) - float(r)
        else:
            s = _shape(kind, rng).f
        e = sdf.sym_max(e, -s) if intersect else sdf.sym_min(e, s)
    return sdf.Function(e, [X, Y])


def _clouds(seed):
    rng = np.random.default_rng(seed)
    yield _points(3000, seed)  # uniform, non-finite ones
    yield rng.normal([0.3, -0.2], 0.05, (2000, 2))  # clustered
    yield np.stack([rng.uniform(-2, 2, 3000), rng.uniform(0.1, 0.12, 3000)], 1)  # a strip
    yield np.array([[0.1, 0.2]])  # a single point
    yield np.concatenate([rng.uniform(-50, 50, (500, 2)), [[1e200, 0.0], [0.0, -1e200]]])


def test_pruned_chains_agree_with_the_kernel():
    """Hard union and intersection of 90 shapes of three kinds (one kernel each to compile)."""
    for intersect in (False, True):
        f = _union(["box", "circle", "capsule"] * 30, 1, intersect)
        assert_agree(f, _points(4000, 5), backends=("numpy",))


@settings(
    max_examples=8, deadline=None, derandomize=True, suppress_health_check=[HealthCheck.too_slow]
)
@given(
    kinds=st.lists(st.sampled_from(["box", "circle", "capsule"]), min_size=8, max_size=120),
    seed=st.integers(0, 10_000),
    intersect=st.booleans(),
    raw=st.booleans(),
)
def test_random_chains_and_clouds_agree_with_the_kernel(kinds, seed, intersect, raw):
    """Random hard chains on point clouds (uniform, clustered, a thin strip, one point, far away
    and huge coordinates, non-finite ones): the kernel's results to rounding, NaN exactly at
    the non-finite points."""
    f = _union(kinds, seed, intersect, raw)
    for p in _clouds(seed):
        d, g = f(*p.T, compute_gradient=True, backend="numpy")
        dt, gt = f(*p.T, compute_gradient=True, backend="kernel")
        ok = np.isfinite(p).all(axis=1)
        assert np.isnan(d[~ok]).all() and np.isnan(g[~ok]).all()
        np.testing.assert_allclose(d[ok], dt[ok], rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(g[ok], gt[ok], rtol=1e-9, atol=1e-9)
        np.testing.assert_array_equal(f(*p.T, backend="numpy"), d)


def test_parameters_and_symbol_names():
    """Runtime parameters are read per call; any two symbol names (in the given order)."""
    a = cg.Param("angle", 0.3)
    with sdf.transform(angle=a, offset=[0.1, 0.2]):
        bar = sdf.Box(minc=[-1, -0.1], maxc=[1, 0.1])
    f = bar | sdf.Circle([0.5, 0.4], 0.3).translate([0.0, 0.5 * sdf.t])
    p = _points(500, 7)
    for vals in ({}, dict(angle=-0.4, t=0.3)):
        d, g = f(*p.T, compute_gradient=True, backend="numpy", **vals)
        dt, gt = f(*p.T, compute_gradient=True, backend="kernel", **vals)
        ok = np.isfinite(p).all(axis=1)
        np.testing.assert_allclose(d[ok], dt[ok], rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(g[ok], gt[ok], rtol=1e-9, atol=1e-9)
    u, v = Symbol("u"), Symbol("v")
    h = sdf.Function(sdf.sym_sqrt(u * u + 4.0 * v * v) - 1.0 + 0.5 * v, [v, u])
    d, g = h(np.array([0.3]), np.array([0.7]), compute_gradient=True, backend="numpy")
    r = np.sqrt(0.49 + 4 * 0.09)
    np.testing.assert_allclose(d, [r - 1 + 0.15], rtol=1e-14)
    np.testing.assert_allclose(g[0], [4 * 0.3 / r + 0.5, 0.7 / r], rtol=1e-14)


_FRESH = r"""
import json, sys, numpy as np
import fastsdf
from fastsdf.shapes.scenes import box_world
f = box_world(20, seed=123)
x, y = np.random.default_rng(0).uniform(-2, 2, (2, 100_000))
d, g = f(x, y, compute_gradient=True, backend="numpy")
print(json.dumps({"numba_setup": "numba.np.arraymath" in sys.modules}))
"""


def test_first_answer_needs_no_numba(tmp_path):
    """In a fresh process, a new scene answers through NumPy without numba's one-time setup
    (which would import numba's registries: numba.np.arraymath)."""
    env = dict(os.environ, FASTSDF_CACHE_DIR=str(tmp_path))
    res = subprocess.run(
        [sys.executable, "-c", _FRESH], env=env, capture_output=True, text=True, timeout=300
    )
    assert res.returncode == 0, res.stderr
    out = json.loads(res.stdout.strip().splitlines()[-1])
    assert out == {"numba_setup": False}


def test_operands_that_differ_in_sharing_or_attributes():
    """Operands that differ only in sharing (``w + w`` with ``w`` shared; ``u * u + v * v``
    reading the same constants from two nodes) and attributes (smooth unions of different
    ``k``): the kernel's results."""
    rng = np.random.default_rng(4)
    e = None
    for i in range(120):
        c = rng.uniform(-2, 2, 4)
        u = (X - float(c[0])) * 0.7 + (Y - float(c[1]))
        v = (X - float(c[2])) * 0.7 + (Y - float(c[3]))
        s = [
            u * u + u * u - 0.01,
            u * u + v * v - 0.01,
            sdf.sym_smin(sym_length(u, v), sym_length(v, u), 2.0) - 0.05,
            sdf.sym_smin(sym_length(u, v), sym_length(v, u), 3.0) - 0.05,
        ][i % 4]
        e = s if e is None else sdf.sym_min(e, s)
    assert_agree(sdf.Function(e, [X, Y]), _points(2000, 8), backends=("numpy",))


def _nested(seed):
    """Hard chains below the root: a floor smoothly united with a union of 40 boxes, minus a
    union of 30 circles (a max whose operand is the negated min chain)."""
    rng = np.random.default_rng(seed)
    boxes = _shape("box", rng)
    for _ in range(39):
        boxes = boxes | _shape("box", rng)
    holes = _shape("circle", rng)
    for _ in range(29):
        holes = holes | _shape("circle", rng)
    with sdf.smoothness(8):
        f = sdf.Halfspace([0, 1], -1.8) | boxes
    return f - holes


def test_chains_below_the_root():
    """Hard chains anywhere in the expression: the kernel's answers."""
    f = _nested(2)
    assert_agree(f, _points(3000, 9), backends=("numpy",))
