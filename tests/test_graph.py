"""The symbolic graph: construction, sharing, folding, printing, and compiled evaluation of
every operation against analytic values and central finite differences."""

import math
import sys

import numpy as np
import pytest
from conftest import central_gradient

import fastsdf.expr.graph as G
import fastsdf.graph as cg
from fastsdf.expr.graph import evaluate_numpy

x, y = cg.Symbol("x"), cg.Symbol("y")


def test_symbols_are_identified_by_name():
    assert cg.Symbol("x") is x
    assert cg.Symbol("x") == x
    assert cg.Symbol("y") != x
    with pytest.raises(ValueError, match="name"):
        cg.Symbol("not a name")


def test_identical_subexpressions_are_shared():
    a = cg.sym_sqrt(x * x + y * y) - 1.0
    b = cg.sym_sqrt(x * x + y * y) - 1.0
    assert a is b
    e = (x + 1) * (x + 1)
    assert e.args[0] is e.args[1]


def test_constants_fold():
    assert (cg.Constant(2.0) * 3 + 1).value == 7.0
    assert cg.sym_exp(cg.Constant(0.0)).value == 1.0
    assert (x * 1) is x and (x + 0) is x and (0 + x) is x and (x - 0) is x
    assert ((x - 1.5) - 2.5) is (x - 4.0)
    assert cg.sym_min(2.0, 3.0).value == 2.0
    assert cg.sym_smin(1.0, 1.0, k=2.0).value == pytest.approx(1.0 - math.log(2) / 2)


def test_str_is_readable():
    c = cg.sym_sqrt((x - 0) ** 2 + (y - 0) ** 2) - 1.0
    assert str(c) == "(length(x, y) - 1)"
    assert str((x - 2) ** 3) == "(x - 2)**3"
    assert str(cg.sym_max(x, -y)) == "max(x, (-y))"
    assert "smin" in str(cg.sym_smin(x, y, 5))


def test_numpy_scalars_combine_with_expressions():
    e = np.float64(2.0) * x - np.array([1.0])[0]
    assert isinstance(e, cg.Expr)
    assert cg.Function(e, [x, y])(3.0, 0.0) == 5.0


def test_expressions_have_no_truth_value():
    with pytest.raises(TypeError, match="truth"):
        bool(x + 1)


def test_bad_operands_raise_type_error():
    with pytest.raises(TypeError, match="real number"):
        x + "a"
    with pytest.raises(TypeError):
        x * (1 + 2j)
    with pytest.raises(ValueError, match="k"):
        cg.sym_smin(x, y, k=-1)
    with pytest.raises(ValueError, match="k"):
        cg.sym_smax(x, y, k=float("nan"))


def test_function_validates_symbols():
    with pytest.raises(ValueError, match="symbols"):
        cg.Function(x + y, [x])
    with pytest.raises(ValueError, match="distinct"):
        cg.Function(x + y, [x, x])
    with pytest.raises(ValueError, match="'z'"):
        cg.Function(x + cg.Symbol("z"), [x, y])
    with pytest.raises(TypeError):
        cg.Function(x, 5)


def test_notebook_circle_outputs():
    """Notebook cell 2: c(0,0), c(1,0), c(100,100) -> (-1, 0, 140.42135624) (scalars for
    scalar coordinates, as NumPy answers; the notebook printed one-element arrays)."""
    c = cg.Function(cg.sym_sqrt((x - 0) ** 2 + (y - 0) ** 2) - 1.0, [x, y])
    d0, d1, d2 = c(0, 0), c(1, 0), c(100, 100)
    assert isinstance(d0, np.float64) and d0 == -1.0
    assert d1 == 0.0
    assert d2 == pytest.approx(140.42135624, abs=1e-8)
    d, g = c(3.0, 4.0, compute_gradient=True)
    assert isinstance(d, np.float64) and g.shape == (2,)
    np.testing.assert_allclose(g, [0.6, 0.8], rtol=1e-15)
    d, g = c(np.array([3.0]), np.array([4.0]), compute_gradient=True)
    assert g.shape == (1, 2)
    np.testing.assert_allclose(g[0], [0.6, 0.8], rtol=1e-15)


def test_function_symbol_order_defines_gradient_order():
    a, b = cg.Symbol("a"), cg.Symbol("b")
    f = cg.Function(a * 2 + b * 3, [b, a])  # first coordinate is b
    d, g = f(np.array([1.0]), np.array([10.0]), compute_gradient=True)
    assert d[0] == 23.0
    np.testing.assert_array_equal(g[0], [3.0, 2.0])


