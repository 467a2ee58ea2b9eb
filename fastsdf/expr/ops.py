"""The table of operations: every node operation of :mod:`fastsdf.expr.graph` is defined once, here.

Each entry of :data:`OPS` is an :class:`Op` with everything an evaluator needs:

``fmt(node, args) -> str``
    how :func:`fastsdf.expr.graph.expr_to_str` prints the node (``args``: the printed arguments).
``np(node, av, with_grad) -> (value, partials)``
    the NumPy reference (whole arrays, one operation per node;
    :func:`fastsdf.expr.graph.evaluate_numpy`). ``partials`` (only when ``with_grad``) is a
    :ref:`gradient rule <rules>`.
``emit(em, out, node, a, r) -> partials``
    the code template for the generated code (:mod:`fastsdf.backends.emit`): append statements
    to ``out`` that assign the node's value to the variable named ``r``. ``a`` holds the
    arguments' emitted values: ``a[i].v`` is an expression of generated code
    (:class:`fastsdf.backends.code.Code`), built with Python's operators and ``em.num(v)``
    (a literal of the formula), ``em.const(v)`` (a number of the scene: a node's attribute),
    ``em.call(fn, *args)`` (``'exp'``, ``'log'``, ``'sqrt'``, ``'sin'``, ``'cos'``, ``'abs'``,
    ``'floor'``: each target picks its implementation), ``em.sel(cond, a, b)`` (branch-free).
    ``em.grad`` says whether the gradient is wanted, ``em.assign(out, name, expr)`` appends an
    assignment and returns the variable, ``em.table_arg(array)`` passes a constant table.
    Returns the gradient rule (expressions), or None when ``em.grad`` is false.
``interval(node, lo, hi) -> (lo, hi)``
    bounds of the node's value over a set of boxes (arrays, one entry per box) given bounds of
    its arguments; sound for the values the compiled code computes (see
    :mod:`fastsdf.expr.interval`).
``lipschitz(node, L, lo, hi) -> L``
    a bound of the gradient's length over the boxes from the arguments' bounds ``L`` (optional:
    ``None`` means no bound is known).
``live(node, args) -> bool`` (optional)
    whether a gradient component of the node can be nonzero given, per argument, whether its
    component can (default: any argument's); the lowering (:mod:`fastsdf.backends.lower`) keeps
    this as data, and the emitter checks its gradient rules against it.
``chain``
    min, max, smin, smax: associative, flattened into n-ary chains by the code generator (which
    emits them itself; their ``emit`` is not used).

.. _rules:

**Gradient rules.** An operation gives the partial derivatives of its value with respect to each
argument, a list with one entry per argument (``None``: known zero; in generated code the
literals ``1.0`` and ``-1.0`` are recognised). The gradient of the node is then the generic
chain rule ``grad(node)[c] = sum_i partials[i] * grad(arg_i)[c]``, applied by the evaluator to
every gradient component ``c`` alike: x and y today, any further symbol (such as a time ``t``)
with no change here. An operation whose gradient is not a linear combination (``select``, which
picks one argument's gradient) returns instead a function ``combine(gs)`` that maps the
arguments' values for one component to the node's; returning ``None`` from ``combine`` (or a
rule of all ``None``) means a zero component.

**Adding an operation**: one :class:`Op` entry here, plus a ``sym_*`` constructor in
:mod:`fastsdf.expr.graph` (which folds constants and simplifies).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

__all__ = ["Op", "OPS", "chain_rule_numpy", "lit", "fmt_const"]


@dataclass(frozen=True)
class Op:
    """One node operation (see the module docstring for the meaning of each field)."""

    name: str
    arity: int | None  # None: variable (prim: two coordinates and its constants)
    fmt: Callable
    np: Callable
    emit: Callable | None
    interval: Callable
    lipschitz: Callable | None = None
    chain: bool = False
    live: Callable | None = None


OPS: dict[str, Op] = {}


def _register(op: Op) -> Op:
    OPS[op.name] = op
    return op


def lit(v: float) -> str:
    """A float as Python source that numba types as float64."""
    if math.isnan(v):
        return "math.nan"
    if math.isinf(v):
        return "math.inf" if v > 0 else "(-math.inf)"
    s = repr(float(v))
    return f"({s})" if v < 0 or s.startswith("-") else s


def chain_rule_numpy(rule: Any, ag: Sequence, like: np.ndarray) -> list:
    """Gradient components of a node from its rule and its arguments' gradients ``ag``
    (``ag[i][c]``: component ``c`` of argument ``i``); ``like``: an array of the output shape."""
    ncomp = len(ag[0]) if ag else 0
    if callable(rule):
        out = []
        for c in range(ncomp):
            g = rule([a[c] for a in ag])
            out.append(np.zeros_like(like) if g is None else g)
        return out
    terms = [(p, a) for p, a in zip(rule, ag) if p is not None]
    out = []
    for c in range(ncomp):
        acc = None
        for p, a in terms:
            t = p * a[c]
            acc = t if acc is None else acc + t
        out.append(np.zeros_like(like) if acc is None else acc)
    return out


# ---------------------------------------------------------------------------------------------
# Interval helpers. Bounds are arrays (one entry per box). For correctly rounded monotone
# operations (+, -, *, /, sqrt, min, max, floor, abs) the bound computed in floating point from
# the arguments' bounds is itself sound, because rounding is monotone; for library functions
# (exp, log, sin, ...) and for compound operations whose bound is computed differently from the
# generated code, the bound is widened by a margin relative to the magnitudes involved.

_EPS = np.finfo(np.float64).eps
_TINY = 1e-290


def _widen(lo, hi, scale, ulps=8.0):
    m = ulps * _EPS * scale + _TINY
    return lo - m, hi + m


def _mag(*arrays):
    out = None
    for a in arrays:
        a = np.abs(np.where(np.isfinite(a), a, 0.0))
        out = a if out is None else np.maximum(out, a)
    return out


def _corners(fn, alo, ahi, blo, bhi):
    c = [fn(alo, blo), fn(alo, bhi), fn(ahi, blo), fn(ahi, bhi)]
    lo = np.minimum(np.minimum(c[0], c[1]), np.minimum(c[2], c[3]))
    hi = np.maximum(np.maximum(c[0], c[1]), np.maximum(c[2], c[3]))
    bad = np.isnan(c[0]) | np.isnan(c[1]) | np.isnan(c[2]) | np.isnan(c[3])
    return np.where(bad, -np.inf, lo), np.where(bad, np.inf, hi)


def _abs_iv(lo, hi):
    """Bounds of |a| for a in [lo, hi]."""
    alo = np.where(lo >= 0, lo, np.where(hi <= 0, -hi, 0.0))
    return alo, np.maximum(np.abs(lo), np.abs(hi))


def _unknown(like):
    return np.full(np.shape(like), -np.inf), np.full(np.shape(like), np.inf)


def _trig_iv(lo, hi, shift):
    """Bounds of sin(a + shift) for a in [lo, hi] (cos: shift = pi/2), widened by a margin."""
    a, b = lo + shift, hi + shift
    fa, fb = np.sin(a), np.sin(b)
    rlo, rhi = np.minimum(fa, fb), np.maximum(fa, fb)
    # A maximum of sin at pi/2 + 2 pi j, a minimum at -pi/2 + 2 pi j inside [a, b]?
    with np.errstate(all="ignore"):
        jmax = np.ceil((a - np.pi / 2) / (2 * np.pi))
        jmin = np.ceil((a + np.pi / 2) / (2 * np.pi))
        has_max = np.pi / 2 + 2 * np.pi * jmax <= b + 1e-9 * (1 + np.abs(b))
        has_min = -np.pi / 2 + 2 * np.pi * jmin <= b + 1e-9 * (1 + np.abs(b))
    wide = ~np.isfinite(a) | ~np.isfinite(b) | (b - a >= 2 * np.pi) | (np.abs(a) > 1e8)
    rhi = np.where(has_max | wide, 1.0, rhi)
    rlo = np.where(has_min | wide, -1.0, rlo)
    m = 1e-12 * (1.0 + np.abs(np.where(np.isfinite(a), a, 0.0)))
    return np.maximum(rlo - m, -1.0), np.minimum(rhi + m, 1.0)


def _monotone(fn, lo, hi, ulps=4.0):
    with np.errstate(all="ignore"):
        rlo, rhi = fn(lo), fn(hi)
    return _widen(rlo, rhi, _mag(rlo, rhi), ulps)


def _iv_ab(lo, hi):
    return lo[0], hi[0], (lo[1] if len(lo) > 1 else None), (hi[1] if len(hi) > 1 else None)


def _call(name):
    return lambda node, s: f"{name}({', '.join(s)})"


def _infix(sym):
    return lambda node, s: f"({s[0]} {sym} {s[1]})"


# -- add, sub, mul, div, neg ----------------------------------------------------------------


def fmt_const(value: float) -> str:
    """How a constant prints (negative ones in parentheses)."""
    s = repr(value) if not value.is_integer() or abs(value) >= 1e16 else str(int(value))
    if value < 0 or (value == 0 and math.copysign(1, value) < 0):
        s = f"({s})"
    return s


def _fmt_add(node, s):
    b = node.args[1]
    if b.op == "const" and b.attr < 0:
        return f"({s[0]} - {fmt_const(-b.attr)})"
    return f"({s[0]} + {s[1]})"


_register(
    Op(
        "add",
        2,
        _fmt_add,
        np=lambda node, av, g: (av[0] + av[1], [1.0, 1.0] if g else None),
        emit=lambda em, out, node, a, r: (
            em.assign(out, r, a[0].v + a[1].v),
            [em.num(1.0), em.num(1.0)],
        )[1],
        interval=lambda node, lo, hi: (lo[0] + lo[1], hi[0] + hi[1]),
        lipschitz=lambda node, L, lo, hi: L[0] + L[1],
    )
)

_register(
    Op(
        "sub",
        2,
        _infix("-"),
        np=lambda node, av, g: (av[0] - av[1], [1.0, -1.0] if g else None),
        emit=lambda em, out, node, a, r: (
            em.assign(out, r, a[0].v - a[1].v),
            [em.num(1.0), em.num(-1.0)],
        )[1],
        interval=lambda node, lo, hi: (lo[0] - hi[1], hi[0] - lo[1]),
        lipschitz=lambda node, L, lo, hi: L[0] + L[1],
    )
)


def _iv_mul(node, lo, hi):
    with np.errstate(all="ignore"):
        return _corners(np.multiply, lo[0], hi[0], lo[1], hi[1])


def _lip_mul(node, L, lo, hi):
    ma, mb = _abs_iv(lo[0], hi[0])[1], _abs_iv(lo[1], hi[1])[1]
    with np.errstate(all="ignore"):
        return np.where(L[0] == 0, 0.0, mb * L[0]) + np.where(L[1] == 0, 0.0, ma * L[1])


_register(
    Op(
        "mul",
        2,
        _infix("*"),
        np=lambda node, av, g: (av[0] * av[1], [av[1], av[0]] if g else None),
        emit=lambda em, out, node, a, r: (
            em.assign(out, r, a[0].v * a[1].v),
            [a[1].v, a[0].v],
        )[1],
        interval=_iv_mul,
        lipschitz=_lip_mul,
    )
)


def _emit_div(em, out, node, a, r):
    R = em.assign(out, r, a[0].v / a[1].v)
    if not em.grad:
        return None
    ib = em.assign(out, f"{r}i", 1.0 / a[1].v)
    return [ib, -R * ib]


def _iv_div(node, lo, hi):
    with np.errstate(all="ignore"):
        rlo, rhi = _corners(np.divide, lo[0], hi[0], lo[1], hi[1])
    zero = (lo[1] <= 0) & (hi[1] >= 0)
    return np.where(zero, -np.inf, rlo), np.where(zero, np.inf, rhi)


def _lip_div(node, L, lo, hi):
    ma = _abs_iv(lo[0], hi[0])[1]
    mb_lo = _abs_iv(lo[1], hi[1])[0]
    with np.errstate(all="ignore"):
        out = L[0] / mb_lo + np.where(L[1] == 0, 0.0, ma * L[1] / (mb_lo * mb_lo))
    return np.where(mb_lo > 0, out, np.inf)


_register(
    Op(
        "div",
        2,
        _infix("/"),
        np=lambda node, av, g: (
            av[0] / av[1],
            [1.0 / av[1], -av[0] / (av[1] * av[1])] if g else None,
        ),
        emit=_emit_div,
        interval=_iv_div,
        lipschitz=_lip_div,
    )
)

_register(
    Op(
        "neg",
        1,
        lambda node, s: f"(-{s[0]})",
        np=lambda node, av, g: (-av[0], [-1.0] if g else None),
        emit=lambda em, out, node, a, r: (em.assign(out, r, -a[0].v), [em.num(-1.0)])[1],
        interval=lambda node, lo, hi: (-hi[0], -lo[0]),
        lipschitz=lambda node, L, lo, hi: L[0],
    )
)


# -- powers -----------------------------------------------------------------------------------


def _fmt_powc(node, s):
    p = node.attr
    ps = str(int(p)) if p.is_integer() else repr(p)
    base = s[0]
    if not (node.args[0].op in ("sym", "const") or base.startswith("(")):
        base = f"({base})"
    return f"{base}**{ps}"


def _emit_powc(em, out, node, a, r):
    p, A = node.attr, a[0].v
    if p == 2.0:
        em.assign(out, r, A * A)
        return [2.0 * A]
    if p == -1.0:
        R = em.assign(out, r, 1.0 / A)
        return [-R * R]
    em.assign(out, r, A ** em.num(p))
    return [em.num(p) * A ** em.num(p - 1.0)]


def _iv_powc(node, lo, hi):
    p, alo, ahi = node.attr, lo[0], hi[0]
    with np.errstate(all="ignore"):
        if p == 2.0:  # computed as a * a: correctly rounded and monotone in |a|
            mlo, mhi = _abs_iv(alo, ahi)
            return mlo * mlo, mhi * mhi
        if p == -1.0:
            return _iv_div(node, [np.ones_like(alo), alo], [np.ones_like(ahi), ahi])
        if p.is_integer():
            if p % 2 == 0:
                mlo, mhi = _abs_iv(alo, ahi)
                cands = (mlo**p, mhi**p)
                rlo, rhi = np.minimum(*cands), np.maximum(*cands)
                if p < 0:
                    rhi = np.where(mlo == 0, np.inf, rhi)
            else:
                rlo, rhi = np.minimum(alo**p, ahi**p), np.maximum(alo**p, ahi**p)
                if p < 0:
                    zero = (alo <= 0) & (ahi >= 0)
                    rlo, rhi = np.where(zero, -np.inf, rlo), np.where(zero, np.inf, rhi)
        else:  # NaN below 0: bound the values at a >= 0
            clo, chi = np.maximum(alo, 0.0), np.maximum(ahi, 0.0)
            cands = (clo**p, chi**p)
            rlo, rhi = np.minimum(*cands), np.maximum(*cands)
    rlo, rhi = np.where(np.isnan(rlo), -np.inf, rlo), np.where(np.isnan(rhi), np.inf, rhi)
    return _widen(rlo, rhi, _mag(rlo, rhi), 4.0)


def _lip_powc(node, L, lo, hi):
    p = node.attr
    m = _abs_iv(lo[0], hi[0])
    with np.errstate(all="ignore"):
        if p >= 1.0:
            return abs(p) * m[1] ** (p - 1.0) * L[0]
        return np.where(m[0] > 0, abs(p) * m[0] ** (p - 1.0) * L[0], np.inf)


_register(
    Op(
        "powc",
        1,
        _fmt_powc,
        np=lambda node, av, g: (
            av[0] ** node.attr,
            [node.attr * av[0] ** (node.attr - 1.0)] if g else None,
        ),
        emit=_emit_powc,
        interval=_iv_powc,
        lipschitz=_lip_powc,
    )
)


def _np_pow(node, av, g):
    x, y = av
    v = x**y
    return v, ([y * x ** (y - 1.0), v * np.log(x)] if g else None)


def _emit_pow(em, out, node, a, r):
    A, B = a[0].v, a[1].v
    R = em.assign(out, r, A**B)
    return [B * A ** (B - 1.0), R * em.call("log", A)]


def _iv_pow(node, lo, hi):
    with np.errstate(all="ignore"):
        rlo, rhi = _corners(np.power, lo[0], hi[0], lo[1], hi[1])
    pos = lo[0] > 0
    rlo, rhi = np.where(pos, rlo, -np.inf), np.where(pos, rhi, np.inf)
    return _widen(rlo, rhi, _mag(rlo, rhi), 8.0)


_register(
    Op(
        "pow",
        2,
        _infix("**"),
        np=_np_pow,
        emit=_emit_pow,
        interval=_iv_pow,
    )
)


# -- elementary functions ---------------------------------------------------------------------


def _np_sqrt(node, av, g):
    v = np.sqrt(av[0])
    return v, ([np.where(v > 0, 0.5 / np.where(v > 0, v, 1.0), 0.0)] if g else None)


def _emit_sqrt(em, out, node, a, r):
    R = em.assign(out, r, em.call("sqrt", a[0].v))
    return [em.sel(R > 0.0, 0.5 / R, 0.0)]


def _lip_sqrt(node, L, lo, hi):
    with np.errstate(all="ignore"):
        return np.where(lo[0] > 0, L[0] / (2.0 * np.sqrt(np.maximum(lo[0], 0.0))), np.inf)


_register(
    Op(
        "sqrt",
        1,
        _call("sqrt"),
        np=_np_sqrt,
        emit=_emit_sqrt,
        interval=lambda node, lo, hi: (
            np.sqrt(np.maximum(lo[0], 0.0)),
            np.sqrt(np.maximum(hi[0], 0.0)),
        ),
        lipschitz=_lip_sqrt,
    )
)


def _np_exp(node, av, g):
    v = np.exp(av[0])
    return v, ([v] if g else None)


def _iv_exp(node, lo, hi):
    rlo, rhi = _monotone(np.exp, lo[0], hi[0])
    return np.maximum(rlo, 0.0), rhi


_register(
    Op(
        "exp",
        1,
        _call("exp"),
        np=_np_exp,
        emit=lambda em, out, node, a, r: [em.assign(out, r, em.call("exp", a[0].v))],
        interval=_iv_exp,
        lipschitz=lambda node, L, lo, hi: np.exp(hi[0]) * L[0],
    )
)


def _iv_log(node, lo, hi):
    with np.errstate(all="ignore"):
        rlo, rhi = _monotone(np.log, np.maximum(lo[0], 0.0), np.maximum(hi[0], 0.0))
    return np.where(lo[0] > 0, rlo, -np.inf), np.where(np.isnan(rhi), np.inf, rhi)


_register(
    Op(
        "log",
        1,
        _call("log"),
        np=lambda node, av, g: (np.log(av[0]), [1.0 / av[0]] if g else None),
        emit=lambda em, out, node, a, r: (
            em.assign(out, r, em.call("log", a[0].v)),
            [1.0 / a[0].v],
        )[1],
        interval=_iv_log,
        lipschitz=lambda node, L, lo, hi: np.where(
            lo[0] > 0, L[0] / np.where(lo[0] > 0, lo[0], 1.0), np.inf
        ),
    )
)

_register(
    Op(
        "sin",
        1,
        _call("sin"),
        np=lambda node, av, g: (np.sin(av[0]), [np.cos(av[0])] if g else None),
        emit=lambda em, out, node, a, r: (
            em.assign(out, r, em.call("sin", a[0].v)),
            [em.call("cos", a[0].v)],
        )[1],
        interval=lambda node, lo, hi: _trig_iv(lo[0], hi[0], 0.0),
        lipschitz=lambda node, L, lo, hi: L[0],
    )
)

_register(
    Op(
        "cos",
        1,
        _call("cos"),
        np=lambda node, av, g: (np.cos(av[0]), [-np.sin(av[0])] if g else None),
        emit=lambda em, out, node, a, r: (
            em.assign(out, r, em.call("cos", a[0].v)),
            [-em.call("sin", a[0].v)],
        )[1],
        interval=lambda node, lo, hi: _trig_iv(lo[0], hi[0], np.pi / 2),
        lipschitz=lambda node, L, lo, hi: L[0],
    )
)

_register(
    Op(
        "abs",
        1,
        _call("abs"),
        np=lambda node, av, g: (np.abs(av[0]), [np.where(av[0] >= 0, 1.0, -1.0)] if g else None),
        emit=lambda em, out, node, a, r: (
            em.assign(out, r, em.call("abs", a[0].v)),
            [em.sel(a[0].v >= 0.0, 1.0, -1.0)],
        )[1],
        interval=lambda node, lo, hi: _abs_iv(lo[0], hi[0]),
        lipschitz=lambda node, L, lo, hi: L[0],
    )
)

_register(
    Op(
        "floor",
        1,
        _call("floor"),
        np=lambda node, av, g: (np.floor(av[0]), [None] if g else None),
        emit=lambda em, out, node, a, r: (em.assign(out, r, em.call("floor", a[0].v)), [None])[1],
        interval=lambda node, lo, hi: (np.floor(lo[0]), np.floor(hi[0])),
        live=lambda node, a: False,
    )
)


# -- min, max, length -------------------------------------------------------------------------


def _np_minmax(node, av, g):
    x, y = av
    pick_a = (x <= y) if node.op == "min" else (x >= y)
    v = np.where(pick_a, x, y)
    return v, ([pick_a * 1.0, 1.0 - pick_a] if g else None)


_register(
    Op(
        "min",
        2,
        _call("min"),
        np=_np_minmax,
        emit=None,
        interval=lambda node, lo, hi: (np.minimum(lo[0], lo[1]), np.minimum(hi[0], hi[1])),
        lipschitz=lambda node, L, lo, hi: np.maximum(L[0], L[1]),
        chain=True,
    )
)

_register(
    Op(
        "max",
        2,
        _call("max"),
        np=_np_minmax,
        emit=None,
        interval=lambda node, lo, hi: (np.maximum(lo[0], lo[1]), np.maximum(hi[0], hi[1])),
        lipschitz=lambda node, L, lo, hi: np.maximum(L[0], L[1]),
        chain=True,
    )
)


_UP = 2.0**600  # rescales tiny and subnormal lengths into the normal range, exactly


def _np_length(node, av, g):
    x, y = av
    v = np.hypot(x, y)
    if not g:
        return v, None
    # The partials are the unit vector (x, y) / v. Below 1e-150 it is taken from the components
    # rescaled by a power of two: 1 / v overflows for subnormal v, and the quotients of
    # subnormals lose bits. At v = 0 it is (1, 0), the gradient of x (the tie rule).
    tiny = v < 1e-150
    xs, ys = np.where(tiny, x * _UP, x), np.where(tiny, y * _UP, y)
    vs = np.where(tiny, np.hypot(xs, ys), v)
    zero = vs == 0
    safe = np.where(zero, 1.0, vs)
    return v, [np.where(zero, 1.0, xs / safe), np.where(zero, 0.0, ys / safe)]


def _emit_length(em, out, node, a, r):
    # One statement: each target writes the overflow-safe length its own way (see
    # fastsdf.backends.code.Length); the partials are (a, b) / r, as in _np_length.
    return em.length(out, r, a[0].v, a[1].v) or None


def _iv_length(node, lo, hi):
    alo, ahi = _abs_iv(lo[0], hi[0])
    blo, bhi = _abs_iv(lo[1], hi[1])
    rlo, rhi = np.hypot(alo, blo), np.hypot(ahi, bhi)
    return _widen(rlo, rhi, _mag(rlo, rhi), 4.0)


_register(
    Op(
        "length",
        2,
        _call("length"),
        np=_np_length,
        emit=_emit_length,
        interval=_iv_length,
        lipschitz=lambda node, L, lo, hi: np.hypot(L[0], L[1]),
    )
)


# -- smooth minima ----------------------------------------------------------------------------


def _fmt_blend(node, s):
    return f"{node.op}({s[0]}, {s[1]}; k={node.attr:g})"


def _np_smooth(node, av, g):
    x, y = av
    k = node.attr
    s = 1.0 if node.op == "smin" else -1.0
    xa, ya = s * x, s * y  # smax(a, b) = -smin(-a, -b)
    m = np.minimum(xa, ya)
    e = np.exp(-k * np.abs(xa - ya))
    v = s * (m - np.log1p(e) / k)
    if not g:
        return v, None
    w_a = np.where(xa <= ya, 1.0 / (1.0 + e), e / (1.0 + e))
    return v, [w_a, 1.0 - w_a]


def _smin_np(a, b, k):
    with np.errstate(all="ignore"):
        return np.minimum(a, b) - np.log1p(np.exp(-k * np.abs(a - b))) / k


def _iv_smooth(node, lo, hi):
    # Both blends increase with each argument: the bounds are the blends of the bounds. The
    # generated code evaluates a chain as a streaming log-sum-exp (a different rounding): margin.
    k = node.attr
    if node.op == "smin":
        rlo, rhi = _smin_np(lo[0], lo[1], k), _smin_np(hi[0], hi[1], k)
    else:
        rlo, rhi = -_smin_np(-lo[0], -lo[1], k), -_smin_np(-hi[0], -hi[1], k)
    rlo = np.where(np.isnan(rlo), -np.inf, rlo)
    rhi = np.where(np.isnan(rhi), np.inf, rhi)
    return _widen(rlo, rhi, _mag(lo[0], lo[1], hi[0], hi[1]) + 1.0 / k, 16.0)


_register(
    Op(
        "smin",
        2,
        _fmt_blend,
        np=_np_smooth,
        emit=None,
        interval=_iv_smooth,
        lipschitz=lambda node, L, lo, hi: np.maximum(L[0], L[1]),
        chain=True,
    )
)
_register(
    Op(
        "smax",
        2,
        _fmt_blend,
        np=_np_smooth,
        emit=None,
        interval=_iv_smooth,
        lipschitz=lambda node, L, lo, hi: np.maximum(L[0], L[1]),
        chain=True,
    )
)


def _np_poly(node, av, g):
    a, b, k = av[0], av[1], node.attr
    h = np.maximum(k - np.abs(a - b), 0.0) / k
    m = np.where(a <= b, a, b)
    if node.op == "qmin":
        v, w_other = m - h * h * k / 4.0, h / 2.0
    else:
        v, w_other = m - h * h * h * k / 6.0, h * h / 2.0
    if not g:
        return v, None
    w_a = np.where(a <= b, 1.0 - w_other, w_other)
    return v, [w_a, 1.0 - w_a]


def _emit_poly(em, out, node, a, r):
    # min(a, b) - k h^2/4 (quadratic) or - k h^3/6 (cubic), h = max(k - |a - b|, 0)/k;
    # the gradient is a convex combination: weight 1 - h/2 (1 - h^2/2) on the smaller.
    A, B = a[0].v, a[1].v
    k = node.attr
    w = em.assign(out, f"{r}w", A <= B)
    t = em.assign(out, f"{r}t", em.const(k) - em.call("abs", A - B))
    h = em.assign(out, f"{r}h", em.sel(t > 0.0, t, 0.0) * em.const(1.0 / k))
    m = em.sel(w, A, B)
    if node.op == "qmin":
        em.assign(out, r, m - h * h * em.const(k / 4.0))
        other = h * 0.5
    else:
        em.assign(out, r, m - h * h * h * em.const(k / 6.0))
        other = h * h * 0.5
    if not em.grad:
        return None
    o = em.assign(out, f"{r}o", other)
    wa = em.assign(out, f"{r}a", em.sel(w, 1.0 - o, o))
    wb = em.assign(out, f"{r}b", 1.0 - wa)

    def rule(gs):
        # Outside the blend (h = 0) exactly the smaller operand's gradient, as min gives it
        # (not g_a + 0 * g_b, which turns -0.0 into 0.0): pruning a chain of blends drops
        # operands only there and keeps the same bits.
        ga, gb = gs
        terms = [wt if g.is_num(1.0) else g * wt for g, wt in ((ga, wa), (gb, wb)) if g is not None]
        if not terms:
            return None
        blend = terms[0] if len(terms) == 1 else terms[0] + terms[1]
        zero = em.num(0.0)
        return em.sel(h > 0.0, blend, em.sel(w, ga or zero, gb or zero))

    return rule


def _poly_np(a, b, k, cubic):
    with np.errstate(all="ignore"):
        h = np.maximum(k - np.abs(a - b), 0.0) / k
        return np.minimum(a, b) - (h * h * h * k / 6.0 if cubic else h * h * k / 4.0)


def _iv_poly(node, lo, hi):
    # Increasing in each argument (the partials are convex weights).
    cubic = node.op == "cmin"
    k = node.attr
    rlo, rhi = _poly_np(lo[0], lo[1], k, cubic), _poly_np(hi[0], hi[1], k, cubic)
    rlo = np.where(np.isnan(rlo), -np.inf, rlo)
    rhi = np.where(np.isnan(rhi), np.inf, rhi)
    return _widen(rlo, rhi, _mag(lo[0], lo[1], hi[0], hi[1]) + k, 16.0)


for _name in ("qmin", "cmin"):
    _register(
        Op(
            _name,
            2,
            _fmt_blend,
            np=_np_poly,
            emit=_emit_poly,
            interval=_iv_poly,
            lipschitz=lambda node, L, lo, hi: np.maximum(L[0], L[1]),
        )
    )


# -- select and compiled primitives -----------------------------------------------------------


def _np_select(node, av, g):
    pick = av[0] > 0
    return np.where(pick, av[1], av[2]), ((lambda gs: np.where(pick, gs[1], gs[2])) if g else None)


def _emit_select(em, out, node, a, r):
    cond = a[0].v > 0.0
    em.assign(out, r, em.sel(cond, a[1].v, a[2].v))

    def combine(gs):
        if gs[1] is None and gs[2] is None:
            return None
        zero = em.num(0.0)
        return em.sel(cond, zero if gs[1] is None else gs[1], zero if gs[2] is None else gs[2])

    return combine


def _iv_select(node, lo, hi):
    take_a, take_b = lo[0] > 0, hi[0] <= 0
    rlo = np.where(take_a, lo[1], np.where(take_b, lo[2], np.minimum(lo[1], lo[2])))
    rhi = np.where(take_a, hi[1], np.where(take_b, hi[2], np.maximum(hi[1], hi[2])))
    return rlo, rhi


_register(
    Op(
        "select",
        3,
        lambda node, s: f"select({s[0]} > 0, {s[1]}, {s[2]})",
        np=_np_select,
        emit=_emit_select,
        interval=_iv_select,
        live=lambda node, a: a[1] or a[2],
    )
)


def _fmt_prim(node, s):
    kind, data = node.attr
    tag = f"{kind}[{len(data)}]" if isinstance(data, tuple) else kind
    return f"{tag}({', '.join(s)})"


def _prim_constants(node, av):
    """The constants of a prim node from its argument values: runtime parameters are one
    number per evaluation, but ``t`` given as a symbol may vary over the points."""
    return [
        np.array([c.attr]) if c.op == "const" else np.unique(v)
        for c, v in zip(node.args[2:], av[2:])
    ]


def _np_prim(node, av, g):
    from fastsdf.expr.prims_ref import evaluate as _prim_reference

    consts = _prim_constants(node, av)
    if all(len(c) <= 1 for c in consts):
        d, du, dv = _prim_reference(
            node.attr[0],
            node.attr[1],
            av[0],
            av[1],
            [float(c[0]) if len(c) else 0.0 for c in consts],
        )
    else:  # constants that vary over the points: one evaluation per distinct row
        rows = np.stack(av[2:], -1)
        d, du, dv = (np.empty(np.shape(av[0])) for _ in range(3))
        for row in np.unique(rows.reshape(-1, rows.shape[-1]), axis=0):
            sel = np.all(rows == row, axis=-1)
            d[sel], du[sel], dv[sel] = _prim_reference(
                node.attr[0], node.attr[1], av[0][sel], av[1][sel], list(row)
            )
    if not g:
        return d, None
    return d, [du, dv] + _prim_constant_partials(node, av, d, du, dv)


def _prim_constant_partials(node, a, d, du, dv):
    """Partial derivatives in a prim node's constants (``None`` where not available), of
    arrays or of generated code's expressions alike. Ellipse: by the envelope theorem, with
    the closest point ``q = p - d n`` (``n`` the gradient), ``dd/da = -n_u q_u / a`` and
    ``dd/db = -n_v q_v / b``."""
    if node.attr[0] != "ellipse":
        return [None] * (len(a) - 2)
    return [-du * (a[0] - d * du) / a[2], -dv * (a[1] - d * dv) / a[3]]


def _emit_prim(em, out, node, a, r):
    # A fixed compiled function of fastsdf.backends.kernel.prims returns (d, dd/du, dd/dv) at the
    # local coordinates (u, v) = (a[0], a[1]); structural data (polygon vertices) becomes a table.
    kind, data = node.attr
    extra = [c.v for c in a[2:]]
    if data is not None:
        extra.insert(0, em.table_arg(np.asarray(data, dtype=np.float64)))
    call = em.call(f"_P.{kind}_{'vg' if em.grad else 'v'}", a[0].v, a[1].v, *extra)
    if not em.grad:
        em.assign(out, r, call)
        return None
    d, du, dv = em.assign_many(out, [r, f"{r}u", f"{r}v"], call)
    if all(c.g is None or all(x is None for x in c.g) for c in a[2:]):
        return [du, dv] + [None] * (len(a) - 2)
    # constants that depend on time (an ellipse's axes given by sdf.t)
    return [du, dv] + _prim_constant_partials(node, [c.v for c in a], d, du, dv)


def _iv_prim(node, lo, hi):
    # Primitives are exact distances of (u, v), hence 1-Lipschitz there: the value over a box of
    # (u, v) is within its half-diagonal of the value at the box's centre.
    from fastsdf.expr.prims_ref import evaluate as _prim_reference

    # Constants given by parameters (an ellipse's axes) have ranges: the distance changes by at
    # most the change of each axis (|dd/da| = |n_u q_u / a| <= 1), so their half-widths add.
    cu, cv = 0.5 * (lo[0] + hi[0]), 0.5 * (lo[1] + hi[1])
    rad = np.hypot(0.5 * (hi[0] - lo[0]), 0.5 * (hi[1] - lo[1]))
    consts = []
    for c, clo, chi in zip(node.args[2:], lo[2:], hi[2:]):
        if c.op == "const":
            consts.append(float(c.attr))
            continue
        mid = 0.5 * (np.min(clo) + np.max(chi))
        rad = rad + np.max(chi - clo) * 0.5 + np.abs(mid - 0.5 * (clo + chi))
        consts.append(float(mid))
    good = bool(np.all(np.isfinite(consts)) and all(c > 0 for c in consts))
    ok = np.isfinite(cu) & np.isfinite(cv) & np.isfinite(rad) & good
    with np.errstate(all="ignore"):
        d = _prim_reference(
            node.attr[0],
            node.attr[1],
            np.where(ok, cu, 0.0),
            np.where(ok, cv, 0.0),
            consts if good else [1.0] * len(consts),
        )[0]
    # The NumPy reference and the compiled primitive agree to far better than this margin.
    m = (
        1e-9 * (np.abs(d) + rad + np.abs(np.where(ok, cu, 0.0)) + np.abs(np.where(ok, cv, 0.0)))
        + _TINY
    )
    return np.where(ok, d - rad - m, -np.inf), np.where(ok, d + rad + m, np.inf)


_register(
    Op(
        "prim",
        None,
        _fmt_prim,
        np=_np_prim,
        emit=_emit_prim,
        interval=_iv_prim,
        live=lambda node, a: a[0] or a[1] or (node.attr[0] == "ellipse" and any(a[2:])),
        lipschitz=lambda node, L, lo, hi: np.hypot(L[0], L[1]),
    )
)
