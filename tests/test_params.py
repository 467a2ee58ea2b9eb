"""Runtime parameters and time: values as kernel data (no recompiles), dd/dt in forward mode."""

import math

import numpy as np
import pytest

import fastsdf as sdf
import fastsdf.graph as cg
from fastsdf.backends.kernel import cache as _cache
from fastsdf.expr.graph import Param, Symbol, evaluate_numpy, sym_cos, sym_sin
from fastsdf.function import Function

X, Y = Symbol("x"), Symbol("y")
rng = np.random.default_rng(7)
PX, PY = rng.uniform(-2, 2, (2, 5000))  # above the parallel threshold
SX, SY = rng.uniform(-2, 2, (2, 50))  # the serial kernels


def _moving_scene(px, w, t, k=8.0):
    """A circle whose centre is a parameter, a box rotating at angular speed w (rad/s) and a
    circle rising at 0.5 per second, joined by an exponential blend."""
    c, s = sym_cos(w * t), sym_sin(w * t)
    u, v = X * c + Y * s, Y * c - X * s  # rotated by w t
    box = sdf.sym_length(
        sdf.sym_max(abs_(u) - 1.0, 0.0), sdf.sym_max(abs_(v) - 0.2, 0.0)
    ) + sdf.sym_min(0.0, sdf.sym_max(abs_(u) - 1.0, abs_(v) - 0.2))
    circle = sdf.sym_length(X - px, Y - 1.0) - 0.4
    rising = sdf.sym_length(X + 1.0, Y - 0.5 * t) - 0.3
    return sdf.sym_smin(sdf.sym_min(box, circle), rising, k)


def abs_(e):
    return sdf.sym_abs(e)


def _kernel_count(f):
    return sum(
        len(getattr(mod, name).overloads)
        for mod in (f.compiled.module, f.compiled.blocks)
        for name in dir(mod)
        if hasattr(getattr(mod, name), "overloads")  # the numba functions
    )


def test_parameter_changes_never_recompile():
    px, w = Param("px", 0.3), Param("w", 2.0)
    f = Function(_moving_scene(px, w, sdf.t), [X, Y])
    assert f.params == {"px": 0.3, "w": 2.0, "t": 0.0}
    assert f.param_names == ("px", "w") and f.time_dependent
    f(PX, PY)
    f(PX, PY, compute_gradient=True)
    f(SX, SY, compute_gradient=True)
    f(PX, PY, time_derivative=True)
    compiled = _kernel_count(f)
    modules = len(_cache._MODULES)
    for value in (-1.0, 0.0, 0.7, 1.5):
        f(PX, PY, px=value, t=value)
        f(SX, SY, compute_gradient=True, w=value)
        f.with_params(px=value)(PX, PY, compute_gradient=True, time_derivative=True, t=2 * value)
    # A second scene differing only in the parameters' defaults: the same module, no compile.
    g = Function(_moving_scene(Param("px", -0.5), Param("w", 1.0), sdf.t), [X, Y])
    assert g.f is not f.f
    assert g.compiled.module is f.compiled.module
    g(PX, PY, compute_gradient=True)
    assert _kernel_count(f) == compiled
    assert len(_cache._MODULES) == modules


def test_values_equal_the_constant_baked_scene():
    f = Function(_moving_scene(Param("px", 0.3), Param("w", 2.0), sdf.t), [X, Y])
    x, y = PX[:50], PY[:50]  # baked scenes evaluated serially (compile only point_vg)
    for px, w, t in [(-0.7, 1.3, 0.4), (1.1, -3.0, 2.5)]:
        baked = Function(_moving_scene(px, w, cg.Constant(t)), [X, Y])
        assert not baked.params
        d0, g0 = baked(x, y, compute_gradient=True)
        d1, g1 = f(PX, PY, compute_gradient=True, px=px, w=w, t=t)  # parallel
        d2, g2, _ = f.with_params(px=px, w=w, t=t)(x, y, time_derivative=True)  # serial
        d3, g3 = f(x, y, compute_gradient=True, px=px, w=w, t=t)
        for d, g in ((d1[:50], g1[:50]), (d2, g2), (d3, g3)):
            np.testing.assert_allclose(d, d0, rtol=0, atol=1e-12)
            np.testing.assert_allclose(g, g0, rtol=0, atol=1e-10)
        assert np.array_equal(f(PX, PY, px=px, w=w, t=t), d1)
    frozen = f.frozen(px=-0.7, w=1.3, t=0.4)
    assert not frozen.params and f.params["px"] == 0.3
    np.testing.assert_allclose(frozen(x, y), f(x, y, px=-0.7, w=1.3, t=0.4), atol=1e-12)