# Each operation: (expression, numpy value function, domain) evaluated on points in the domain.
OPS = [
    ("add", x + y, lambda X, Y: X + Y, (-3, 3)),
    ("sub", x - 2 * y, lambda X, Y: X - 2 * Y, (-3, 3)),
    ("mul", x * y, lambda X, Y: X * Y, (-3, 3)),
    ("div", x / (y * y + 1), lambda X, Y: X / (Y * Y + 1), (-3, 3)),
    ("neg", -(x * y), lambda X, Y: -(X * Y), (-3, 3)),
    ("powc2", (x + y) ** 2, lambda X, Y: (X + Y) ** 2, (-3, 3)),
    ("powc3", (x - y) ** 3, lambda X, Y: (X - Y) ** 3, (-3, 3)),
    ("powc_frac", (x * x + 1) ** 1.5, lambda X, Y: (X * X + 1) ** 1.5, (-3, 3)),
    ("pow_inv", (x * x + 1) ** -1, lambda X, Y: 1 / (X * X + 1), (-3, 3)),
    ("pow_general", (x * x + 1) ** (y * y), lambda X, Y: (X * X + 1) ** (Y * Y), (-1.5, 1.5)),
    (
        "sqrt",
        cg.sym_sqrt(x * x + 2 * y * y + 1),
        lambda X, Y: np.sqrt(X * X + 2 * Y * Y + 1),
        (-3, 3),
    ),
    ("exp", cg.sym_exp(x - y), lambda X, Y: np.exp(X - Y), (-3, 3)),
    ("log", cg.sym_log(x * x + y * y + 0.5), lambda X, Y: np.log(X * X + Y * Y + 0.5), (-3, 3)),
    ("sin", cg.sym_sin(x * y), lambda X, Y: np.sin(X * Y), (-3, 3)),
    ("cos", cg.sym_cos(x + y), lambda X, Y: np.cos(X + Y), (-3, 3)),
    ("abs", cg.sym_abs(x - y), lambda X, Y: np.abs(X - Y), (-3, 3)),
    ("min", cg.sym_min(x, y * y), lambda X, Y: np.minimum(X, Y * Y), (-3, 3)),
    ("max", cg.sym_max(x, y * y), lambda X, Y: np.maximum(X, Y * Y), (-3, 3)),
    ("length", cg.sym_length(x - 1, y + 2), lambda X, Y: np.hypot(X - 1, Y + 2), (-3, 3)),
    (
        "smin",
        cg.sym_smin(x, y, 3.0),
        lambda X, Y: -np.log(np.exp(-3 * X) + np.exp(-3 * Y)) / 3,
        (-3, 3),
    ),
    (
        "smax",
        cg.sym_smax(x, y, 3.0),
        lambda X, Y: np.log(np.exp(3 * X) + np.exp(3 * Y)) / 3,
        (-3, 3),
    ),
]


