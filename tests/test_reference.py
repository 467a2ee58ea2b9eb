"""The NumPy reference (``backend='numpy'``, the op table's formulas) against the compiled
kernels, to rounding (values 1e-12 relative, gradients 1e-9), on the bench scenes, random
scenes, every primitive kind, smooth and polynomial blends, transforms, parameters and
non-finite points; and the ``backend`` switch of Function (``'auto'`` answers with the kernel
and compiles the scene's other kinds meanwhile)."""

import json
import math
import os
import subprocess
import sys

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from test_codegen import (
    _long_straight_line_scene,
    _unstructured_scene,
    build_scene,
    operation,
    placed,
)

import fastsdf as sdf
import fastsdf.expr.graph  # sdf.graph
import fastsdf.graph as cg
from fastsdf.backends.kernel.layout import BLOCK
from fastsdf.expr.graph import Param, Symbol, evaluate_numpy
from fastsdf.shapes.scenes import box_world, seed_world

X, Y = Symbol("x"), Symbol("y")


def _points(n, seed, bad=True):
    p = np.random.default_rng(seed).uniform(-2.5, 2.5, (n, 2))
    if bad:  # non-finite coordinates: NaN for those points only
        p[::37, 0] = np.nan
        p[5::41, 1] = np.inf
        p[9::43, 0] = -np.inf
    return p


def assert_same_bits(a, b):
    """Equal bit patterns (any NaN equals any NaN: the payload is not a result)."""
    a, b = np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64)
    assert a.shape == b.shape
    same = (a.view(np.int64) == b.view(np.int64)) | (np.isnan(a) & np.isnan(b))
    bad = np.argwhere(~same)
    assert same.all(), (
        f"{len(bad)} of {a.size} differ, e.g. at {bad[:3].tolist()}: "
        f"{a[~same][:3].tolist()} vs {b[~same][:3].tolist()}"
    )


def assert_agree(f, p, backends=("numpy",), **params):
    """The NumPy path agrees with the kernel to rounding, value (also value-only calls) and
    gradient; non-finite points give NaN for those points only."""
    dk, gk = f(*p.T, compute_gradient=True, **params)
    ok = np.isfinite(p).all(axis=1)
    for backend in backends:
        dt, gt = f(*p.T, compute_gradient=True, backend=backend, **params)
        assert np.all(np.isnan(dt[~ok])) and np.all(np.isnan(gt[~ok]))
        assert np.array_equal(np.isnan(dt), np.isnan(dk))
        fin = ok & np.isfinite(dk)
        scale = max(1.0, float(np.max(np.abs(dk[fin])))) if fin.any() else 1.0
        np.testing.assert_allclose(dt[fin], dk[fin], rtol=1e-12, atol=1e-12 * scale)
        np.testing.assert_allclose(gt[ok], gk[ok], rtol=1e-9, atol=1e-9)
        vt = f(*p.T, backend=backend, **params)
        assert_same_bits(vt, dt)  # the value does not depend on the gradient's mode
        if backend == backends[0]:
            out = dt, gt
    return out


def _every_primitive():
    with sdf.transform(angle=0.4, offset=[0.3, -0.2]):
        shapes = [
            sdf.Circle([0.1, 0.2], 0.5),
            sdf.Halfspace([0.3, 1], -1.5),
            sdf.Box([-0.4, -0.2], [0.3, 0.5]),
            sdf.Segment([0, 0], [1, 0.5]),
            sdf.Capsule([0, 0], [1, 0.3], 0.2),
            sdf.RoundedBox([-1, -0.5], [0.5, 0.2], 0.1),
            sdf.OrientedBox([-1, 0], [1, 0.4], 0.3),
            sdf.Triangle(),
            sdf.RegularPolygon([0.2, 0], 0.8, 7),
            sdf.EquilateralTriangle([0, 0.1], 0.6),
            sdf.Polygon([[0, 0], [1, 0], [1, 1], [0.5, 0.3], [0, 1]]),
            sdf.Star([0.1, 0], 1.0, 5),
            sdf.Ellipse([0.1, 0.2], [0.9, 0.3]),
            sdf.Ring([0.3, 0], 0.5, 0.1),
            sdf.Arc(),
        ]
    return shapes


def test_every_primitive_kind_against_the_kernel():
    """All kinds in one scene (one kernel to compile): hard and smooth unions, modifiers."""
    shapes = _every_primitive()
    f = shapes[0]
    for j, s in enumerate(shapes[1:]):
        with sdf.smoothness([0, 8][j % 2]):
            f = f | s.round(0.03) if j % 3 else f - s.shell(0.05)
    assert_agree(f, _points(3000, 99))