def test_time_derivative_against_finite_differences_and_reference():
    f = Function(_moving_scene(Param("px", 0.3), Param("w", 2.0), sdf.t), [X, Y])
    t, h = 0.37, 1e-6
    d, grad, dt = f(PX, PY, t=t, time_derivative=True)
    fd = (f(PX, PY, t=t + h) - f(PX, PY, t=t - h)) / (2 * h)
    # Away from kinks (ties of min/max, box corners) the central difference is O(h^2).
    ok = np.abs(fd - dt) < 1e-5
    assert ok.mean() > 0.99
    ref, (rx, ry, rt) = evaluate_numpy(
        f.f, {"x": PX, "y": PY, "t": np.full_like(PX, t)}, True, params={"px": 0.3, "w": 2.0}
    )
    np.testing.assert_allclose(d, ref, atol=1e-12)
    np.testing.assert_allclose(grad[:, 0], rx, atol=1e-10)
    np.testing.assert_allclose(dt, rt, atol=1e-10)
    # A serial-sized batch and the per-point function agree with the batch kernels.
    d_s, g_s, dt_s = f(PX[:40], PY[:40], t=t, time_derivative=True)
    np.testing.assert_allclose(dt_s, dt[:40], atol=1e-13)
    one = f.point_time_fn(float(PX[0]), float(PY[0]), t, f.param_tuple())
    np.testing.assert_allclose(one, [d[0], grad[0, 0], grad[0, 1], dt[0]], atol=1e-13)


def test_surface_normal_speed_of_a_rising_circle():
    # A circle rising at u: on its boundary -dd/dt / |grad d| is the normal speed u n_y.
    u = 0.8
    f = Function(sdf.sym_length(X, Y - u * sdf.t) - 1.0, [X, Y])
    a = np.linspace(0, 2 * np.pi, 50)
    t = 1.25
    x, y = np.cos(a), np.sin(a) + u * t
    d, g, dt = f(x, y, t=t, time_derivative=True)
    np.testing.assert_allclose(d, 0, atol=1e-12)
    np.testing.assert_allclose(-dt / np.hypot(g[:, 0], g[:, 1]), u * np.sin(a), atol=1e-12)


def test_static_scene_time_derivative_is_zero_and_t_is_accepted():
    f = sdf.Circle(center=[0.2, 0], radius=0.5)
    assert f.params == {} and not f.time_dependent
    d, g, dt = f(SX, SY, time_derivative=True)
    assert np.array_equal(dt, np.zeros_like(SX))
    assert np.array_equal(f(SX, SY, t=3.0), f(SX, SY))


def test_parameter_errors_name_the_parameter():
    f = Function(sdf.sym_length(X - Param("px", 0.1), Y) - 1.0, [X, Y])
    with pytest.raises(TypeError, match="unknown parameter 'py'"):
        f(SX, SY, py=1.0)
    with pytest.raises(ValueError, match="px must be finite"):
        f(SX, SY, px=math.nan)
    with pytest.raises(TypeError, match="px must be a real number"):
        f.with_params(px="a")
    with pytest.raises(ValueError, match="two defaults"):
        Function(sdf.sym_min(X - Param("a", 1.0), Y - Param("a", 2.0)), [X, Y])
    with pytest.raises(ValueError, match="identifier"):
        Param("not a name")
    with pytest.raises(ValueError, match="coordinate"):
        Param("x")
    with pytest.raises(ValueError, match="finite"):
        Param("a", math.inf)
    g = f.with_params(px=0.5)
    assert g.params == {"px": 0.5} and f.params == {"px": 0.1}
    np.testing.assert_allclose(g(SX, SY), np.hypot(SX - 0.5, SY) - 1.0, atol=1e-12)