@pytest.mark.parametrize("name,expr,ref,domain", OPS, ids=[o[0] for o in OPS])
def test_operation_values_and_gradients(name, expr, ref, domain, rng):
    f = cg.Function(expr, [x, y])
    X = rng.uniform(*domain, 400)
    Y = rng.uniform(*domain, 400)
    if name in ("abs", "min", "max"):  # keep finite differences away from the kink
        keep = np.abs({"abs": X - Y, "min": X - Y * Y, "max": X - Y * Y}[name]) > 1e-3
        X, Y = X[keep], Y[keep]
    d, g = f(X, Y, compute_gradient=True)
    np.testing.assert_allclose(d, ref(X, Y), rtol=1e-13, atol=1e-13)
    np.testing.assert_allclose(f(X, Y), d, rtol=0, atol=0)  # value-only kernel agrees exactly
    fd = central_gradient(lambda a, b: ref(a, b), X, Y, h=1e-6)
    np.testing.assert_allclose(g, fd, rtol=1e-6, atol=1e-6)
    # The NumPy reference evaluation of the same graph agrees too.
    rv, (rgx, rgy) = evaluate_numpy(expr, {"x": X, "y": Y}, compute_gradient=True)
    np.testing.assert_allclose(d, rv, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(g, np.stack([rgx, rgy], -1), rtol=1e-10, atol=1e-12)


def test_sqrt_gradient_is_finite_at_zero():
    f = cg.Function(cg.sym_sqrt(x * x * x * x), [x, y])  # not a length(): plain sqrt
    d, g = f(np.array([0.0]), np.array([0.0]), compute_gradient=True)
    assert d[0] == 0 and np.all(np.isfinite(g))


def test_min_max_ties_return_left_gradient():
    fmin = cg.Function(cg.sym_min(2 * x, y + x), [x, y])  # tie where x == y
    fmax = cg.Function(cg.sym_max(y + x, 2 * x), [x, y])
    _, g = fmin(np.array([1.0]), np.array([1.0]), compute_gradient=True)
    np.testing.assert_array_equal(g[0], [2.0, 0.0])
    _, g = fmax(np.array([1.0]), np.array([1.0]), compute_gradient=True)
    np.testing.assert_array_equal(g[0], [1.0, 1.0])


def _deep(depth):
    e = x
    for i in range(depth):
        e = e * 0.999 + y * 1e-3 if i % 2 else cg.sym_sin(e) * 0.5 + x
    return e


def test_deep_graph_builds_prints_and_evaluates():
    """No recursion limit: a graph 5x deeper than Python's recursion limit builds, prints and
    evaluates (all traversals are iterative)."""
    depth = 5 * sys.getrecursionlimit()
    e = _deep(depth)
    assert len(str(e)) > depth
    X, Y = np.array([0.3, -0.2]), np.array([0.1, 0.7])
    ref = evaluate_numpy(e, {"x": X, "y": Y})
    assert np.all(np.isfinite(ref))


def test_deep_graph_compiles():
    """A graph deeper than the recursion limit also generates code and compiles."""
    e = _deep(sys.getrecursionlimit() + 200)
    X, Y = np.array([0.3, -0.2]), np.array([0.1, 0.7])
    f = cg.Function(e, [x, y])
    np.testing.assert_allclose(f(X, Y), evaluate_numpy(e, {"x": X, "y": Y}), rtol=1e-12)


def test_dead_nodes_are_not_generated():
    unused = cg.sym_exp(x) * 12345.678  # built but not part of f
    f = cg.Function(x + y, [x, y])
    assert "12345.678" not in f.compiled.module_source and unused is not None


def test_input_shapes_and_types():
    f = cg.Function(x * 2 + y, [x, y])
    assert f(1, 2) == 4.0 and np.shape(f(1, 2)) == ()
    assert f(np.array([1]), 2).shape == (1,)
    grid = np.mgrid[0:1:3j, 0:1:4j]
    d, g = f(grid[0], grid[1], compute_gradient=True)
    assert d.shape == (3, 4) and g.shape == (3, 4, 2)
    assert f(np.array([], dtype=float), np.array([], dtype=float)).shape == (0,)
    assert f(np.arange(3), np.arange(3)).tolist() == [0.0, 3.0, 6.0]  # integers accepted
    with pytest.raises(ValueError, match=r"x\.shape=\(3,\).*y\.shape=\(2,\)"):
        f(np.zeros(3), np.zeros(2))
    with pytest.raises(TypeError, match="x must hold real numbers"):
        f(np.array(["a", "b"]), np.zeros(2))
    with pytest.raises(TypeError, match="y must hold real numbers"):
        f(np.zeros(2), np.zeros(2, dtype=complex))
    with pytest.raises(TypeError, match="x must hold real numbers"):
        f(np.array([1, None]), np.zeros(2))


def test_interned_nodes_are_unique_and_forgotten_when_unused():
    import gc

    x, y = cg.Symbol("x"), cg.Symbol("y")
    # constants are told apart by their bits: 0.0 and -0.0 are two nodes, NaN is one
    assert cg.Constant(-0.0) is not cg.Constant(0.0)
    assert cg.Constant(math.nan) is cg.Constant(math.nan)
    assert cg.Constant(np.float64(2.5)) is cg.Constant(2.5)
    e = cg.sym_min(x * 3.25 + 1.5, y)
    assert cg.sym_min(x * 3.25 + 1.5, y) is e
    assert e.syms == {"x", "y"} and e.args[0].syms == {"x"} and not e.prms
    p = cg.Param("pp_intern", 0.5)
    assert (e + p).prms == {("pp_intern", 0.5)} and (e + p).syms == {"x", "y"}
    gc.collect()
    before = len(G._INTERN)
    nodes = [x * (1.0 + i / 7) - i for i in range(500)]
    assert len(G._INTERN) >= before + 1000
    del nodes
    gc.collect()
    assert len(G._INTERN) <= before  # the table holds its nodes weakly
    # a node rebuilt after its twin was collected is interned again
    a = x * 123.0
    assert x * 123.0 is a


@pytest.mark.parametrize("limit", [3, 20, 200, 300, 10**6])
def test_printing_with_a_limit_is_the_prefix_of_the_full_text(limit):
    # a limited print walks only the nodes near the root: the same text as cutting the full one
    import functools

    x, y = cg.Symbol("x"), cg.Symbol("y")
    exprs = [
        ((((x * 2 + 1) ** 2 + 1) ** 3) ** 2 + y) ** 2,  # powers print their base first
        functools.reduce(cg.sym_min, [x * float(i) + y for i in range(1, 300)]),
        functools.reduce(lambda a, b: b + a, [cg.sym_abs(x - float(i)) for i in range(300)]),
        cg.sym_smin(cg.sym_select(x, y**3, cg.sym_length(x, y)), -x, 4.0),
    ]
    for e in exprs:
        full = G.expr_to_str(e)
        want = full if len(full) <= limit else full[: limit - 3] + "..."
        assert G.expr_to_str(e, limit=limit) == want