@pytest.mark.parametrize(
    "scene",
    [seed_world, lambda: box_world(20), _long_straight_line_scene, lambda: _unstructured_scene(3)],
)
def test_worlds(scene):
    """Folded loops over tables (box worlds), long straight-line scenes, block kernels with
    folded primitives: several blocks and a ragged last one."""
    f = scene()
    for n in (1, BLOCK + 3, 5000):
        assert_agree(f, _points(n, n))


@settings(
    max_examples=6,
    deadline=None,
    derandomize=True,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
)
@given(
    prims=st.lists(placed, min_size=1, max_size=30),
    ops=st.lists(operation, min_size=0, max_size=30),
)
def test_random_scenes(prims, ops):
    """Random circles, half-spaces and boxes, transformed, combined by hard and exponential
    unions, intersections and differences (the scene builder of test_codegen)."""
    f = build_scene(prims, ops)
    assert_agree(f, _points(400, len(prims)))


def _circles(n, seed=3):
    rng = np.random.default_rng(seed)
    f = sdf.Circle(rng.uniform(-2, 2, 2), 0.1)
    for _ in range(n - 1):
        f = f | sdf.Circle(rng.uniform(-2, 2, 2), rng.uniform(0.05, 0.2))
    return f


@pytest.mark.parametrize(
    "scene",
    [seed_world, lambda: box_world(20), lambda: _circles(200)],
    ids=["seed world", "20-box world", "200 circles"],
)
def test_bench_scenes(scene):
    """The bench scenes (a hard union of 200 primitives is a combine program in the kernel) on
    points spread over the scene, several blocks."""
    f = scene()
    p = _points(3 * BLOCK + 17, 23)
    assert_agree(f, p)


def _blend(a, b, op, kind, k):
    if op == "|":
        return a.union(b, k=k, kind=kind)
    if op == "&":
        return a.intersection(b, k=k, kind=kind)
    return a.difference(b, k=k, kind=kind)


