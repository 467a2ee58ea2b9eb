"""Block kernels: vectorizable shape, agreement with the C-library kernels and the point
functions."""

import re

import numba
import numpy as np
import pytest
from conftest import evaluate
from test_vmath import PACKED, _has_avx2

from fastsdf.backends.emit import Emitter
from fastsdf.backends.kernel.drive import BLOCK_SIG
from fastsdf.backends.kernel.simd import BLOCK, choose_lanes
from fastsdf.expr.graph import Symbol, evaluate_numpy, sym_exp, sym_log, sym_max
from fastsdf.function import Function, compile_expr
from fastsdf.shapes.scenes import box_world, seed_world


def _points(n, seed, nan_every=0):
    p = np.random.default_rng(seed).uniform(-2, 2, (n, 2))
    if nan_every:
        p[::nan_every, seed % 2] = np.nan
        p[1 :: nan_every * 3, 0] = np.inf
    return p


def _user_exp_log_scene():
    """exp and log as graph operations (not only inside smooth blends)."""
    x, y = Symbol("x"), Symbol("y")
    return Function(
        sym_log(sym_exp(x) + sym_exp(y * 0.5) + 1.0)
        - 1.5
        + sym_max(x * 0.01, sym_exp(-30.0 * (x * x))),
        [x, y],
    )


SCENES = {"seed": seed_world, "box6": lambda: box_world(6), "explog": _user_exp_log_scene}


@pytest.fixture(scope="module", params=list(SCENES))
def pair(request):
    f = SCENES[request.param]()
    expr = f.f
    return compile_expr(expr, ["x", "y"], vmath=True), compile_expr(expr, ["x", "y"], vmath=False)


def test_switch_selects_the_elementary_functions():
    fast, libm = (compile_expr(seed_world().f, ["x", "y"], vmath=v) for v in (True, False))
    assert "_vexp(" in fast.module_source and "math.exp(" not in fast.module_source
    assert "_vlength(" in fast.module_source and "math.hypot" not in fast.module_source
    assert "math.exp(" in libm.module_source and "_vexp(" not in libm.module_source


