"""The CUDA target's own surface (the evaluator suite and the hard cases run it too): device
arrays in and out, parameters and time, grids on the device, and its errors. Without a GPU it
runs under numba-cuda's simulator (tests/conftest.py), on small inputs."""

import builtins
import sys

import numpy as np
import pytest

import fastsdf as sdf
from fastsdf import device
from fastsdf.shapes.scenes import seed_world

pytest.importorskip("numba_cuda")
pytestmark = pytest.mark.filterwarnings("ignore::RuntimeWarning")


@pytest.fixture(scope="module")
def points():
    rng = np.random.default_rng(5)
    p = rng.uniform(-2.5, 2.5, (300, 2))
    p[3] = [np.nan, 0.0]
    p[4] = [0.0, -np.inf]
    return p


def test_device_arrays_in_give_device_arrays_out(points):
    f = seed_world()
    cu = device.cuda()
    xd, yd = cu.to_device(points[:, 0].copy()), cu.to_device(points[:, 1].copy())
    d, g = f(xd, yd, compute_gradient=True, backend="cuda")
    assert device.is_device_array(d) and device.is_device_array(g)
    assert d.shape == (300,) and g.shape == (300, 2)
    d_cpu, g_cpu = f(points, compute_gradient=True, backend="kernel")
    np.testing.assert_allclose(device.to_host(d), d_cpu, rtol=1e-13, atol=1e-13)
    np.testing.assert_allclose(device.to_host(g), g_cpu, rtol=1e-12, atol=1e-12)
    # one (n, 2) device array of points, read by columns
    dp = f(cu.to_device(points), backend="cuda")
    np.testing.assert_array_equal(device.to_host(dp), device.to_host(d))
    assert np.isnan(device.to_host(d)[3:5]).all()


def test_numpy_in_is_copied_and_answered_as_numpy(points):
    f = sdf.Circle([0.2, -0.1], 0.7)
    grid = points.reshape(20, 15, 2)
    d = f(grid, backend="cuda")
    assert isinstance(d, np.ndarray) and d.shape == (20, 15)
    r = np.hypot(grid[..., 0] - 0.2, grid[..., 1] + 0.1) - 0.7
    ok = np.isfinite(r)
    np.testing.assert_allclose(d[ok], r[ok], rtol=1e-14, atol=1e-15)


