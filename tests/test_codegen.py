"""The code generator: lazy compilation, loop folding of same-shape operands, the disk cache
across processes, and property tests of compiled code against the NumPy reference on random
scenes."""

import os
import subprocess
import sys
import textwrap
import time

import numpy as np
import pytest
from conftest import central_gradient, evaluate, value_of
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import fastsdf as sdf
from fastsdf.expr.graph import evaluate_numpy
from fastsdf.shapes.scenes import box_world, seed_world

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def test_source_is_inspectable_python():
    f = seed_world()
    src = f.source()
    assert src.lstrip().startswith("@njit") and "def point_vg(x, y):" in src
    assert "_vexp(" in src and "_vlog(" in src and "math.exp" not in src
    assert "def point_v(x, y):" in f.source(gradient=False)
    compile(f.compiled.module_source, "<generated>", "exec")


def test_value_only_call_compiles_no_gradient_code():
    # A scene no earlier run has cached: a kernel loaded from disk registers no callee
    # signatures, and this test inspects what gets compiled.
    unique = 0.3 + (os.getpid() * 7919 + time.time_ns()) % 10**9 * 1e-12
    with sdf.transform(angle=0.123, offset=[0.2, 0.1]):
        f = sdf.Circle([0.31, 0.2], unique) | sdf.Box([-0.1, -0.2], [0.3, 0.4])
    f(np.zeros(10), np.zeros(10), backend="kernel")  # the default would compile both kinds
    blocks = f.compiled.blocks
    assert blocks._block_v.signatures and not blocks._block_vg.signatures
    assert not f.compiled.module.point_vg.signatures  # block kernels only  # block kernels only


def _overloads(module) -> int:
    functions = [getattr(module, n) for n in dir(module)]
    return sum(len(fn.overloads) for fn in functions if hasattr(fn, "overloads"))