def test_vectorizable_and_libm_kernels_agree(pair):
    """Same statements, only exp/log differ (each within 1-2 ulp): values to a few ulp of the
    terms summed, gradients to 1e-13 of their length; non-finite points NaN in both."""
    fast, libm = pair
    p = _points(20_000, 1, nan_every=97)
    d1, g1 = evaluate(fast, p[:, 0], p[:, 1], compute_gradient=True)
    d2, g2 = evaluate(libm, p[:, 0], p[:, 1], compute_gradient=True)
    bad = ~np.isfinite(p).all(axis=1)
    assert np.isnan(d1[bad]).all() and np.isnan(g1[bad]).all() and np.isnan(d2[bad]).all()
    ok = ~bad
    assert np.isfinite(d1[ok]).all() and np.isfinite(g1[ok]).all()
    np.testing.assert_allclose(d1[ok], d2[ok], rtol=1e-14, atol=4e-15)
    scale = np.linalg.norm(g2[ok], axis=1)[:, None]
    assert np.max(np.abs(g1[ok] - g2[ok]) / scale) < 1e-13
    np.testing.assert_array_equal(evaluate(fast, p[:, 0], p[:, 1]), d1)  # value-only kernel
    ref = evaluate_numpy(fast.expr, {"x": p[ok, 0], "y": p[ok, 1]})
    np.testing.assert_allclose(d1[ok], ref, rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("n", [1, 3, BLOCK - 1, BLOCK, BLOCK + 1, 3 * BLOCK + 5, 4096 + 7])
def test_every_block_length_matches_the_point_function(n):
    """The block kernels (serial below 4096 points, parallel above) give exactly what the
    per-point function gives, for full and partial blocks (vector body and scalar tail)."""
    comp = box_world(6).compiled
    p = _points(n, n, nan_every=7 if n > 10 else 0)
    d, g = evaluate(comp, p[:, 0], p[:, 1], compute_gradient=True)
    point = comp.point_fn("vg")
    ref = np.array([point(x, y) for x, y in p])
    np.testing.assert_array_equal(d, ref[:, 0])
    np.testing.assert_array_equal(g, ref[:, 1:])


def test_table_loop_becomes_the_outer_loop():
    """A folded loop over a table of operands runs all points of the block against one row,
    then the next: the row's constants are read outside the point loop."""
    src = box_world(20).compiled.function_source("vg")  # per-point: loop over rows inside
    loop = r"for (i\d+)q in range\(_off\[0\], _off\[1\]\):"
    assert re.search(r"^    " + loop + "$", src, re.M)
    block = box_world(20).compiled.module_source
    start = block.index("def _block_vg")
    block = block[start : block.index("def batch_vg_par", start)]
    outer = re.search(r"^    " + loop + r"\n((?:        .*\n)+)", block, re.M)
    assert outer, block
    body = outer.group(2)
    row = outer.group(1)
    assert body.startswith(f"        {row} = _act[{row}q]\n")  # the row list (pruning)
    assert re.search(r"^        h\w+ = _T0\[" + row + r", \d+\]$", body, re.M)
    inner = re.search(r"^        for i in range\((\d+)\):$", body, re.M)
    assert inner and int(inner.group(1)) == BLOCK  # one lane: a constant trip count per block
    assert "_T0[" not in body[inner.start() :]


def test_loop_free_bodies_interleave_two_lanes():
    """Points i and i + BLOCK/2 are computed in one iteration (two independent dependency
    chains), each lane reading and writing its own rows of the scratch array."""
    comp = seed_world().compiled
    src = comp.module_source
    start = src.index("def _block_vg")
    block = src[start : src.index("def batch_vg_par", start)]
    lanes = choose_lanes(Emitter(comp.program, "vg", {}).plain().stmts)
    assert lanes == 2
    assert f"    for i in range({BLOCK // 2}):" in block
    assert f"x_1 = S[{BLOCK // 2} + i]" in block and "x_0 = S[0 + i]" in block
    assert re.search(r"w\d+e_1 = _vexp\(", block)


def _fresh_block(comp, kind="vg"):
    """The block function compiled afresh (numba shows no assembly for cached code)."""
    fn = numba.njit(error_model="numpy", nogil=True)(getattr(comp.blocks, f"_block_{kind}").py_func)
    fn.compile(BLOCK_SIG.args)
    return "\n".join(fn.inspect_asm().values())


@pytest.mark.skipif(
    not _has_avx2(),
    reason="host CPU without AVX2: LLVM's cost model may "
    "keep the block loops scalar on older SIMD, which is not a regression",
)
@pytest.mark.parametrize("scene", ["seed", "box6"])
def test_block_loops_compile_to_packed_vector_code(scene):
    """The per-point statements, exp and log included, become packed float64 arithmetic (any
    vector width: the test does not assume AVX-512)."""
    comp = SCENES[scene]().compiled
    asm = _fresh_block(comp)
    packed = PACKED.findall(asm)
    assert len(packed) >= 100, f"{len(packed)} packed float64 instructions"
    assert "vdivpd" in asm or "divpd" in asm  # the blends' divisions are vectorized too


def test_batch_kernels_are_compiled_once_for_all_scenes():
    """The parallel and serial kernels take a scene's block function as a first-class function
    value: two scenes (different block functions and scratch sizes) share one compiled kernel,
    and each gives exactly what its per-point function gives."""
    from fastsdf.backends.kernel import drive as _drive

    for f in (box_world(3), seed_world()):
        for n in (4099, 37):  # parallel, serial
            p = np.random.default_rng(n).uniform(-2, 2, (n, 2))
            d, g = f(*p.T, compute_gradient=True)
            ref = np.array([f.point_fn(x, y) for x, y in p[:40]])
            np.testing.assert_array_equal(d[:40], ref[:, 0])
            np.testing.assert_array_equal(g[:40], ref[:, 1:])
            np.testing.assert_array_equal(f(*p.T), d)
    for kernel in (_drive.run_par, _drive.run_ser):
        assert len(kernel.signatures) == 1, kernel.signatures
