"""The tape interpreter (fastsdf.backends.vm) against the compiled kernels: the tape computes the
kernel's bits (value and gradient, bit for bit) on the bench scenes, random scenes, every
primitive kind, smooth and polynomial blends, transforms, parameters and non-finite points; the
NumPy path agrees to rounding (values 1e-12 relative, gradients 1e-9); and the ``backend``
switch of Function (``'auto'`` answers through the tape, then the kernel)."""

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
from fastsdf.backends.vm import BLOCK, compile_tape, warm
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


def assert_agree(f, p, backends=("tape", "numpy"), **params):
    """The tape gives the kernel's bits, the NumPy path agrees with it to rounding, value (also
    value-only calls) and gradient; non-finite points give NaN for those points only."""
    dk, gk = f(*p.T, compute_gradient=True, **params)
    ok = np.isfinite(p).all(axis=1)
    for backend in backends:
        dt, gt = f(*p.T, compute_gradient=True, backend=backend, **params)
        assert np.all(np.isnan(dt[~ok])) and np.all(np.isnan(gt[~ok]))
        assert np.array_equal(np.isnan(dt), np.isnan(dk))
        if backend == "tape":
            assert_same_bits(dt, dk)
            assert_same_bits(gt, gk)
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


def assert_matches_reference(f, p):
    """Tape against the NumPy reference of the op table (no kernel compiled)."""
    ok = np.isfinite(p).all(axis=1)
    d, g = f(*p.T, compute_gradient=True, backend="tape")
    assert np.all(np.isnan(d[~ok])) and np.all(np.isnan(g[~ok]))
    ref, (gx, gy) = evaluate_numpy(f.f, {"x": p[ok, 0], "y": p[ok, 1]}, compute_gradient=True)
    np.testing.assert_allclose(d[ok], ref, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(g[ok], np.stack([gx, gy], -1), rtol=1e-9, atol=1e-9)


@pytest.mark.parametrize("i", range(15))
def test_every_primitive_kind(i):
    """Each primitive kind alone and with modifiers and blends, against the NumPy reference."""
    s = _every_primitive()[i]
    p = _points(700, i)
    assert_matches_reference(s, p)
    with sdf.smoothness(6):
        assert_matches_reference(
            (s.round(0.05) | sdf.Circle([1, 1], 0.3)) - s.shell(0.02).rotate(0.3), p
        )


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
def test_bench_scenes_give_the_kernels_bits(scene):
    """The bench scenes (a hard union of 200 primitives is a combine program in the kernel) on
    points spread over the scene, several blocks: the tape's bits are the kernel's."""
    f = scene()
    p = _points(3 * BLOCK + 17, 23)
    assert_agree(f, p, backends=("tape",))


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
def test_random_blend_scenes_give_the_kernels_bits(prims, ops, chain):
    """Random scenes of every blend kind (exponential, quadratic, cubic) between random pairs,
    the rest joined by one left fold of blends (folded into loops where four neighbours share
    a shape): the tape's bits are the kernel's."""
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
    assert_agree(f, _points(300, len(prims)), backends=("tape",))


def test_loop_members_with_nested_chains_and_zero_gradient_components():
    """Corners where the generated code's form decides the last bits: loop members whose
    nested chains the loop evaluates pairwise (the straight-line code would flatten them), a
    left fold of blends that opens with a loop, and chains whose gradient components are known
    zero (the kernel still carries them: at x = 0, 1/x makes them NaN, not dropped terms)."""
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
    for f in (hard, fold, flat, hard.union(fold, k=0.3, kind="quadratic")):
        assert_agree(f, p, backends=("tape",))


@settings(max_examples=3, deadline=None, derandomize=True)
@given(
    n=st.integers(8, 30),
    kind=st.sampled_from(["exponential", "quadratic", "cubic", "hard"]),
    union=st.booleans(),
    seed=st.integers(0, 1000),
)
def test_chains_and_polynomial_blends(n, kind, union, seed):
    """Long chains (folded into loops in the kernel: the tape follows its operand order and
    start), polynomial blends between random primitive kinds."""
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
    """Parameters and time are read per call: no rebuild, the kernel's answers."""
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
    tape = f.compiled.tape
    for vals in (dict(angle=-0.4, px=0.1, r=0.5, k=0.05, t=0.3), dict(angle=1.2, t=-1.0)):
        assert_agree(f, p, **vals)
    assert f.compiled.tape is tape
    # time derivative: the kernel answers (the tape has none)
    d, g, dt = f(*p[:50].T, time_derivative=True, backend="tape")
    assert np.isfinite(dt[np.isfinite(p[:50]).all(axis=1)]).all()


def test_instructions_are_deduplicated_and_registers_reused():
    """A shared subexpression is one instruction; the register file follows the scene's width
    (a union of 200 circles needs a handful of registers, not one per node)."""
    c = sdf.sym_length(X, Y)
    tape = compile_tape(c - 1.0 + sdf.sym_exp(c), ["x", "y"])
    assert sum(1 for row in tape.code if row[0] == 18) == 1  # one length
    f = sdf.Circle([0, 0], 0.1)
    rng = np.random.default_rng(0)
    for _ in range(200):
        f = f | sdf.Circle(rng.uniform(-2, 2, 2), rng.uniform(0.05, 0.2))
    tape = f.compiled.tape
    assert len(tape) > 1000 and tape.nreg < 16
    assert_agree(f, _points(300, 2))


@pytest.mark.default_backend
def test_backend_switch_and_errors(monkeypatch):
    from fastsdf import function

    warm()  # the default call answers through the interpreter once it is compiled

    f = sdf.Circle([0.2, 0], 0.7) | sdf.Box([-1, -1], [-0.5, 0.3])
    p = _points(300, 3)
    with pytest.raises(ValueError, match="backend"):
        f(*p.T, backend="jit")
    with pytest.raises(ValueError, match="got symbol .z."):
        compile_tape(X + Symbol("z"), ["x", "y"])
    assert sdf.Function.backend == "auto"  # the shipped default: the tape, then the kernel
    f(*p.T, backend="kernel")
    assert f.compiled._tape is None  # the kernel path never builds a tape
    # a call that asks for pruning goes to the kernel: pruned blends are its own approximation
    g = sdf.Circle([0.1, 0], 0.5) | sdf.Circle([0.5, 0.2], 0.3)
    g(*p.T, prune=True)
    assert g.compiled._tape is None
    # a call the tape would take longer for than the kernel's first answer waits for the kernel
    h = sdf.Circle([0, 0], 0.5) | sdf.Box([0.1, 0.1], [0.6, 0.4])
    monkeypatch.setattr(function, "AUTO_TAPE_MAX_S", 1e-6)
    assert h._path_for("auto", p[:, 0]) is None and h.compiled._tape is None
    monkeypatch.setattr(function, "AUTO_TAPE_MAX_S", 1.0)
    assert h._path_for("auto", p[:, 0]) == "tape"


@pytest.mark.default_backend
def test_default_call_answers_through_the_tape_then_the_kernel_with_the_same_bits():
    """The default call on a new scene answers through the tape and starts the kernel's
    compilation in a background thread; once it is done, calls run the kernel and return the
    same bits (value-only and value + gradient, with parameters, non-finite points too)."""
    warm()  # the default call answers through the interpreter once it is compiled
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
    assert c._tape is not None and c._warm is not None
    v0 = f(*p.T)
    assert c._warm.wait(300) and c.warm_error is None and c.kernel_ready
    assert f._path_for("auto", p[:, 0]) is None  # the kernel answers from now on
    d1, g1 = f(*p.T, compute_gradient=True, a=0.7)
    assert_same_bits(d1, d0)
    assert_same_bits(g1, g0)
    assert_same_bits(f(*p.T), v0)
    assert math.isnan(d1[0]) and math.isnan(d0[0])


def test_auto_backend_answers_then_switches_to_the_kernel():
    """``backend='auto'`` named on a call, with the kernel as the class default: the first call
    answers through the tape and starts the compilation in a background thread; once it is
    done, calls run the kernel (the same bits)."""
    warm()
    rng = np.random.default_rng(11)
    f = sdf.Halfspace([0, 1], -1.8)
    for _ in range(7):  # a scene of its own (not in the kernel cache of an earlier test)
        with (
            sdf.transform(angle=rng.uniform(-3, 3), offset=rng.uniform(-2, 2, 2)),
            sdf.smoothness(float(rng.uniform(1, 9))),
        ):
            f = f | sdf.Capsule([0, 0], rng.uniform(0.1, 0.4, 2), rng.uniform(0.05, 0.2))
    p = _points(5000, 4)
    d0, g0 = f(*p.T, compute_gradient=True, backend="auto")
    c = f.compiled
    assert c._tape is not None and c._warm is not None
    assert c._warm.wait(300) and c.warm_error is None and c.kernel_ready
    d1, g1 = f(*p.T, compute_gradient=True, backend="auto")
    assert_same_bits(d1, d0)
    assert_same_bits(g1, g0)
    assert_same_bits(f(*p.T, compute_gradient=True)[0], d1)  # the kernel's bits
    assert math.isnan(d1[0]) and math.isnan(d0[0])


_FIRST_CONTACT = r"""
import json, numpy as np
import fastsdf as sdf
from fastsdf import function
from fastsdf.backends import vm

function.COMPILE_NOTICE_AFTER_S = 0.0  # the notice whatever the machine's speed
out = {"ready_before": vm.interpreter_ready()}
f = sdf.Circle([0.1, 0.2], 0.7) | sdf.Box([0.2, -0.5], [0.8, -0.1])
x, y = np.random.default_rng(0).uniform(-2, 2, (2, 500))
d, g = f(x, y, compute_gradient=True)
out["tape_built"] = f.compiled._tape is not None
out["interpreter_compiled"] = bool(vm._eval_par.overloads)
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
    scene does not wait for the interpreter (which takes several times longer to compile than
    the scene's kernel); the kernel answers, with its own bits, and the wait is said once on
    stderr."""
    env = dict(
        os.environ,
        FASTSDF_CACHE_DIR=str(tmp_path / "kernels"),
        NUMBA_CACHE_DIR=str(tmp_path / "numba"),
        FASTSDF_BACKGROUND_COMPILE="0",
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
    assert out == {
        "ready_before": False,
        "tape_built": False,
        "interpreter_compiled": False,
        "kernel_bits": True,
    }
    assert res.stderr.count("fastsdf: compiling the kernel of a new scene") == 1, res.stderr


def test_interpreter_is_compiled_for_later_in_a_process_of_its_own(tmp_path, monkeypatch):
    """Where the interpreter is not compiled yet, one low-priority process per installation
    compiles it into numba's disk cache (a claim file keeps a second process from starting the
    same job); ``FASTSDF_BACKGROUND_COMPILE=0`` turns that off. Once the interpreter is in the
    disk cache a fresh process sees it there without compiling."""
    from fastsdf.backends import vm

    warm()
    code = (
        "import fastsdf.backends.vm as v\nprint(v.interpreter_ready(), len(v._eval_par.overloads))"
    )
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert res.stdout.split() == ["True", "0"], res.stderr  # found on disk, not compiled
    started = []
    monkeypatch.setattr(vm.subprocess, "Popen", lambda cmd, **kw: started.append((cmd, kw)))
    monkeypatch.setattr(vm, "interpreter_ready", lambda: False)
    monkeypatch.setenv("FASTSDF_CACHE_DIR", str(tmp_path))
    monkeypatch.setenv("FASTSDF_BACKGROUND_COMPILE", "0")
    monkeypatch.setattr(vm, "_warm_started", [False])
    assert not vm.warm_in_background() and not started
    monkeypatch.delenv("FASTSDF_BACKGROUND_COMPILE")
    monkeypatch.setattr(vm, "_warm_started", [False])
    assert vm.warm_in_background() and len(started) == 1
    cmd, kw = started[0]
    claim = tmp_path / "interpreter-compiling.claim"
    assert claim.exists() and cmd[-1] == str(claim) and "warm()" in cmd[2]
    assert kw["env"]["FASTSDF_BACKGROUND_COMPILE"] == "0"  # the child starts no child
    assert not vm.warm_in_background()  # once per process
    monkeypatch.setattr(vm, "_warm_started", [False])
    assert not vm.warm_in_background() and len(started) == 1  # claimed by the first