def test_shapes_take_parameters_wherever_a_number_is():
    a, px, r, k = Param("angle", 0.3), Param("px", 0.5), Param("r", 0.3), Param("k", 0.2)

    def scene(angle, cx, radius, blend, lift):
        with sdf.transform(angle=angle, offset=[0.1, 0.2]):
            bar = sdf.Box(minc=[-1, -0.1], maxc=[1, 0.1])
        ball = sdf.Circle(center=[cx, 0.4], radius=radius).translate([0.0, lift])
        return bar.union(ball, k=blend, kind="quadratic").round(0.05) | sdf.Halfspace(
            normal=[0, 1], d=-1.5
        ).union(bar.rotate(angle), k=10 * blend)

    f = scene(a, px, r, k, 0.5 * sdf.t)
    assert f.params == {"angle": 0.3, "px": 0.5, "r": 0.3, "k": 0.2, "t": 0.0}
    assert f.exactness == "bound"
    assert sdf.Circle(center=[px, 0], radius=r).exactness == "exact"
    f(SX, SY, compute_gradient=True)
    before = _kernel_count(f)
    for vals in [
        dict(angle=-0.4, px=0.1, r=0.5, k=0.05, t=0.3),
        dict(angle=1.2, px=-0.3, r=0.2, k=0.3, t=-1.0),
    ]:
        baked = scene(vals["angle"], vals["px"], vals["r"], vals["k"], 0.5 * vals["t"])
        d0, g0 = baked(SX, SY, compute_gradient=True)
        d1, g1 = f(SX, SY, compute_gradient=True, **vals)
        np.testing.assert_allclose(d1, d0, atol=1e-12)
        np.testing.assert_allclose(g1, g0, atol=1e-9)
    assert _kernel_count(f) == before


def test_shape_parameter_errors():
    with pytest.raises(ValueError, match="radius must be > 0"):
        sdf.Circle(radius=Param("r", -1.0))
    with pytest.raises(ValueError, match="coordinates"):
        sdf.Circle(center=[X, 0])
    with pytest.raises(ValueError, match="minc must be below maxc"):
        sdf.Box(minc=[Param("lo", 2.0), 0], maxc=[1, 1])
    with pytest.raises(ValueError, match="must be > 0"):
        sdf.Circle().union(sdf.Circle(center=[1, 0]), k=Param("k", 0.0))


def test_grid_of_a_parametric_scene_is_a_snapshot():
    f = sdf.Circle(center=[Param("px", 0.25), 0.0], radius=0.5)
    g = sdf.GridSDF(f.with_params(px=-0.25), bounds=[(-1, 1), (-1, 1)], samples=[41, 41])
    np.testing.assert_allclose(g(SX / 2, SY / 2), np.hypot(SX / 2 + 0.25, SY / 2) - 0.5, atol=0.02)
    with pytest.raises(ValueError, match="depends on time"):
        sdf.GridSDF(sdf.Circle(center=[0.0, sdf.t], radius=0.5))


@pytest.mark.parametrize("n", [1, 511, 513, 3 * 512 + 5, 4096 + 7])
def test_parametric_block_kernels_at_block_edges(n):
    # The batch kernels of a parametric scene are the SIMD block kernels (parameters and time
    # read once per block): every kind, any length, non-finite points NaN, the same numbers as
    # the one-point function.
    from fastsdf.backends.kernel.simd import BLOCK

    assert BLOCK == 512
    f = Function(_moving_scene(Param("px", 0.3), Param("w", 2.0), sdf.t), [X, Y])
    assert "def _block_vgt(" in f.compiled.module_source
    r = np.random.default_rng(n)
    x, y = r.uniform(-2, 2, (2, n))
    x[::7] = np.nan
    d, g, gt = f(x, y, t=0.4, px=-0.3, time_derivative=True)
    point = f.compiled.point_fn("vgt")
    prm = f.with_params(px=-0.3).param_tuple()
    ref = np.array([point(a, b, 0.4, prm) for a, b in zip(x, y)])
    np.testing.assert_allclose(np.stack([d, g[:, 0], g[:, 1], gt], -1), ref, rtol=0, atol=1e-12)
    assert np.array_equal(f(x, y, t=0.4, px=-0.3), d, equal_nan=True)
    d2, g2 = f(x, y, t=0.4, px=-0.3, compute_gradient=True)
    assert np.array_equal(d2, d, equal_nan=True) and np.array_equal(g2, g, equal_nan=True)
    assert np.all(np.isnan(d[::7])) and np.all(np.isfinite(np.delete(d, np.s_[::7])))