@pytest.mark.parametrize("n", [3, 20])
def test_scenes_of_one_structure_share_their_block_kernels(n):
    """The block kernels read a scene's numbers (constants, tables, blend sharpness) from each
    call's data: box worlds of one size share one block module, the second compiles nothing,
    and each gives its own values (against the NumPy reference)."""
    f, g = box_world(n, seed=3), box_world(n, seed=4)
    assert f.compiled.blocks is g.compiled.blocks and f.compiled.module is not g.compiled.module
    x, y = np.random.default_rng(5).uniform(-2, 2, (2, 3000))
    answers = [evaluate(f.compiled, x, y, True)]
    compiled = _overloads(f.compiled.blocks)
    answers.append(evaluate(g.compiled, x, y, True))
    assert _overloads(g.compiled.blocks) == compiled
    for h, (d, grad) in zip((f, g), answers):
        ref, ref_grad = h(x, y, compute_gradient=True, backend="numpy")
        np.testing.assert_allclose(d, ref, rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(grad, ref_grad, rtol=1e-9, atol=1e-9)
    assert not np.allclose(answers[0][0], answers[1][0])


def test_same_shape_operands_become_one_loop():
    """Generated code grows with distinct shapes, not with the number of primitives."""
    src20, src60 = box_world(20).source(), box_world(60).source()
    assert "for i" in src20
    assert len(src20.splitlines()) == len(src60.splitlines())
    f = box_world(60)
    p = np.random.default_rng(0).uniform(-2, 2, (5000, 2))
    np.testing.assert_allclose(
        f(*p.T), evaluate_numpy(f.f, {"x": p[:, 0], "y": p[:, 1]}), rtol=1e-12, atol=1e-12
    )


def _long_straight_line_scene():
    """Alternating kinds and operations: nothing folds into loops, the body is long."""
    rng = np.random.default_rng(5)
    f = sdf.Halfspace([0, 1], -1.8)
    for i in range(9):
        with (
            sdf.transform(angle=rng.uniform(-3, 3), offset=rng.uniform(-2, 2, 2)),
            sdf.smoothness([0, 5, 10][i % 3]),
        ):
            s = sdf.Circle([0, 0], 0.2) if i % 2 else sdf.Box([-0.2, -0.1], [0.1, 0.2])
            f = [f | s, f & (sdf.Circle([0, 0], 3.0) - s), f | s][i % 3]
    return f


def _unstructured_scene(seed, n=24):
    """A random scene without repeated structure next to each other: random kinds (box,
    circle, capsule, triangle), operations (union, intersection, difference) and smoothness,
    long enough that the block kernels evaluate same-shape primitives in loops."""
    rng = np.random.default_rng(seed)
    f = sdf.Halfspace([0, 1], -1.8)
    for _ in range(n):
        with (
            sdf.transform(angle=rng.uniform(-3, 3), offset=rng.uniform(-2, 2, 2)),
            sdf.smoothness(float(rng.choice([0, 4, 8]))),
        ):
            kind = rng.integers(4)
            s = [
                lambda: sdf.Box(-rng.uniform(0.1, 0.3, 2), rng.uniform(0.1, 0.3, 2)),
                lambda: sdf.Circle(rng.uniform(-0.1, 0.1, 2), rng.uniform(0.1, 0.3)),
                lambda: sdf.Capsule([0, 0], rng.uniform(0.1, 0.4, 2), rng.uniform(0.05, 0.2)),
                lambda: sdf.Triangle(
                    [-0.2, -0.1], [0.2, -0.1], rng.uniform(-0.1, 0.1, 2) + [0, 0.2]
                ),
            ][kind]()
            op = rng.integers(3)
            f = f | s if op == 0 else f & (sdf.Circle([0, 0], 3.0) - s) if op == 1 else f - s
    return f


@pytest.mark.slow
@pytest.mark.parametrize("seed, cap", [(3, None), (11, 40)])
def test_folded_block_kernels_match_the_straight_line_code(seed, cap, monkeypatch):
    """Scenes without repeated structure: the block kernels evaluate the primitives that share
    a shape in loops first (``_fold_vg``), the per-point functions keep the straight-line code.
    Both give the same bits, value and gradient, serial and parallel; and they agree with the
    NumPy reference and with central differences. ``cap``: a small budget of stored values per
    point, so that only some groups are folded."""
    from fastsdf.backends import lower
    from fastsdf.backends.kernel import codegen

    monkeypatch.setattr(codegen, "COMBINE_PROGRAMS", False)  # see test_combine.py for those
    if cap is not None:
        monkeypatch.setattr(lower, "MAX_FOLD_ROWS", cap)
    f = _unstructured_scene(seed)
    src = f.compiled.module_source
    assert "def _fold_vg(" in src and "def _fold_v(" in src
    assert "_F0[" not in f.source() and len(f.source().splitlines()) > 400
    p = np.random.default_rng(seed).uniform(-2.5, 2.5, (4500, 2))
    p[::97, 0] = np.nan
    d, g = f(*p.T, compute_gradient=True)  # parallel
    ds, gs = f(*p[:300].T, compute_gradient=True)  # serial
    np.testing.assert_array_equal(ds, d[:300])
    np.testing.assert_array_equal(gs, g[:300])
    np.testing.assert_array_equal(f(*p.T), d)
    point = f.point_fn
    ref = np.array([point(x, y) for x, y in p[:600]])
    np.testing.assert_array_equal(d[:600], ref[:, 0])
    np.testing.assert_array_equal(g[:600], ref[:, 1:])
    ok = np.isfinite(p[:, 0])
    assert np.all(np.isnan(d[~ok])) and np.all(np.isnan(g[~ok]))
    np.testing.assert_allclose(
        d[ok], evaluate_numpy(f.f, {"x": p[ok, 0], "y": p[ok, 1]}), rtol=1e-12, atol=1e-12
    )
    q = p[ok][:400]
    fd = central_gradient(value_of(f), q[:, 0], q[:, 1])
    close = np.all(np.abs(fd - g[ok][:400]) < 1e-4, axis=1)
    assert close.mean() > 0.95  # kinks (medial axes, blend seams) excepted


@pytest.mark.parametrize("scene", [seed_world, lambda: box_world(6), _long_straight_line_scene])
def test_parallel_and_serial_kernels_agree(scene):
    """The parallel block kernels (every tail length, NaN points) against the serial ones."""
    f = scene()
    for n in (4096, 4097, 4098, 4099, 9999):
        p = np.random.default_rng(n).uniform(-2, 2, (n, 2))
        p[np.random.default_rng(n + 1).random(n) < 0.01, n % 2] = np.nan
        d, g = f(*p.T, compute_gradient=True)
        ds, gs = evaluate(f.compiled, p[-9:, 0], p[-9:, 1], compute_gradient=True)  # serial
        np.testing.assert_array_equal(d[-9:], ds)
        np.testing.assert_array_equal(g[-9:], gs)
        np.testing.assert_array_equal(f(*p.T), d)
        bad = np.isnan(p).any(axis=1)
        assert np.all(np.isnan(d[bad])) and np.all(np.isnan(g[bad])) and np.isfinite(d[~bad]).all()
        ref = evaluate_numpy(f.f, {"x": p[~bad, 0], "y": p[~bad, 1]})
        np.testing.assert_allclose(d[~bad], ref, rtol=1e-12, atol=1e-12)


def test_point_fn_is_callable_from_user_njit_code():
    import numba

    f = seed_world()
    point = f.point_fn

    @numba.njit
    def march(x, y, steps):  # sphere tracing downwards from (x, y)
        for _ in range(steps):
            d, gx, gy = point(x, y)
            y -= d
        return y

    y_hit = march(1.0, 1.9, 100)
    d = f(np.array([1.0]), np.array([y_hit]))[0]
    assert abs(d) < 1e-9


# ---------------------------------------------------------------------------------------------
# The disk cache.


def _run(code, cache_dir):
    env = dict(os.environ, FASTSDF_CACHE_DIR=str(cache_dir), PYTHONPATH=REPO)
    res = subprocess.run(
        [sys.executable, "-c", textwrap.dedent(code)],
        capture_output=True,
        text=True,
        env=env,
        timeout=600,
    )
    assert res.returncode == 0, res.stderr
    return res.stdout.strip().splitlines()[-1]


_CACHE_PROBE = """
import numpy as np
from fastsdf.shapes.scenes import box_world
f = box_world({n})
p = np.random.default_rng(0).uniform(-2, 2, (20000, 2))
d, g = f(p[:, 0], p[:, 1], compute_gradient=True, backend="kernel")
k = f.compiled.blocks._block_vg  # the scene's compiled code (the batch kernels are shared)
print(k.stats.cache_hits.__len__() if hasattr(k.stats.cache_hits, '__len__') else 0,
      sum(k.stats.cache_hits.values()), sum(k.stats.cache_misses.values()), repr(float(d.sum())))
"""


@pytest.mark.slow
def test_second_process_reuses_the_disk_cache(tmp_path):
    first = _run(_CACHE_PROBE.format(n=5), tmp_path).split()
    second = _run(_CACHE_PROBE.format(n=5), tmp_path).split()
    assert int(first[1]) == 0 and int(first[2]) >= 1  # compiled
    assert int(second[1]) >= 1 and int(second[2]) == 0  # loaded, nothing compiled
    assert first[3] == second[3]
    assert len([p for p in os.listdir(tmp_path) if p.endswith(".py")]) == 1


@pytest.mark.slow
def test_changed_scene_never_reuses_a_stale_kernel(tmp_path):
    a = _run(_CACHE_PROBE.format(n=5), tmp_path).split()
    b = _run(_CACHE_PROBE.format(n=6), tmp_path).split()
    assert int(b[2]) >= 1  # a new scene compiles
    assert a[3] != b[3]
    f = box_world(6)
    p = np.random.default_rng(0).uniform(-2, 2, (20000, 2))
    assert (
        repr(float(f(p[:, 0], p[:, 1]).sum())) == b[3]
        or abs(float(f(p[:, 0], p[:, 1]).sum()) - float(b[3])) < 1e-9
    )


def test_corrupted_cache_file_is_not_used(tmp_path, monkeypatch):
    from fastsdf.backends.kernel import cache as _cache

    monkeypatch.setenv("FASTSDF_CACHE_DIR", str(tmp_path))
    source = "VALUE = 1\n"
    key = _cache.source_key(source)
    (tmp_path / f"fastsdf_probe_{key}.py").write_text("VALUE = 2\n")  # wrong content
    with pytest.warns(RuntimeWarning, match="cache"):
        mod = _cache.load_module(source, prefix="fastsdf_probe")
    assert mod.VALUE == 1


@pytest.mark.slow
def test_concurrent_processes_share_an_empty_cache(tmp_path):
    env = dict(os.environ, FASTSDF_CACHE_DIR=str(tmp_path), PYTHONPATH=REPO)
    code = textwrap.dedent(_CACHE_PROBE.format(n=4))
    procs = [
        subprocess.Popen(
            [sys.executable, "-c", code],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            env=env,
        )
        for _ in range(3)
    ]
    outs = [p.communicate(timeout=600) for p in procs]
    assert all(p.returncode == 0 for p in procs), [o[1] for o in outs]
    sums = {o[0].split()[3] for o in outs}
    assert len(sums) == 1
    assert len([p for p in os.listdir(tmp_path) if p.endswith(".py")]) == 1
    again = _run(_CACHE_PROBE.format(n=4), tmp_path).split()
    assert again[3] in sums and int(again[2]) == 0


# ---------------------------------------------------------------------------------------------
# Property tests: random scenes against the independent NumPy evaluation of the same graph.

finite = dict(allow_nan=False, allow_infinity=False)
primitive = st.one_of(
    st.tuples(
        st.just("circle"),
        st.floats(-1.5, 1.5, **finite),
        st.floats(-1.5, 1.5, **finite),
        st.floats(0.05, 1.0, **finite),
    ),
    st.tuples(
        st.just("halfspace"),
        st.floats(-1, 1, **finite),
        st.floats(-1, 1, **finite),
        st.floats(-1.5, 1.5, **finite),
    ).filter(lambda t: abs(t[1]) + abs(t[2]) > 0.1),
    st.tuples(
        st.just("box"),
        st.floats(-1.5, 1.0, **finite),
        st.floats(-1.5, 1.0, **finite),
        st.floats(0.05, 1.0, **finite),
        st.floats(0.05, 1.0, **finite),
    ),
)
placed = st.tuples(
    primitive,
    st.one_of(
        st.none(),
        st.tuples(
            st.floats(-3.2, 3.2, **finite), st.floats(-1, 1, **finite), st.floats(-1, 1, **finite)
        ),
    ),
)
operation = st.tuples(
    st.sampled_from(["|", "&", "-"]),
    st.one_of(st.just(0.0), st.floats(0.5, 40.0, **finite)),
    st.integers(0, 10**6),
)


def _make(prim):
    kind = prim[0]
    if kind == "circle":
        return sdf.Circle(center=prim[1:3], radius=prim[3])
    if kind == "halfspace":
        return sdf.Halfspace(normal=prim[1:3], d=prim[3])
    return sdf.Box(minc=prim[1:3], maxc=(prim[1] + prim[3], prim[2] + prim[4]))


def build_scene(prims, ops):
    shapes = []
    for prim, tf in prims:
        if tf is None:
            shapes.append(_make(prim))
        else:
            with sdf.transform(angle=tf[0], offset=tf[1:]):
                shapes.append(_make(prim))
    for op, k, pick in ops:  # combine random pairs until one shape is left
        if len(shapes) == 1:
            break
        i = pick % len(shapes)
        a = shapes.pop(i)
        b = shapes.pop(pick // 7 % len(shapes))
        with sdf.smoothness(k):
            shapes.append(a | b if op == "|" else a & b if op == "&" else a - b)
    f = shapes[0]
    for s in shapes[1:]:
        f |= s
    return f


@settings(
    max_examples=25,
    deadline=None,
    derandomize=True,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
)
@given(
    prims=st.lists(placed, min_size=1, max_size=30),
    ops=st.lists(operation, min_size=0, max_size=30),
)
def test_random_scenes_match_numpy_reference(prims, ops):
    f = build_scene(prims, ops)
    p = np.random.default_rng(len(prims)).uniform(-2.5, 2.5, (300, 2))
    X, Y = p.T
    d, g = f(X, Y, compute_gradient=True)
    ref, (rgx, rgy) = evaluate_numpy(f.f, {"x": X, "y": Y}, compute_gradient=True)
    np.testing.assert_allclose(d, ref, rtol=1e-12, atol=1e-12)
    # Gradient vs central differences where the function is smooth at the scale of the step
    # (two step sizes agree); at kinks a one-sided gradient is returned instead.
    fd1 = central_gradient(value_of(f), X, Y, h=1e-6)
    fd2 = central_gradient(value_of(f), X, Y, h=5e-7)
    smooth = np.all(np.abs(fd1 - fd2) < 1e-6, axis=1)
    assert smooth.mean() > 0.5
    np.testing.assert_allclose(g[smooth], fd1[smooth], rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(g, np.stack([rgx, rgy], -1), rtol=1e-9, atol=1e-9)


@settings(max_examples=8, deadline=None, derandomize=True)
@given(
    n=st.integers(8, 40),
    k=st.one_of(st.just(0.0), st.floats(0.5, 50.0, **finite)),
    union=st.booleans(),
    seed=st.integers(0, 1000),
)
def test_looped_chains_match_numpy_reference(n, k, union, seed):
    """Chains long enough to be folded into loops over tables (and, for k > 0, evaluated as an
    online log-sum-exp): boxes and circles in random order, one operation, one k."""
    rng = np.random.default_rng(seed)
    f = sdf.Halfspace([0, 1], -1.8) if union else sdf.Circle([0, 0], 2.4)
    for _ in range(n):
        with (
            sdf.transform(angle=rng.uniform(-3, 3), offset=rng.uniform(-2, 2, 2)),
            sdf.smoothness(k),
        ):
            shape = (
                sdf.Box(-rng.uniform(0.05, 0.3, 2), rng.uniform(0.05, 0.3, 2))
                if rng.random() < 0.5
                else sdf.Circle(rng.uniform(-0.2, 0.2, 2), rng.uniform(0.05, 0.3))
            )
            f = f | shape if union else f & sdf.Circle([0, 0], 2.5) - shape
    assert "for i" in f.source()  # 8+ operands of two kinds: one kind has at least 4
    p = rng.uniform(-2.5, 2.5, (400, 2))
    d, g = f(*p.T, compute_gradient=True)
    ref, (rgx, rgy) = evaluate_numpy(f.f, {"x": p[:, 0], "y": p[:, 1]}, compute_gradient=True)
    np.testing.assert_allclose(d, ref, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(g, np.stack([rgx, rgy], -1), rtol=1e-9, atol=1e-9)


def test_one_lowering_per_scene_serves_every_evaluator(monkeypatch):
    """The Program of a scene is built once and read by everything that evaluates it: the CPU
    kernel's code (value and gradient), the pruning plan, the NumPy reference and the CUDA
    target's code; no other module plans the scene again."""
    from conftest import HAS_NUMBA_CUDA

    from fastsdf.backends import lower

    built = []
    real = lower.Program.__init__

    def counting(self, *args, **kwargs):
        built.append(self)
        real(self, *args, **kwargs)

    monkeypatch.setattr(lower.Program, "__init__", counting)
    f = box_world(36, seed=5)
    p = np.random.default_rng(0).uniform(-2, 2, (2000, 2))
    d, g = f(p, compute_gradient=True)
    np.testing.assert_array_equal(f(p), d)
    plan = f.compiled.plan(((-2, 2), (-2, 2)))
    assert sum(plan.sizes) == 36  # the Program's loop over the boxes
    dn = f(p, backend="numpy")
    np.testing.assert_allclose(dn, d, rtol=1e-12, atol=1e-12)
    if HAS_NUMBA_CUDA:
        dc = f(p[:64], backend="cuda")
        np.testing.assert_allclose(dc, d[:64], rtol=1e-12, atol=1e-12)
        assert f.compiled.cuda.program is f.compiled.program
    assert built == [f.compiled.program]


def test_no_private_name_is_imported_across_modules_of_the_backends():
    """The backends' modules share their plan through the Program and public names only: no
    module imports another's private name (``_x``), and nothing outside the lowering names
    its planning helpers."""
    import ast
    import pathlib

    root = pathlib.Path(sdf.__file__).parent
    bad = []
    for path in root.rglob("*.py"):
        tree = ast.parse(path.read_text())
        for node in ast.walk(tree):
            if isinstance(node, ast.ImportFrom) and (node.module or "").startswith(
                "fastsdf.backends"
            ):
                bad += [f"{path.name}: {a.name}" for a in node.names if a.name.startswith("_")]
        if path.name != "lower.py":
            text = path.read_text()
            bad += [
                f"{path.name}: {n}"
                for n in ("_Emitter", "_foldable", "_flatten_chain")
                if n in text
            ]
    assert not bad