@settings(
    max_examples=3,
    deadline=None,
    derandomize=True,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
)
@given(
    prims=st.lists(placed, min_size=2, max_size=16),
    ops=st.lists(
        st.tuples(
            st.sampled_from(["|", "&", "-"]),
            st.sampled_from(["exponential", "quadratic", "cubic"]),
            st.floats(0.02, 0.5),
            st.integers(0, 10**6),
        ),
        max_size=16,
    ),
    chain=st.sampled_from(["quadratic", "cubic", "exponential"]),
)
def test_random_blend_scenes(prims, ops, chain):
    """Random scenes of every blend kind (exponential, quadratic, cubic) between random pairs,
    the rest joined by one left fold of blends (folded into loops where four neighbours share
    a shape)."""
    shapes = [build_scene([pr], []) for pr in prims]
    for op, kind, k, pick in ops:
        if len(shapes) == 2:
            break
        a = shapes.pop(pick % len(shapes))
        b = shapes.pop(pick // 7 % len(shapes))
        shapes.append(_blend(a, b, op, kind, k))
    f = shapes[0]
    for s in shapes[1:]:
        f = f.union(s, k=0.1, kind=chain)
    assert_agree(f, _points(300, len(prims)))


def test_loop_members_with_nested_chains_and_zero_gradient_components():
    """Corners of the generated code's form: loop members whose nested chains the loop
    evaluates pairwise (the straight-line code would flatten them), a left fold of blends that
    opens with a loop, and chains whose gradient components are known zero (the kernel carries
    them: at x = 0, 1/x makes them NaN where the reference drops the term, so the gradient of
    that scene is compared away from x = 0)."""
    rng = np.random.default_rng(4)
    members = []
    for _ in range(6):
        with (
            sdf.transform(angle=rng.uniform(-3, 3), offset=rng.uniform(-2, 2, 2)),
            sdf.smoothness(6.0),
        ):
            members.append(
                sdf.Circle([0, 0], 0.2)
                | sdf.Box([-0.2, -0.1], [0.1, 0.2])
                | sdf.Circle([0.2, 0], 0.1)
            )
    hard = members[0]
    for m in members[1:]:
        hard = hard | m
    fold = members[0]
    for m in members[1:]:
        fold = fold.union(m, k=0.2, kind="cubic")
    flat = sdf.Function(sdf.graph.sym_min(Y - 1.0, -Y - 1.0) / X + X * Y, [X, Y])
    p = _points(600, 5)
    p[:40, 0] = np.repeat([0.0, -0.0, 5e-324, -5e-324], 10)
    for f in (hard, fold, hard.union(fold, k=0.3, kind="quadratic")):
        assert_agree(f, p)
    assert_agree(flat, p[40:])
    d, g = flat(*p[:40].T, compute_gradient=True)
    np.testing.assert_array_equal(d, flat(*p[:40].T, backend="numpy"))


@settings(max_examples=3, deadline=None, derandomize=True)
@given(
    n=st.integers(8, 30),
    kind=st.sampled_from(["exponential", "quadratic", "cubic", "hard"]),
    union=st.booleans(),
    seed=st.integers(0, 1000),
)
def test_chains_and_polynomial_blends(n, kind, union, seed):
    """Long chains (folded into loops in the kernel), polynomial blends between random
    primitive kinds."""
    rng = np.random.default_rng(seed)
    f = sdf.Halfspace([0, 1], -1.8) if union else sdf.Circle([0, 0], 2.4)
    for _ in range(n):
        with sdf.transform(angle=rng.uniform(-3, 3), offset=rng.uniform(-2, 2, 2)):
            shape = (
                sdf.Box(-rng.uniform(0.05, 0.3, 2), rng.uniform(0.05, 0.3, 2))
                if rng.random() < 0.5
                else sdf.Circle(rng.uniform(-0.2, 0.2, 2), rng.uniform(0.05, 0.3))
            )
        if kind == "hard":
            f = f | shape if union else f & sdf.Circle([0, 0], 2.5) - shape
        elif kind == "exponential":
            with sdf.smoothness(float(rng.uniform(2, 30))):
                f = f | shape if union else f - shape
        else:
            f = (
                f.union(shape, k=0.1, kind=kind)
                if union
                else f.intersection(shape.rotate(0.2), k=0.05, kind=kind)
            )
    assert_agree(f, _points(600, seed))


def test_elementary_operations_against_numpy():
    """Operations the shapes rarely produce (pow, exp, log, sin, floor, select, division), by
    the NumPy reference of the op table."""
    e = (
        sdf.sym_exp(-X * X) * sdf.sym_sin(3 * Y)
        + sdf.sym_log(1.5 + sdf.sym_cos(X * Y))
        + (X * X + 2.0) ** (0.5 + 0.1 * Y) / (3.0 + sdf.sym_abs(Y))
        + X**3
        + 1.0 / (2.0 + X * X)
        + cg.sym_floor(X) * 0.1
        + cg.sym_select(X - Y, X * Y, sdf.sym_sqrt(X * X + 1.0))
    )
    f = sdf.Function(e, [X, Y])
    p = _points(900, 1)
    d, g = assert_agree(f, p)
    ok = np.isfinite(p).all(axis=1)
    ref, (gx, gy) = evaluate_numpy(e, {"x": p[ok, 0], "y": p[ok, 1]}, compute_gradient=True)
    np.testing.assert_allclose(d[ok], ref, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(g[ok], np.stack([gx, gy], -1), rtol=1e-9, atol=1e-9)


def test_runtime_parameters_are_inputs():
    """Parameters and time are read per call: no rebuild, no recompile."""
    a, px, r, k = Param("angle", 0.3), Param("px", 0.5), Param("r", 0.3), Param("k", 0.2)
    with sdf.transform(angle=a, offset=[0.1, 0.2]):
        bar = sdf.Box(minc=[-1, -0.1], maxc=[1, 0.1])
    ball = sdf.Circle(center=[px, 0.4], radius=r).translate([0.0, 0.5 * sdf.t])
    f = (
        bar.union(ball, k=k, kind="quadratic").round(0.05)
        | sdf.Halfspace(normal=[0, 1], d=-1.5).union(bar.rotate(a), k=10 * k)
        | sdf.Ellipse([0, 0], [r + 0.5, 0.2])
    )
    p = _points(500, 7)
    assert_agree(f, p)
    module = f.compiled.blocks
    for vals in (dict(angle=-0.4, px=0.1, r=0.5, k=0.05, t=0.3), dict(angle=1.2, t=-1.0)):
        assert_agree(f, p, **vals)
    assert f.compiled.blocks is module and len(module._block_vg.signatures) == 1
    d, g, dt = f(*p[:50].T, time_derivative=True)
    assert np.isfinite(dt[np.isfinite(p[:50]).all(axis=1)]).all()


@pytest.mark.default_backend
def test_backend_switch_and_errors():
    f = sdf.Circle([0.2, 0], 0.7) | sdf.Box([-1, -1], [-0.5, 0.3])
    p = _points(300, 3)
    with pytest.raises(ValueError, match="backend must be one of .*got backend='jit'"):
        f(*p.T, backend="jit")
    # the interpreter of earlier versions is gone: the error names what answers instead
    with pytest.raises(ValueError, match="'kernel', 'numpy'.*'tape' was removed"):
        f(*p.T, backend="tape")
    with pytest.raises(ValueError, match="no time derivative"):
        f(*p.T, time_derivative=True, backend="numpy")
    assert sdf.Function.backend == "auto"


@pytest.mark.default_backend
def test_default_call_answers_with_the_kernel_and_compiles_the_other_kind_meanwhile():
    """The default call on a new scene answers with the kernel and starts compiling the
    scene's other kinds of kernel in a background thread; calls of every kind return the
    kernel's bits before and after (with parameters, non-finite points too)."""
    rng = np.random.default_rng(12)
    a = Param("a", 0.3)
    f = sdf.Halfspace([0, 1], -1.8)
    for _ in range(3):
        with (
            sdf.transform(angle=rng.uniform(-3, 3), offset=rng.uniform(-2, 2, 2)),
            sdf.smoothness(float(rng.uniform(1, 9))),
        ):
            f = f | sdf.Capsule([0, 0], rng.uniform(0.1, 0.4, 2), rng.uniform(0.05, 0.2))
    f = f.union(sdf.Circle([a, 0.2], 0.3), k=0.2, kind="quadratic")
    p = _points(3000, 4)
    d0, g0 = f(*p.T, compute_gradient=True, a=0.7)
    c = f.compiled
    assert c._warm is not None
    assert c._warm.wait(300) and c.warm_error is None and c.kernel_ready
    assert c.blocks._block_v.signatures  # the value-only kernel compiled meanwhile
    d1, g1 = f(*p.T, compute_gradient=True, a=0.7, backend="kernel")
    assert_same_bits(d1, d0)
    assert_same_bits(g1, g0)
    assert_same_bits(f(*p.T, a=0.7), d0)
    assert math.isnan(d1[0]) and math.isnan(d0[0])


_FIRST_CONTACT = r"""
import json, numpy as np
import fastsdf as sdf
from fastsdf import function

function.COMPILE_NOTICE_AFTER_S = 0.0  # the notice whatever the machine's speed
out = {}
f = sdf.Circle([0.1, 0.2], 0.7) | sdf.Box([0.2, -0.5], [0.8, -0.1])
x, y = np.random.default_rng(0).uniform(-2, 2, (2, 500))
d, g = f(x, y, compute_gradient=True)
assert f.compiled._warm.wait(300) and f.compiled.warm_error is None
dk, gk = f(x, y, compute_gradient=True, backend="kernel")
out["kernel_bits"] = d.tobytes() == dk.tobytes() and g.tobytes() == gk.tobytes()
circle = np.hypot(x - 0.1, y - 0.2) - 0.7
qx, qy = np.abs(x - 0.5) - 0.3, np.abs(y + 0.3) - 0.2
box = np.hypot(np.maximum(qx, 0), np.maximum(qy, 0)) + np.minimum(np.maximum(qx, qy), 0)
out["err"] = float(np.max(np.abs(d - np.minimum(circle, box))))
print(json.dumps(out))
"""


def test_first_call_on_a_fresh_installation_compiles_the_kernel_and_says_so(tmp_path):
    """A fresh installation (empty kernel cache, empty numba cache): the default call of a new
    scene compiles its kernel, which answers with its own bits, and the wait is said once on
    stderr."""
    env = dict(
        os.environ,
        FASTSDF_CACHE_DIR=str(tmp_path / "kernels"),
        NUMBA_CACHE_DIR=str(tmp_path / "numba"),
    )
    env.pop("FASTSDF_QUIET", None)
    res = subprocess.run(
        [sys.executable, "-c", _FIRST_CONTACT],
        env=env,
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert res.returncode == 0, res.stderr
    out = json.loads(res.stdout.strip().splitlines()[-1])
    assert out.pop("err") < 1e-12
    assert out == {"kernel_bits": True}
    assert res.stderr.count("fastsdf: compiling the kernel of a new scene") == 1, res.stderr
