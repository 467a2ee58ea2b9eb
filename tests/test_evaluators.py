"""One suite for every evaluator of a scene: the same scenes and the same assertions run on each
path (the NumPy reference of the op table, the compiled kernel serial, parallel and pruned, the
NumPy path, and the CUDA kernels, plain and pruned), as a
backend-agnostic test suite should."""

import numpy as np
import pytest
from conftest import HAS_NUMBA_CUDA

import fastsdf as sdf
from fastsdf.expr.graph import evaluate_numpy
from fastsdf.expr.points import PARALLEL_MIN_POINTS
from fastsdf.shapes.scenes import box_world, seed_world


def _reference(f, x, y):
    ok = np.isfinite(x) & np.isfinite(y)
    d = np.full(x.shape, np.nan)
    g = np.full(x.shape + (2,), np.nan)
    vals, (gx, gy) = evaluate_numpy(f.f, {"x": x[ok], "y": y[ok]}, compute_gradient=True)
    d[ok] = vals
    g[ok, 0], g[ok, 1] = gx, gy
    return d, g


def _kernel_serial(f, x, y):
    # Calls below PARALLEL_MIN_POINTS run the serial kernel.
    parts = [
        f(x[i : i + 1000], y[i : i + 1000], compute_gradient=True, prune=False, backend="kernel")
        for i in range(0, x.size, 1000)
    ]
    return np.concatenate([p[0] for p in parts]), np.concatenate([p[1] for p in parts])


def _kernel_parallel(f, x, y):
    assert x.size >= PARALLEL_MIN_POINTS
    return f(x, y, compute_gradient=True, prune=False, backend="kernel")


def _kernel_pruned(f, x, y):
    return f(x, y, compute_gradient=True, prune=True, backend="kernel")


def _numpy(f, x, y):
    return f(x, y, compute_gradient=True, backend="numpy")


def _cuda(f, x, y):
    # The CUDA target (under numba-cuda's simulator where no GPU is present: tests/conftest.py)
    return f(x, y, compute_gradient=True, prune=False, backend="cuda")


def _cuda_pruned(f, x, y):
    return f(x, y, compute_gradient=True, prune=True, backend="cuda")


PATHS = {
    "reference": _reference,
    "kernel_serial": _kernel_serial,
    "kernel_parallel": _kernel_parallel,
    "kernel_pruned": _kernel_pruned,
    "numpy": _numpy,
}
if HAS_NUMBA_CUDA:
    PATHS.update(cuda=_cuda, cuda_pruned=_cuda_pruned)


def _every_kind():
    f = sdf.Halfspace([0, 1], -1.8)
    shapes = [
        sdf.Circle([0.1, 0.2], 0.5),
        sdf.Box([-0.4, -0.2], [0.3, 0.5]),
        sdf.Segment([0, 0], [1, 0.5]),
        sdf.Capsule([0, 0], [1, 0.3], 0.2),
        sdf.RoundedBox([-1, -0.5], [0.5, 0.2], 0.1),
        sdf.OrientedBox([-1, 0], [1, 0.4], 0.3),
        sdf.Triangle(),
        sdf.RegularPolygon([0.2, 0], 0.8, 7),
        sdf.Polygon([[0, 0], [1, 0], [1, 1], [0.5, 0.3], [0, 1]]),
        sdf.Star([0.1, 0], 1.0, 5),
        sdf.Ellipse([0.1, 0.2], [0.9, 0.3]),
        sdf.Ring([0.3, 0], 0.5, 0.1),
        sdf.Arc(),
    ]
    for j, s in enumerate(shapes):
        with sdf.transform(angle=0.3 * j, offset=[0.2 * (j % 3) - 0.2, 0.1 * (j % 4) - 0.15]):
            s = s.rotate(0.1 * j)
        f = f.union(s, k=0.08, kind="quadratic") if j % 2 else f - s.shell(0.03)
    return f


SCENES = {
    "seed world": seed_world,
    "20-box world": lambda: box_world(20),
    "every primitive kind, blended": _every_kind,
    "200-circle union": lambda: sdf.union(
        [sdf.Circle([np.cos(k), np.sin(2 * k)], 0.05) for k in range(200)]
    ),
}


@pytest.fixture(scope="module", params=list(SCENES))
def scene(request):
    f = SCENES[request.param]()
    rng = np.random.default_rng(len(request.param))
    x, y = rng.uniform(-2.2, 2.2, (2, 6000))
    x[::97], y[5::101], x[9::89] = np.nan, np.inf, -np.inf  # non-finite: NaN for those only
    return f, x, y, _reference(f, x, y)


#: The CUDA paths run the first points only: the simulator executes every GPU thread as Python.
CUDA_POINTS = 1200


@pytest.mark.parametrize("path", [p for p in PATHS if p != "reference"])
def test_every_path_agrees_with_the_reference(scene, path):
    f, x, y, (d_ref, g_ref) = scene
    if path.startswith("cuda"):
        x, y, d_ref, g_ref = (a[:CUDA_POINTS] for a in (x, y, d_ref, g_ref))
    d, g = PATHS[path](f, x, y)
    ok = np.isfinite(x) & np.isfinite(y)
    assert d.shape == x.shape and g.shape == x.shape + (2,)
    assert np.isnan(d[~ok]).all() and np.isnan(g[~ok]).all()
    assert np.isfinite(d[ok]).all() and np.isfinite(g[ok]).all()
    np.testing.assert_allclose(d[ok], d_ref[ok], rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(g[ok], g_ref[ok], rtol=1e-9, atol=1e-9)
    # The value does not depend on whether the gradient was asked for.
    if path != "kernel_serial":
        kw = {
            "kernel_parallel": {"prune": False, "backend": "kernel"},
            "kernel_pruned": {"prune": True, "backend": "kernel"},
            "cuda": {"prune": False, "backend": "cuda"},
            "cuda_pruned": {"prune": True, "backend": "cuda"},
        }.get(path, {"backend": path})
        np.testing.assert_array_equal(f(x, y, **kw), d)


def test_kernel_paths_give_the_same_bits(scene):
    """Serial, parallel and pruned kernels run the same arithmetic per point."""
    f, x, y, _ = scene
    serial, parallel, pruned = (
        PATHS[p](f, x, y) for p in ("kernel_serial", "kernel_parallel", "kernel_pruned")
    )
    for a, b in ((serial, parallel), (parallel, pruned)):
        np.testing.assert_array_equal(a[0], b[0])
        np.testing.assert_array_equal(a[1], b[1])


def test_reference_gradient_matches_finite_differences(scene):
    """The oracle itself: its analytic gradient against central differences of its values,
    away from the kinks of min/max (where one-sided slopes differ)."""
    f, x, y, (d, g) = scene
    h = 1e-6
    ok = np.isfinite(x) & np.isfinite(y)
    xs, ys = x[ok][:2000], y[ok][:2000]
    fd = np.stack(
        [
            (_reference(f, xs + h, ys)[0] - _reference(f, xs - h, ys)[0]) / (2 * h),
            (_reference(f, xs, ys + h)[0] - _reference(f, xs, ys - h)[0]) / (2 * h),
        ],
        -1,
    )
    err = np.abs(fd - g[ok][:2000]).max(axis=1)
    assert np.median(err) < 1e-6
    assert (err < 1e-5).mean() > 0.97  # the rest straddle a kink within h
