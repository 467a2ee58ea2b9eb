"""Runtime parameters in every primitive, modifier and blend: a scene built with parameters and
evaluated at values equals the scene built with those values as constants (value, gradient, and
dd/dt against finite differences), and new values never recompile."""

import math

import numpy as np
import pytest

import fastsdf as sdf
from fastsdf.expr.graph import Param, Symbol, evaluate_numpy, sym_cmin, sym_qmin, sym_smax, sym_smin

rng = np.random.default_rng(13)
PX, PY = rng.uniform(-2.5, 2.5, (2, 300))

# name -> (builder taking a dict of numbers or parameters, {parameter: (low, high)}): every
# draw from the ranges gives a valid shape.
CASES = {
    "Halfspace": (
        lambda v: sdf.Halfspace(normal=[v["nx"], 1.0], d=v["d"]),
        dict(nx=(-2, 2), d=(-1, 1)),
    ),
    "Segment": (
        lambda v: sdf.Segment(a=[v["ax"], -0.3], b=[0.8, v["by"]]),
        dict(ax=(-1.5, 0), by=(-1, 1)),
    ),
    "Capsule": (
        lambda v: sdf.Capsule(a=[v["ax"], -0.3], b=[0.8, 0.2], radius=v["r"]),
        dict(ax=(-1.5, 0), r=(0.05, 0.6)),
    ),
    "RoundedBox": (
        lambda v: sdf.RoundedBox(
            minc=[v["x0"], -0.5], maxc=[1.0, v["y1"]], radii=[v["r"], 0.1, 0.2, v["r"]]
        ),
        dict(x0=(-1.5, -0.2), y1=(0.3, 1.2), r=(0.0, 0.35)),
    ),
    "RoundedBox1": (
        lambda v: sdf.RoundedBox(minc=[-1, -0.5], maxc=[1.0, 0.6], radii=v["r"]),
        dict(r=(0.0, 0.5)),
    ),
    "OrientedBox": (
        lambda v: sdf.OrientedBox(a=[v["ax"], -0.5], b=[1, 0.6], thickness=v["w"]),
        dict(ax=(-1.5, 0), w=(0.1, 1)),
    ),
    "Triangle": (
        lambda v: sdf.Triangle(p0=[v["x0"], -0.5], p1=[1, v["y1"]], p2=[0, 1]),
        dict(x0=(-1.5, -0.5), y1=(-0.8, 0.5)),
    ),
    "RegularPolygon": (
        lambda v: sdf.RegularPolygon(center=[v["cx"], 0.1], radius=v["r"], n=6),
        dict(cx=(-0.5, 0.5), r=(0.3, 1.5)),
    ),
    "EquilateralTriangle": (
        lambda v: sdf.EquilateralTriangle(center=[0.2, v["cy"]], radius=v["r"]),
        dict(cy=(-0.5, 0.5), r=(0.3, 1.5)),
    ),
    "Polygon": (
        lambda v: sdf.Polygon([[v["x0"], -1], [1, -1], [1, 1], [0, v["yn"]], [-1, 1]]),
        dict(x0=(-1.5, -0.5), yn=(-0.5, 0.8)),
    ),
    "Star": (
        lambda v: sdf.Star(center=[v["cx"], 0], radius=1.2, inner_radius=v["ri"], n=4),
        dict(cx=(-0.5, 0.5), ri=(0.2, 1.0)),
    ),
    "Ellipse": (
        lambda v: sdf.Ellipse(center=[v["cx"], 0.1], axes=[v["a"], v["b"]]),
        dict(cx=(-0.5, 0.5), a=(0.3, 1.5), b=(0.2, 1.2)),
    ),
    "Ring": (
        lambda v: sdf.Ring(center=[v["cx"], 0.1], radius=v["r"], thickness=v["w"]),
        dict(cx=(-0.5, 0.5), r=(0.6, 1.2), w=(0.05, 1.0)),
    ),
    "Arc": (
        lambda v: sdf.Arc(center=[0.1, v["cy"]], radius=v["r"], aperture=v["ap"], thickness=0.2),
        dict(cy=(-0.5, 0.5), r=(0.5, 1.2), ap=(0.3, 2 * math.pi)),
    ),
    "shell": (lambda v: sdf.Box().shell(v["w"]), dict(w=(0.05, 0.8))),
    "scale": (lambda v: sdf.Triangle().scale(v["s"]), dict(s=(0.3, 2.0))),
    "repeat": (lambda v: sdf.Circle(radius=0.2).repeat([v["sx"], 0.6], 3), dict(sx=(0.5, 0.9))),
    "repeat_count": (
        lambda v: sdf.Circle(radius=0.2).repeat(
            0.5, int(v["n"]) if isinstance(v["n"], float) else v["n"]
        ),
        dict(n=(1, 5)),
    ),
    "smooth_union": (
        lambda v: sdf.Circle(radius=0.5).union(sdf.Box(maxc=[1.5, 0.3]), k=v["k"], kind="cubic"),
        dict(k=(0.05, 1.0)),
    ),
}


def _draw(ranges, r):
    return {
        k: float(r.integers(lo, hi + 1)) if k == "n" else float(r.uniform(lo, hi))
        for k, (lo, hi) in ranges.items()
    }


def _numpy(f, values=None):
    d, g = evaluate_numpy(f.f, {"x": PX, "y": PY}, compute_gradient=True, params=values)
    return d, np.stack(g, -1)


