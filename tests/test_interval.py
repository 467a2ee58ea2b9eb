"""Interval evaluation: for random scenes, random rectangles and random points inside them, the
bounds of every node hold the value computed at every point (NumPy reference at every node; the
compiled kernel at the root)."""

import numpy as np
import pytest
from hypothesis import HealthCheck, Phase, given, settings
from hypothesis import strategies as st

import fastsdf as sdf
import fastsdf.graph as cg
from fastsdf.expr.graph import topological_order
from fastsdf.expr.interval import bounds, node_bounds, node_values
from fastsdf.shapes.scenes import box_world, seed_world

# Shrinking a failing scene takes minutes; the failing example is reported as found.
_NO_SHRINK = (Phase.explicit, Phase.reuse, Phase.generate)
finite = dict(allow_nan=False, allow_infinity=False)
X, Y = cg.Symbol("x"), cg.Symbol("y")

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
    st.tuples(
        st.just("polygon"),
        st.floats(-1.0, 1.0, **finite),
        st.floats(-1.0, 1.0, **finite),
        st.floats(0.1, 1.0, **finite),
        st.floats(0.1, 1.0, **finite),
    ),
    st.tuples(
        st.just("ellipse"),
        st.floats(-1.0, 1.0, **finite),
        st.floats(-1.0, 1.0, **finite),
        st.floats(0.1, 1.0, **finite),
        st.floats(0.1, 1.0, **finite),
    ),
    st.tuples(
        st.just("capsule"),
        st.floats(-1.0, 1.0, **finite),
        st.floats(-1.0, 1.0, **finite),
        st.floats(0.1, 1.0, **finite),
        st.floats(0.05, 0.5, **finite),
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
    st.sampled_from(["|", "&", "-", "q|", "c&", "round"]),
    st.one_of(st.just(0.0), st.floats(0.5, 40.0, **finite)),
    st.integers(0, 10**6),
)


def _make(prim):
    kind, a, b, c, d = (prim + (None,))[:5]
    if kind == "circle":
        return sdf.Circle(center=[a, b], radius=c)
    if kind == "halfspace":
        return sdf.Halfspace(normal=[a, b], d=c)
    if kind == "box":
        return sdf.Box(minc=[a, b], maxc=(a + c, b + d))
    if kind == "polygon":
        return sdf.Polygon([[a, b], [a + c, b], [a + 0.3 * c, b + d], [a + 0.1 * c, b + 0.4 * d]])
    if kind == "ellipse":
        return sdf.Ellipse([a, b], [c, d])
    return sdf.Capsule([a, b], [a + c, b - c], d)


