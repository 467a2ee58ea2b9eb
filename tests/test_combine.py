"""Combine programs: a long scene that is a tree of blends (min, max, smin, smax) over small
subexpressions runs its blends through the installation's interpreter
(``fastsdf.backends.kernel.drive``) instead of straight-line code. The program must give the same
bits as the per-point straight-line functions, value and gradient, for every blend kind, argument
order, tie and non-finite point."""

import numpy as np
import pytest
from conftest import evaluate
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import fastsdf as sdf
from fastsdf.backends.kernel import codegen
from fastsdf.expr.graph import evaluate_numpy
from fastsdf.function import compile_expr
from fastsdf.shapes.scenes import mixed_scene

# One step of a random scene: (primitive kind, operation, smoothness, operand order).
_STEP = st.tuples(
    st.integers(0, 3),
    st.sampled_from(["|", "&", "-", "cut", "q|", "c&", "q-"]),
    st.sampled_from([0.0, 0.0, 5.0, 10.0, 1e-3]),
    st.booleans(),
)


def _scene(steps, seed):
    """A scene without repeated structure next to each other: a chain of blends whose other
    operands are transformed primitives. ``kind`` 3 repeats the previous primitive exactly
    (ties everywhere); equal consecutive smoothness makes n-ary smooth chains; ``swap`` puts
    the new primitive first."""
    rng = np.random.default_rng(seed)
    f = sdf.Halfspace([0, 1], -1.8)
    s = None
    for kind, op, k, swap in steps:
        with sdf.transform(angle=rng.uniform(-3, 3), offset=rng.uniform(-1.5, 1.5, 2)):
            if kind == 0 or s is None:
                s = sdf.Circle([0, 0], rng.uniform(0.1, 0.4))
            elif kind == 1:
                s = sdf.Box(-rng.uniform(0.1, 0.3, 2), rng.uniform(0.1, 0.3, 2))
            elif kind == 2:
                s = sdf.Capsule([0, 0], rng.uniform(0.1, 0.4, 2), rng.uniform(0.05, 0.2))
        with sdf.smoothness(k):
            a, b = (s, f) if swap else (f, s)
            if op in ("q|", "c&", "q-"):  # polynomial blends: width k (or 0.3 where k is 0)
                kind = "quadratic" if op[0] == "q" else "cubic"
                w = k if k >= 1e-2 else 0.3
                f = {"|": a.union, "&": a.intersection, "-": a.difference}[op[1]](b, w, kind)
            elif op == "|":
                f = a | b
            elif op == "&":
                f = a & b
            elif op == "-":
                f = a - b
            else:
                f = a & (sdf.Circle([0, 0], 3.0) - b)
    return f


def _points(seed, n=1100):
    p = np.random.default_rng(seed).uniform(-2.5, 2.5, (n, 2))
    p[::37, 0] = np.nan
    p[5::41, 1] = np.inf
    p[7::53, 0] = -np.inf
    p[9::59] = 0.0  # the origin: ties between centred operands
    return p