def test_runtime_parameters_and_time_on_the_device(points):
    X, Y = sdf.Symbol("x"), sdf.Symbol("y")
    f = sdf.Function(sdf.sym_length(X - 0.3 * sdf.t, Y) - sdf.Param("r", 0.5), [X, Y])
    x, y = points[:, 0], points[:, 1]
    for kw in ({}, {"r": 0.9}, {"r": 0.2, "t": 1.5}):
        d, g, dt = f(x, y, time_derivative=True, backend="cuda", **kw)
        d0, g0, dt0 = f(x, y, time_derivative=True, backend="kernel", **kw)
        ok = np.isfinite(d0)
        np.testing.assert_allclose(d[ok], d0[ok], rtol=1e-13, atol=1e-13)
        np.testing.assert_allclose(g[ok], g0[ok], rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(dt[ok], dt0[ok], rtol=1e-12, atol=1e-12)
        # analytic: the circle's centre moves at 0.3 along x
        t = kw.get("t", 0.0)
        rr = kw.get("r", 0.5)
        exact = np.hypot(x - 0.3 * t, y) - rr
        np.testing.assert_allclose(d[ok], exact[ok], rtol=1e-13, atol=1e-13)


def test_a_static_scene_has_no_time_derivative(points):
    d, g, dt = seed_world()(points, time_derivative=True, backend="cuda")
    assert dt.shape == d.shape and not dt.any()


@pytest.mark.parametrize("gradient", ["stored", "fd"])
@pytest.mark.parametrize("mode", ["exact", "nearest"])
def test_grid_on_the_device_matches_the_cpu(points, gradient, mode):
    g = sdf.GridSDF(
        seed_world(), bounds=[(-2, 2), (-2, 2)], samples=[40j, 40j], gradient=gradient, mode=mode
    )
    d, gr = g(points, compute_gradient=True, backend="cuda")
    d0, gr0 = g(points, compute_gradient=True)
    np.testing.assert_allclose(d, d0, rtol=1e-13, atol=1e-13, equal_nan=True)
    np.testing.assert_allclose(gr, gr0, rtol=1e-12, atol=1e-12, equal_nan=True)
    outside = np.abs(points).max(axis=1) > 2
    assert outside.sum() > 20  # the exact answers outside the grid are exercised


def test_bad_input_is_a_clear_error(points):
    f = seed_world()
    cu = device.cuda()
    x, y = np.ascontiguousarray(points.T)
    with pytest.raises(TypeError, match="x must hold float64"):
        f(cu.to_device(x.astype(np.float32)), cu.to_device(y), backend="cuda")
    with pytest.raises(ValueError, match="same shape"):
        f(cu.to_device(x), cu.to_device(y[:10]), backend="cuda")
    with pytest.raises(ValueError, match="last axis of length 2"):
        f(cu.to_device(np.zeros((5, 3))), backend="cuda")
    with pytest.raises(ValueError, match="backend must be one of"):
        f(points, backend="gpu")
    with pytest.raises(ValueError, match="backend must be None, 'cpu' or 'cuda'"):
        sdf.GridSDF(f, samples=[8j, 8j])(points, backend="gpu")


def test_missing_numba_cuda_names_the_extra(monkeypatch):
    real_import = builtins.__import__

    def no_numba_cuda(name, *args, **kwargs):
        if name == "numba_cuda":
            raise ImportError("No module named 'numba_cuda'")
        return real_import(name, *args, **kwargs)

    monkeypatch.setattr(builtins, "__import__", no_numba_cuda)
    monkeypatch.delitem(sys.modules, "numba_cuda", raising=False)
    with pytest.raises(RuntimeError, match=r"fastsdf\[cuda\]"):
        device.cuda()
    with pytest.raises(RuntimeError, match=r"fastsdf\[cuda\]"):
        sdf.Circle([0, 0], 1)(np.zeros(3), np.zeros(3), backend="cuda")


def test_importing_fastsdf_does_not_import_numba_cuda():
    """numba-cuda is an extra: the package and its layers import without it (it is loaded
    when a CUDA path is first asked for)."""
    import subprocess
    import textwrap

    code = textwrap.dedent("""
        import sys
        import fastsdf, fastsdf.particles, fastsdf.granular, fastsdf.fields, fastsdf.viz
        print(sorted(m for m in sys.modules if m == "numba_cuda" or m.startswith("numba.cuda")))
    """)
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"


@pytest.mark.parametrize(
    "framework, maker",
    [
        ("cupy", lambda mod, result: mod.asarray(result)),
        ("torch", lambda mod, result: mod.as_tensor(result, device="cuda")),
    ],
)
def test_results_go_back_as_the_callers_kind_of_array(monkeypatch, framework, maker):
    """A caller's CuPy or PyTorch array gets its answer as the same kind, handed over without
    a copy by that framework's own zero-copy constructor (stand-ins here: no GPU in CI)."""
    import types

    handed = []
    fake = types.ModuleType(framework)
    fake.asarray = lambda a: handed.append(("asarray", a)) or "cupy result"
    fake.as_tensor = lambda a, device=None: handed.append(("as_tensor", a, device)) or "tensor"
    monkeypatch.setitem(sys.modules, framework, fake)
    template = type("Array", (), {"__module__": f"{framework}._core"})()
    result = device.cuda().to_device(np.arange(3.0))
    expected = maker(
        types.SimpleNamespace(
            asarray=lambda a: "cupy result", as_tensor=lambda a, device=None: "tensor"
        ),
        result,
    )
    assert device.like(result, template) == expected
    assert handed[0][1] is result  # the device array itself: no copy to the host
    # NumPy in: a NumPy copy out; a numba device array in: the device array out
    np.testing.assert_array_equal(device.like(result, np.zeros(3)), [0.0, 1.0, 2.0])
    assert device.like(result, result) is result