@pytest.mark.parametrize("name", sorted(CASES))
def test_parametric_shape_equals_the_shape_built_with_constants(name):
    """Graph level (NumPy evaluation): random values, value and gradient."""
    build, ranges = CASES[name]
    r = np.random.default_rng(abs(hash(name)) % 2**32)
    defaults = _draw(ranges, r)
    f = build({k: Param(k, v) for k, v in defaults.items()})
    assert f.params == defaults
    for _ in range(6):
        values = _draw(ranges, r)
        d0, g0 = _numpy(build(values))
        d1, g1 = _numpy(f, values)
        np.testing.assert_allclose(d1, d0, rtol=0, atol=1e-12)
        np.testing.assert_allclose(g1, g0, rtol=0, atol=1e-9)


def _kernel_count(f):
    return sum(
        len(getattr(mod, n).overloads)
        for mod in (f.compiled.module, f.compiled.blocks)
        for n in dir(mod)
        if hasattr(getattr(mod, n), "overloads")  # the numba functions
    )


@pytest.mark.slow
@pytest.mark.parametrize("name", sorted(CASES))
def test_compiled_parametric_shape_never_recompiles(name):
    build, ranges = CASES[name]
    r = np.random.default_rng(abs(hash(name)) % 2**32 + 1)
    f = build({k: Param(k, v) for k, v in _draw(ranges, r).items()})
    f(PX, PY, compute_gradient=True)
    before = _kernel_count(f)
    for _ in range(3):
        values = _draw(ranges, r)
        d0, g0 = _numpy(build(values))
        d1, g1 = f(PX, PY, compute_gradient=True, **values)
        np.testing.assert_allclose(d1, d0, rtol=0, atol=1e-11)
        np.testing.assert_allclose(g1, g0, rtol=0, atol=1e-8)
    assert _kernel_count(f) == before


t = sdf.t
MOVING = {
    "ellipse axes": sdf.Ellipse(center=[0.2 * t, 0.1], axes=[1.0 + 0.3 * t, 0.5 - 0.1 * t]),
    "polygon vertices": sdf.Polygon([[-1 + 0.2 * t, -1], [1, -1], [1, 1], [0, 0.2 + t], [-1, 1]]),
    "triangle": sdf.Triangle(p0=[-1 + 0.5 * t, -0.5], p1=[1, -0.5], p2=[0, 1 + t]),
    "arc aperture": sdf.Arc(radius=1.0 + 0.1 * t, aperture=2.0 + t, thickness=0.2),
    "regular polygon": sdf.RegularPolygon(radius=1.0 + 0.2 * t, n=4),
    "rounded box": sdf.RoundedBox(maxc=[1.0 + t, 1.0], radii=0.2 + 0.1 * t),
}


@pytest.mark.slow
@pytest.mark.parametrize("name", sorted(MOVING))
def test_time_derivative_of_moving_primitives(name):
    f, T, h = MOVING[name], 0.7, 1e-6
    x, y = PX[:100], PY[:100]
    d, g, gt = f(x, y, t=T, time_derivative=True)
    fd = (f(x, y, t=T + h) - f(x, y, t=T - h)) / (2 * h)
    np.testing.assert_allclose(gt, fd, rtol=0, atol=1e-7)
    dn, gn = evaluate_numpy(f.f, {"x": x, "y": y, "t": np.full_like(x, T)}, compute_gradient=True)
    np.testing.assert_allclose(d, dn, rtol=0, atol=1e-12)
    np.testing.assert_allclose(gt, gn[2], rtol=0, atol=1e-9)


def test_graph_blends_take_a_parameter_k():
    X, Y = Symbol("x"), Symbol("y")
    a, b = sdf.sym_length(X, Y) - 1.0, X - 0.3
    for op in (sym_smin, sym_smax, sym_qmin, sym_cmin):
        e = op(a, b, Param("k", 0.5))
        for k in (0.2, 0.9):
            got = evaluate_numpy(e, {"x": PX, "y": PY}, params={"k": k})
            np.testing.assert_allclose(
                got, evaluate_numpy(op(a, b, k), {"x": PX, "y": PY}), rtol=0, atol=1e-12
            )
    with pytest.raises(ValueError, match="k given by parameters must be finite and > 0"):
        sym_smin(a, b, Param("k", -1.0))


def test_parameter_errors_name_the_parameter_and_say_why():
    p = Param("p", 5.0)
    with pytest.raises(TypeError, match="n cannot be a runtime parameter.*structure"):
        sdf.RegularPolygon(n=Param("n", 5.0))
    with pytest.raises(TypeError, match="n cannot be a runtime parameter"):
        sdf.Star(n=p)
    with pytest.raises(ValueError, match="axes must be > 0"):
        sdf.Ellipse(axes=[Param("a", -1.0), 0.5])
    with pytest.raises(ValueError, match="a and b must differ"):
        sdf.OrientedBox(a=[Param("ax", 1.0), 0.0], b=[1.0, 0.0])
    with pytest.raises(ValueError, match="radii must be in"):
        sdf.RoundedBox(radii=Param("r", 2.0))
    with pytest.raises(ValueError, match="not simple"):
        sdf.Polygon([[0, 0], [1, 0], [Param("u", 0.0), 1], [1, 1]])
    with pytest.raises(ValueError, match="inner_radius must be < radius"):
        sdf.Star(radius=Param("r", 1.0), inner_radius=1.5)
    with pytest.raises(ValueError, match="thickness must be < 2 \\* radius"):
        sdf.Ring(radius=Param("r", 0.1), thickness=0.5)
    with pytest.raises(ValueError, match="count must be an integer >= 1"):
        sdf.Circle().repeat(3.0, Param("c", 1.5))
    with pytest.raises(ValueError, match="s must be > 0"):
        sdf.Circle().scale(Param("s", 0.0))
    with pytest.raises(ValueError, match="coordinates"):
        sdf.Segment(a=[Symbol("x"), 0.0])