def _check(f, p):
    """Block kernels (parallel and serial, value and value+gradient) against the per-point
    straight-line functions, bit for bit."""
    src = f.compiled.module_source
    if f.compiled.groups:  # same-shape operands of one chain: loops, straight-line blocks
        assert "_PROG_V" not in src
    else:
        assert "_PROG_VG = np.array" in src and "_PROG_V = np.array" in src
        assert "def _block_vg(" not in src  # the blends run in the interpreter
    d, g = f(*p.T, compute_gradient=True, prune=False)
    ds, gs = evaluate(f.compiled, p[:200, 0], p[:200, 1], compute_gradient=True, prune=False)
    dv = f(*p.T, prune=False)
    # the reference: the straight-line per-point functions (a module without programs)
    line = compile_expr(f.f, ["x", "y"])
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(codegen, "COMBINE_PROGRAMS", False)
        assert "_PROG_V" not in line.module_source
    pv = line.point_fn("vg")
    ref = np.array([pv(x, y) for x, y in p])
    same = lambda a, b: (
        np.array_equal(a.view(np.int64), b.view(np.int64))
        or (
            np.array_equal(np.isnan(a), np.isnan(b))
            and np.array_equal(a[~np.isnan(a)].view(np.int64), b[~np.isnan(b)].view(np.int64))
        )
    )
    assert same(d, ref[:, 0]) and same(g[:, 0], ref[:, 1]) and same(g[:, 1], ref[:, 2])
    assert same(ds, d[:200]) and same(gs.ravel(), g[:200].ravel())
    p1 = line.point_fn("v")
    assert same(dv, np.array([p1(x, y) for x, y in p]))
    # the one-point functions of the program module (the particle step's exact query)
    own = f.compiled.point_fn("vg")
    mine = np.array([own(x, y) for x, y in p])
    assert all(same(mine[:, j], ref[:, j]) for j in range(3))
    own_v = f.compiled.point_fn("v")
    assert same(np.array([own_v(x, y) for x, y in p[:300]]), dv[:300])
    bad = ~np.isfinite(p).all(axis=1)
    assert np.isnan(d[bad]).all() and np.isnan(g[bad]).all() and np.isfinite(d[~bad]).all()
    ok = ~bad
    np.testing.assert_allclose(
        d[ok], evaluate_numpy(f.f, {"x": p[ok, 0], "y": p[ok, 1]}), rtol=1e-12, atol=1e-12
    )


@settings(max_examples=4, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.lists(_STEP, min_size=3, max_size=7), st.integers(0, 2**16))
def test_combine_program_matches_the_straight_line_code(steps, seed):
    with pytest.MonkeyPatch.context() as mp:  # short scenes take the long-scene path
        mp.setattr(codegen, "FOLD_MIN_LINES", 10)
        _check(_scene(steps, seed), _points(seed))


def test_combine_program_every_blend_kind_and_order(monkeypatch):
    """Every step kind of the interpreter: hard min and max, a smooth pair (fused step), an
    n-ary smooth chain (same k three times: init in place, steps, finish), negation, the
    polynomial blends (a left fold of two quadratic ones, a cubic intersection), both operand
    orders, an operand equal to the accumulator (ties), and a shared subexpression used by two
    blends."""
    monkeypatch.setattr(codegen, "FOLD_MIN_LINES", 10)
    steps = [
        (0, "|", 0.0, False),
        (1, "&", 0.0, True),
        (3, "|", 5.0, False),
        (2, "-", 5.0, True),
        (0, "|", 4.0, False),
        (1, "|", 4.0, False),
        (2, "|", 4.0, False),
        (3, "cut", 10.0, True),
        (1, "&", 7.0, False),
        (0, "|", 0.0, True),
        (1, "q|", 0.3, False),
        (2, "q|", 0.3, False),
        (3, "c&", 0.2, True),
        (0, "q-", 0.25, False),
    ]
    f = _scene(steps, 7)
    shared = f | sdf.Circle([0.3, 0.1], 0.5)
    g = (shared - sdf.Box([-0.1, -0.1], [0.2, 0.2])).union(shared & sdf.Circle([0, 0], 1.5), 3.0)
    for h in (f, g):
        prog = h.compiled.module._PROG_VG
        ops = set(prog[:, 0].astype(int))
        _check(h, _points(3))
    assert {0, 1, 2, 3, 5, 7, 8, 9, 10, 11, 12} <= ops | set(
        f.compiled.module._PROG_VG[:, 0].astype(int)
    )


def test_mixed_scene_uses_the_program_without_monkeypatching():
    """A 30-primitive scene without repeated structure is long enough for the program on its
    own; the other long scenes keep the straight-line block kernels."""
    f = mixed_scene(30, seed=5)
    assert "_combine_point_vg(F, _PROG_VG)" in f.source()  # the one-point function too
    p = _points(11, 700)
    _check(f, p)