def build_scene(prims, ops):
    shapes = []
    for prim, tf in prims:
        if tf is None:
            shapes.append(_make(prim))
        else:
            with sdf.transform(angle=tf[0], offset=tf[1:]):
                shapes.append(_make(prim))
    for op, k, pick in ops:
        if len(shapes) == 1:
            break
        a = shapes.pop(pick % len(shapes))
        if op == "round":
            shapes.append(a.round(0.05 + k / 100))
            continue
        b = shapes.pop(pick // 7 % len(shapes))
        if op == "q|":
            shapes.append(a.union(b, k=0.05 + k / 40, kind="quadratic"))
        elif op == "c&":
            shapes.append(a.intersection(b, k=0.05 + k / 40, kind="cubic"))
        else:
            with sdf.smoothness(k):
                shapes.append(a | b if op == "|" else a & b if op == "&" else a - b)
    f = shapes[0]
    for s in shapes[1:]:
        f |= s
    return f


# Every operation of the table, each as a function of two operands and a parameter in [0, 1).
_EXPR_OPS = [
    lambda a, b, c: a + b,
    lambda a, b, c: a - b * c,
    lambda a, b, c: a * b,
    lambda a, b, c: a / (b * b + 0.5),
    lambda a, b, c: -a,
    lambda a, b, c: a**2,
    lambda a, b, c: cg.sym_abs(a) ** 1.5,
    lambda a, b, c: a**3,
    lambda a, b, c: 1.0 / (cg.sym_abs(a) + 0.1),
    lambda a, b, c: (cg.sym_abs(b) + 0.5) ** a,
    lambda a, b, c: cg.sym_sqrt(cg.sym_abs(a)),
    lambda a, b, c: cg.sym_exp(a * 0.5),
    lambda a, b, c: cg.sym_log(a * a + 0.01),
    lambda a, b, c: cg.sym_sin(a * (1 + 5 * c)),
    lambda a, b, c: cg.sym_cos(a),
    lambda a, b, c: cg.sym_abs(a - c),
    lambda a, b, c: cg.sym_min(a, b),
    lambda a, b, c: cg.sym_max(a, b),
    lambda a, b, c: cg.sym_length(a, b),
    lambda a, b, c: cg.sym_smin(a, b, 1 + 10 * c),
    lambda a, b, c: cg.sym_smax(a, b, 0.5 + c),
    lambda a, b, c: cg.sym_floor(a * 2.0),
    lambda a, b, c: cg.sym_select(a - c, a, b),
    lambda a, b, c: cg.sym_qmin(a, b, 0.1 + c),
    lambda a, b, c: cg.sym_cmin(a, b, 0.1 + c),
]


def _expr(draw_ops):
    """A raw expression using every operation of the table (not only SDF-shaped ones)."""
    e = [X, Y, X * 0.7 - Y, cg.sym_sin(X * 3.0), cg.sym_cos(Y - 0.3)]
    for code, c in draw_ops:
        a, b = e[-1], e[-2 - int(c * 3) % min(len(e) - 1, 4)]
        e.append(_EXPR_OPS[code % len(_EXPR_OPS)](a, b, c))
    return e[-1]


def _check_nodes(root, lo_x, hi_x, lo_y, hi_y, rng, lipschitz=True, points=200):
    nb = node_bounds(root, {"x": (lo_x, hi_x), "y": (lo_y, hi_y)}, lipschitz=lipschitz)
    n_boxes = len(lo_x)
    t = rng.random((2, n_boxes, points))
    t[:, :, :4] = np.array([[0, 1, 0, 1], [0, 0, 1, 1]])[:, None, :]  # the corners too
    # (clipped: lo + 1 * (hi - lo) can round past hi)
    px = np.clip(lo_x[:, None] + t[0] * (hi_x - lo_x)[:, None], lo_x[:, None], hi_x[:, None])
    py = np.clip(lo_y[:, None] + t[1] * (hi_y - lo_y)[:, None], lo_y[:, None], hi_y[:, None])
    vals = node_values(root, {"x": px, "y": py})
    for node in topological_order(root):
        v = vals[id(node)]
        lo, hi = nb[id(node)]
        ok = np.isfinite(v)
        assert np.all(lo[:, None] <= np.where(ok, v, np.inf)), (node.op, str(node)[:200])
        assert np.all(hi[:, None] >= np.where(ok, v, -np.inf)), (node.op, str(node)[:200])
    return nb


def _boxes(rng, n, size):
    cx, cy = rng.uniform(-2.5, 2.5, (2, n))
    w, h = size * rng.random((2, n)) + 1e-9
    return cx - w, cx + w, cy - h, cy + h


@settings(
    max_examples=40,
    deadline=None,
    derandomize=True,
    phases=_NO_SHRINK,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
)
@given(
    prims=st.lists(placed, min_size=1, max_size=12),
    ops=st.lists(operation, min_size=0, max_size=14),
    size=st.sampled_from([1e-6, 0.01, 0.2, 1.5]),
    seed=st.integers(0, 1000),
    lipschitz=st.booleans(),
)
def test_random_scene_bounds_hold_at_every_node(prims, ops, size, seed, lipschitz):
    f = build_scene(prims, ops)
    rng = np.random.default_rng(seed)
    _check_nodes(f.f, *_boxes(rng, 12, size), rng, lipschitz=lipschitz, points=60)


@settings(max_examples=60, deadline=None, derandomize=True, phases=_NO_SHRINK)
@given(
    draw=st.lists(
        st.tuples(st.integers(0, 24), st.floats(0.0, 1.0, **finite)), min_size=1, max_size=10
    ),
    size=st.sampled_from([1e-9, 1e-3, 0.3, 3.0]),
    seed=st.integers(0, 1000),
    lipschitz=st.booleans(),
)
def test_random_expression_bounds_hold_at_every_node(draw, size, seed, lipschitz):
    """Every operation of the table, including the non-SDF ones (exp, log, pow, floor, select)."""
    root = _expr(draw)
    rng = np.random.default_rng(seed)
    _check_nodes(root, *_boxes(rng, 10, size), rng, lipschitz=lipschitz, points=80)


def test_bounds_are_tight_for_small_boxes_and_hold_for_the_compiled_kernel():
    """The Lipschitz bound makes an exact SDF's bounds about as wide as the box (interval
    arithmetic alone is looser for rotated shapes); the compiled root values obey them."""
    rng = np.random.default_rng(3)
    for f in (box_world(12), seed_world()):
        lx, hx, ly, hy = _boxes(rng, 50, 0.05)
        lo, hi = bounds(f.f, {"x": (lx, hx), "y": (ly, hy)})
        lo_ia, hi_ia = bounds(f.f, {"x": (lx, hx), "y": (ly, hy)}, lipschitz=False)
        assert np.all(lo >= lo_ia) and np.all(hi <= hi_ia)
        diag = np.hypot(hx - lx, hy - ly)
        assert np.all(hi - lo <= diag * (1 + 1e-6) + 1e-9)
        t = rng.random((2, 50, 100))
        px = np.clip(lx[:, None] + t[0] * (hx - lx)[:, None], lx[:, None], hx[:, None])
        py = np.clip(ly[:, None] + t[1] * (hy - ly)[:, None], ly[:, None], hy[:, None])
        d = f(px.ravel(), py.ravel()).reshape(px.shape)
        assert np.all(lo[:, None] <= d) and np.all(d <= hi[:, None])


def test_bounds_validate_their_input():
    with pytest.raises(ValueError, match="lo > hi"):
        bounds(X + Y, {"x": (1.0, 0.0), "y": (0.0, 1.0)})
    with pytest.raises(ValueError, match="no range given"):
        bounds(X + Y, {"x": (0.0, 1.0)})
