"""Interval evaluation: sound bounds of every node of an expression over boxes of the plane.

``node_bounds(root, boxes)`` gives, for each box (a rectangle of x and y; any symbol can be given
a range), ``lo <= value <= hi`` for every node, where ``value`` is what the compiled kernels
compute at any point of the box (rounding included) wherever that value is finite. Two bounds
are combined, node by node:

* interval arithmetic, by the ``interval`` rule of each operation in :mod:`fastsdf.expr.ops`.
  Correctly rounded monotone operations need no widening (rounding is monotone, so the
  floating-point bound of the bounds bounds the floating-point result); library functions and
  compound operations are widened by a margin relative to the magnitudes involved;
* a Lipschitz bound: ``|f(p) - f(c)| <= L * |p - c|`` from the value at the box's centre, where
  ``L`` bounds the gradient's length over the box (the ``lipschitz`` rules of
  :mod:`fastsdf.expr.ops`, or 1 for an expression known to be an exact or 'bound' SDF, see
  :func:`note_lipschitz`). This is much tighter than interval arithmetic for shapes that are rotated
  or built from many operations, since interval arithmetic forgets that ``x`` is the same ``x``
  everywhere.
"""

from __future__ import annotations

import numpy as np

from fastsdf.expr.graph import Expr, topological_order
from fastsdf.expr.ops import OPS

__all__ = ["node_bounds", "bounds", "note_lipschitz", "node_values"]


class _Hints:
    """Lipschitz constants noted for expressions (exact and 'bound' SDFs, noted by the
    modelling layer): ``LIPSCHITZ_RULES.get(node)`` is the constant or None. Kept on the node itself
    (its ``lip`` slot), which lives exactly as long as the node, at no cost per lookup."""

    @staticmethod
    def get(node: Expr, default: float | None = None) -> float | None:
        value = node.lip
        return default if value is None else value


LIPSCHITZ_RULES = _Hints()
_set_lip = vars(Expr)["lip"].__set__  # the slot's own setter: Expr refuses setattr


def note_lipschitz(expr: Expr, L: float) -> None:
    """Record that ``expr`` is ``L``-Lipschitz in its symbols (e.g. 1 for an exact SDF)."""
    old = expr.lip
    _set_lip(expr, L if old is None else min(old, L))


def node_values(root: Expr, symbols: dict) -> dict:
    """Value of every node (``id(node) -> array``) by the NumPy reference of each operation."""
    shape = np.broadcast(*[np.asarray(v) for v in symbols.values()]).shape
    val: dict[int, np.ndarray] = {}
    with np.errstate(all="ignore"):
        for node in topological_order(root):
            if node.op == "const":
                v = np.full(shape, node.attr)
            elif node.op in ("sym", "param"):  # a runtime parameter is given like a symbol
                name = node.attr if node.op == "sym" else node.attr[0]
                v = np.broadcast_to(np.asarray(symbols[name], dtype=np.float64), shape)
            else:
                v = OPS[node.op].np(node, [val[id(a)] for a in node.args], False)[0]
            val[id(node)] = v
    return val


def _as_ranges(boxes: dict) -> tuple[dict, tuple]:
    out = {}
    for name, (lo, hi) in boxes.items():
        lo, hi = (
            np.atleast_1d(np.asarray(lo, dtype=np.float64)),
            np.atleast_1d(np.asarray(hi, dtype=np.float64)),
        )
        if np.any(lo > hi):
            raise ValueError(f"box of {name!r} has lo > hi")
        out[name] = (lo, hi)
    shape = np.broadcast(*[r[0] for r in out.values()], *[r[1] for r in out.values()]).shape
    return {
        k: (np.broadcast_to(lo, shape), np.broadcast_to(hi, shape)) for k, (lo, hi) in out.items()
    }, shape


def node_bounds(root: Expr, boxes: dict, lipschitz: bool = True) -> dict:
    """Bounds ``id(node) -> (lo, hi)`` of every node of ``root`` over boxes.

    ``boxes`` maps each symbol to ``(lo, hi)``: arrays (or numbers) of equal shape, one entry
    per box. With ``lipschitz`` the interval bound is intersected with the Lipschitz bound
    around each box's centre (see the module docstring).
    """
    ranges, shape = _as_ranges(boxes)
    # Runtime parameters (and time) need ranges like symbols: their values are not constants.
    missing = {
        n.attr if n.op == "sym" else n.attr[0]
        for n in topological_order(root)
        if n.op in ("sym", "param")
    } - set(ranges)
    if missing:
        raise ValueError(f"no range given for symbols or parameters {sorted(missing)}")
    order = topological_order(root)
    if lipschitz:
        centre = node_values(root, {k: 0.5 * (lo + hi) for k, (lo, hi) in ranges.items()})
        with np.errstate(all="ignore"):  # huge ranges: an infinite half-diagonal is sound
            half = np.sqrt(sum((0.5 * (hi - lo)) ** 2 for lo, hi in ranges.values()))
            scale = sum(np.abs(0.5 * (lo + hi)) for lo, hi in ranges.values()) + half
    out: dict[int, tuple] = {}
    lip: dict[int, np.ndarray] = {}
    with np.errstate(all="ignore"):
        for node in order:
            op = node.op
            if op == "const":
                lo = hi = np.full(shape, node.attr)
                L = np.zeros(shape)
            elif op in ("sym", "param"):
                lo, hi = ranges[node.attr if op == "sym" else node.attr[0]]
                L = np.ones(shape)
            else:
                spec = OPS[op]
                alo = [out[id(a)][0] for a in node.args]
                ahi = [out[id(a)][1] for a in node.args]
                lo, hi = spec.interval(node, alo, ahi)
                lo = np.where(np.isnan(lo), -np.inf, lo)
                hi = np.where(np.isnan(hi), np.inf, hi)
                if lipschitz:
                    L = (
                        spec.lipschitz(node, [lip[id(a)] for a in node.args], alo, ahi)
                        if spec.lipschitz is not None
                        else np.full(shape, np.inf)
                    )
                    L = np.where(np.isnan(L), np.inf, L)
                    hint = LIPSCHITZ_RULES.get(node)
                    if hint is not None:
                        L = np.minimum(L, hint)
                    c = centre[id(node)]
                    r = L * half
                    # The centre value and the kernel's values differ by roundings of the
                    # magnitudes involved: a relative margin far below any tile size.
                    m = 1e-10 * (np.abs(c) + r + scale) + 1e-290
                    ok = np.isfinite(c) & np.isfinite(r)
                    lo = np.where(ok, np.maximum(lo, c - r - m), lo)
                    hi = np.where(ok, np.minimum(hi, c + r + m), hi)
            if lipschitz:
                lip[id(node)] = L
            out[id(node)] = (np.asarray(lo, dtype=np.float64), np.asarray(hi, dtype=np.float64))
    return out


def bounds(root: Expr, boxes: dict, lipschitz: bool = True) -> tuple:
    """``(lo, hi)`` of ``root`` over boxes (see :func:`node_bounds`)."""
    return node_bounds(root, boxes, lipschitz)[id(root)]
