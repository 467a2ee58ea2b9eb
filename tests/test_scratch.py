"""Scratch space of the scene-independent kernels (``fastsdf.backends.kernel.drive``): the buffer is
kept per Python thread between calls and a small call computes only the lanes it needs. Neither may
change a bit: stale rows must never be read, and two threads must never share a buffer."""

import threading

import numba
import numpy as np
import pytest

import fastsdf as sdf
from fastsdf.shapes.scenes import mixed_scene

SIZES = (0, 1, 7, 8, 9, 511, 512, 513, 1100)


def _mixed():
    """A scene without repeated structure (the combine-program path)."""
    return mixed_scene(30, seed=5)


def _looped(n=60, seed=2):
    """A hard union of many same-shape operands (block kernels with loops over tables; the
    tile path prunes it bit for bit)."""
    rng = np.random.default_rng(seed)
    f = None
    for c, r in zip(rng.uniform(-2, 2, (n, 2)), rng.uniform(0.05, 0.2, n)):
        s = sdf.Circle(c, r)
        f = s if f is None else f | s
    return f


def _points(n, seed=0):
    p = np.random.default_rng(seed).uniform(-2.5, 2.5, (n, 2))
    p[3::37, 0] = np.nan
    p[5::41, 1] = np.inf
    return np.ascontiguousarray(p[:, 0]), np.ascontiguousarray(p[:, 1])


def _same(a, b):
    return np.array_equal(np.asarray(a).view(np.int64), np.asarray(b).view(np.int64))


def _reference(f, xs, ys):
    """The one-point function of the scene's own module, point by point."""
    pv = f.compiled.point_fn("vg")
    ref = np.array([pv(x, y) for x, y in zip(xs, ys)]).reshape(-1, 3)
    return ref[:, 0], ref[:, 1:]


@pytest.mark.parametrize("scene", ["mixed", "looped"])
def test_kept_scratch_gives_the_same_bits(scene):
    """Every size around the block length, serial and parallel kernels, value and gradient,
    with this thread's kept buffer filled with NaN first (a stale row that were read would
    show) and with a fresh buffer: bit for bit the one-point function."""
    f = _mixed() if scene == "mixed" else _looped()
    comp = f.compiled
    if scene == "mixed":
        assert "_PROG_VG = np.array" in comp.module_source
    else:
        assert "def _block_vg(" in comp.module_source and comp.groups
    for n in SIZES:
        xs, ys = _points(n, n)
        d_ref, g_ref = _reference(f, xs, ys)
        for parallel in (False, True):
            extra = (8,) if parallel else ()
            for fresh in (False, True):
                kw = {} if fresh else comp.scratch("vg", parallel)
                if kw:
                    kw["S"][:] = np.nan
                out, grad = np.empty(n), np.empty((n, 2))
                if n:
                    comp.kernel("vg", parallel)(xs, ys, out, grad, *extra, **kw)
                assert _same(out, d_ref) and _same(grad, g_ref), (n, parallel, fresh)
                kw = {} if fresh else comp.scratch("v", parallel)
                if kw:
                    kw["S"][:] = np.nan
                out = np.empty(n)
                if n:
                    comp.kernel("v", parallel)(xs, ys, out, *extra, **kw)
                assert _same(out, d_ref), (n, parallel, fresh, "v")
        d, g = f(xs, ys, compute_gradient=True, prune=False)
        assert _same(d, d_ref) and _same(g, g_ref)
        assert _same(f(xs, ys, prune=False), d_ref)


def test_tile_path_uses_the_kept_scratch():
    """The pruned tile kernels take the same per-thread buffer: hard unions prune bit for bit,
    whatever the buffer held before."""
    f = _looped()
    xs, ys = _points(5000, 1)
    d0, g0 = f(xs, ys, compute_gradient=True, prune=False)
    for _ in range(2):
        f.compiled.scratch("vg", True)["S"][:] = np.nan
        d, g = f(xs, ys, compute_gradient=True, prune=True)
        assert _same(d, d0) and _same(g, g0)
    assert _same(f(xs, ys, prune=True), d0)


def test_too_small_scratch_is_refused():
    f = _mixed()
    xs, ys = _points(10)
    out, grad = np.empty(10), np.empty((10, 2))
    size = f.compiled.blocks.scratch_vg
    with pytest.raises(ValueError, match="scratch"):
        f.compiled.kernel("vg", False)(xs, ys, out, grad, S=np.empty(size - 1))


def test_two_python_threads_share_a_function():
    """Two Python threads evaluate the same function at once (the kernels release the GIL):
    each gets its own buffer and the right bits. Parallel kernels only where the threading
    layer allows concurrent parallel regions."""
    f = _mixed()
    f(np.zeros(1), np.zeros(1), compute_gradient=True)  # compile first
    sizes = [1, 9, 513, 1100]
    layer_ok = numba.threading_layer() in ("omp", "tbb")
    if layer_ok:
        sizes.append(5000)  # parallel kernels (PARALLEL_MIN_POINTS)
    cases = {}
    for k in range(2):
        for n in sizes:
            xs, ys = _points(n, 100 * k + n)
            cases[k, n] = (xs, ys) + _reference(f, xs, ys)
    errors, bufs = [], {}
    start = threading.Barrier(2)

    def work(k):
        try:
            start.wait()
            for _ in range(15):
                for n in sizes:
                    xs, ys, d_ref, g_ref = cases[k, n]
                    d, g = f(xs, ys, compute_gradient=True, prune=False)
                    if not (_same(d, d_ref) and _same(g, g_ref)):
                        errors.append((k, n))
            bufs[k] = f.compiled.scratch("vg", False)["S"]
        except BaseException as exc:  # reported below
            errors.append(exc)

    threads = [threading.Thread(target=work, args=(k,)) for k in range(2)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert not errors, errors
    assert bufs[0] is not bufs[1]
