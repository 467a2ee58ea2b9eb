"""A NumPy evaluator of scenes: the first answer of a new scene without waiting for numba.

The first call of any cached numba function in a process pays numba's one-time setup (about
0.3 s: it loads every registry of its type system, and imports SciPy's linear algebra when SciPy
is installed), and a new scene's kernel compiles for seconds. This module answers such calls
with NumPy alone: one whole-array operation per node of the expression, the points taken in
blocks that stay in the cache. It is the path of ``backend='numpy'`` and of the first calls of
``backend='auto'`` (see :class:`fastsdf.function.Function`).

The formulas are those of the compiled kernels (:mod:`fastsdf.backends.kernel.codegen`): chains of
``min``/ ``max``/``smin``/``smax`` are flattened, hard ones streamed operand by operand (the earlier
operand wins a tie), smooth ones as a log-sum-exp relative to their extremum (the kernels'
streamed sum, to rounding), ``length`` as ``sqrt(a*a + b*b)`` with the ``hypot`` fallback, the
other operations by the NumPy reference of :mod:`fastsdf.expr.ops`.
Results agree with the kernels to rounding (tested: values 1e-12 relative, gradients 1e-9);
ties between different operands of a chain may pick another (equal-valued) operand's gradient
where the kernels reorder a chain. Non-finite points give NaN for those points only.

**Hard unions of many shapes** (a ``min`` or ``max`` chain with many operands of one shape,
e.g. 1000 boxes at different places, at the root or anywhere below it) are evaluated with
pruning: the operands of the same shape are evaluated together with their constants as
columns (one array operation per node of the shape, over all operands at once), and a
quadtree of tiles over the points' bounding box keeps, per tile, only the operands that can be
the minimum there (sound bounds from each operand's value at the tile's centre and its
Lipschitz constant, or interval arithmetic where none is known; an operand whose lower bound
exceeds the smallest upper bound cannot win, so the result is bit-identical to evaluating
every operand). Each point then evaluates the few survivors of its tile (values only), and
the gradient only of the winner.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from fastsdf.expr.graph import Expr
from fastsdf.expr.ops import OPS

__all__ = ["NumpyScene", "compile_numpy", "BLOCK"]

#: Points per block of the general path: a few arrays of this size stay in the L2 cache.
BLOCK = 16384

_CHAINS = ("min", "max", "smin", "smax")
#: Cost model (seconds) of :meth:`NumpyScene.cost`.
PER_NODE_POINT = 4e-9
PER_NODE_CALL = 5e-6
PER_PRUNED_NODE_POINT = 60e-9
#: A hard chain with at least this many operands of one shape is evaluated with pruning.
GROUP_MIN = 24
#: Operands of more nodes are never taken for a shape (they are evaluated as they are).
MAX_SHAPE_NODES = 400


# ---------------------------------------------------------------------------------------------
# Linear programs: the nodes of an expression in evaluation order, chains flattened.


def _flatten(node: Expr) -> list:
    """Operands of the maximal chain of ``node``'s operation (same op and k), left to right."""
    out, stack = [], [node]
    op, attr = node.op, node.attr
    while stack:
        n = stack.pop()
        if n.op == op and n.attr == attr:
            stack.extend(reversed(n.args))
        else:
            out.append(n)
    return out


def _kids(node: Expr) -> Sequence[Expr]:
    return _flatten(node) if node.op in _CHAINS else node.args


def _linearize(root: Expr, slots: bool = False, leaf: Callable | None = None) -> tuple[list, list]:
    """``(steps, consts)``: ``steps[i] = (node, refs)`` in evaluation order, each ref
    ``('n', i)`` (the value of step i) or ``('c', j)`` (constant j: ``consts[j]``, one per
    occurrence when ``slots``, else one per distinct constant node). ``leaf(node, kids)``, if
    given, may claim a node: it becomes a step without references (evaluated by the claimer)
    and nothing below it is visited."""
    index: dict = {}
    cindex: dict = {}
    steps: list[tuple] = []
    consts: list = []
    stack: list[tuple] = [(root, None)]
    while stack:
        node, kids = stack.pop()
        if id(node) in index:
            continue
        if kids is None:
            kids = _kids(node)
            if leaf is not None and leaf(node, kids):
                index[id(node)] = len(steps)
                steps.append((node, ()))
                continue
            stack.append((node, kids))
            for a in reversed(kids):
                if a.op != "const" and id(a) not in index:
                    stack.append((a, None))
            continue
        refs = []
        for a in kids:
            if a.op == "const":
                if slots:
                    refs.append(("c", len(consts)))
                    consts.append(a.attr)
                else:
                    j = cindex.get(id(a))
                    if j is None:
                        j = cindex[id(a)] = len(consts)
                        consts.append(a.attr)
                    refs.append(("c", j))
            else:
                refs.append(("n", index[id(a)]))
        index[id(node)] = len(steps)
        steps.append((node, tuple(refs)))
    return steps, consts


class _Program:
    """A linearized expression: per step the operation, attribute, operand references and the
    step after which its value is dead (values are freed as soon as possible).

    With ``prune``, every hard ``min``/``max`` chain with many operands of one shape (anywhere
    in the expression, see :class:`_Chain`) is one step, evaluated with pruning."""

    def __init__(self, root: Expr, xname: str, slots: bool = False, prune: bool = False):
        self.xname = xname
        found: dict = {}

        def claim(node, kids):
            if node.op not in ("min", "max") or len(kids) < GROUP_MIN:
                return False
            chain = _Chain(node, kids, xname)
            if chain.useful:
                found[id(node)] = chain
            return chain.useful

        steps, consts = _linearize(root, slots, claim if prune else None)
        self.steps = steps
        self.consts = consts
        self.nodes = [s[0] for s in steps]
        #: step index -> the pruned chain it evaluates
        self.chains = {i: found[id(n)] for i, n in enumerate(self.nodes) if id(n) in found}
        last = list(range(len(steps)))
        for i, (_, refs) in enumerate(steps):
            for kind, j in refs:
                if kind == "n":
                    last[j] = i
        last[-1] = len(steps)
        self.free: list[list[int]] = [[] for _ in steps]
        for j, i in enumerate(last):
            if i < len(steps):
                self.free[i].append(j)
        self.has_prim = any(n.op == "prim" for n in self.nodes)
        self.ellipse = any(n.op == "prim" and n.attr[0] != "polygon" for n in self.nodes) or any(
            c.ellipse for c in self.chains.values()
        )

    @property
    def size(self) -> int:
        """Nodes evaluated per point without pruning."""
        return len(self.steps) - len(self.chains) + sum(c.size for c in self.chains.values())

    def run(
        self,
        x: Any,
        y: Any,
        consts: Sequence,
        grad: bool,
        params: dict | None = None,
        prune: bool = True,
    ) -> tuple[Any, Any]:
        """Value (and gradient ``[gx, gy]``, each an array, a float or None for zero) at the
        points ``x, y`` (arrays of equal shape, or anything that broadcasts); ``consts[j]`` is
        constant j (a float, or an array over the points)."""
        ctx = (self.xname, params)
        vals: list = [None] * len(self.steps)
        grads: list = [None] * len(self.steps)
        chains = self.chains
        for i, (node, refs) in enumerate(self.steps):
            if i in chains:
                vals[i], grads[i] = chains[i].evaluate(x, y, grad, params, prune)
            else:
                av = [vals[j] if k == "n" else consts[j] for k, j in refs]
                ag = [grads[j] if k == "n" else _ZERO for k, j in refs] if grad else None
                vals[i], grads[i] = _OPS.get(node.op, _generic)(node, av, ag, x, y, ctx)
            for j in self.free[i]:
                vals[j] = grads[j] = None
        return vals[-1], grads[-1]


def _data_key(data):
    return data if isinstance(data, (tuple, str, int, float, type(None))) else id(data)


# ---------------------------------------------------------------------------------------------
# Operations: ``fn(node, av, ag, x, y, ctx) -> (value, gradient)``. A gradient is a pair of
# components, each an array, a float, or None (known zero); ``ag`` is None for value only;
# ``ctx`` is ``(name of the x symbol, parameter values or None)``.

_ZERO = (None, None)


def _sc(g, f):
    """Component ``g`` times ``f`` (None stays None)."""
    return None if g is None else g * f


def _add_c(a, b):
    if a is None:
        return b
    if b is None:
        return a
    return a + b


def _sub_c(a, b):
    if b is None:
        return a
    if a is None:
        return -b
    return a - b


def _op_sym(node, av, ag, x, y, ctx):
    isx = node.attr == ctx[0]
    return (x if isx else y), (((1.0, None) if isx else (None, 1.0)) if ag is not None else None)


def _op_add(node, av, ag, x, y, ctx):
    v = av[0] + av[1]
    if ag is None:
        return v, None
    return v, (_add_c(ag[0][0], ag[1][0]), _add_c(ag[0][1], ag[1][1]))


def _op_sub(node, av, ag, x, y, ctx):
    v = av[0] - av[1]
    if ag is None:
        return v, None
    return v, (_sub_c(ag[0][0], ag[1][0]), _sub_c(ag[0][1], ag[1][1]))


def _op_mul(node, av, ag, x, y, ctx):
    a, b = av
    v = a * b
    if ag is None:
        return v, None
    (ax, ay), (bx, by) = ag
    return v, (_add_c(_sc(ax, b), _sc(bx, a)), _add_c(_sc(ay, b), _sc(by, a)))


def _op_div(node, av, ag, x, y, ctx):
    a, b = av
    v = a / b
    if ag is None:
        return v, None
    ib = 1.0 / b
    pb = -v * ib
    (ax, ay), (bx, by) = ag
    return v, (_add_c(_sc(ax, ib), _sc(bx, pb)), _add_c(_sc(ay, ib), _sc(by, pb)))


def _op_neg(node, av, ag, x, y, ctx):
    v = -av[0]
    if ag is None:
        return v, None
    return v, (_sc(ag[0][0], -1.0), _sc(ag[0][1], -1.0))


def _op_abs(node, av, ag, x, y, ctx):
    a = av[0]
    v = np.abs(a)
    if ag is None:
        return v, None
    s = np.where(a >= 0.0, 1.0, -1.0)
    return v, (_sc(ag[0][0], s), _sc(ag[0][1], s))


def _pick(w, gb, ga):
    """Component: ``gb`` where ``w``, else ``ga`` (None: zero)."""
    if gb is None and ga is None:
        return None
    return np.where(w, 0.0 if gb is None else gb, 0.0 if ga is None else ga)


def _op_hard(node, av, ag, x, y, ctx):
    """A min/max chain streamed in order: strict comparison, the earlier operand wins ties."""
    less = node.op == "min"
    m = av[0]
    g = ag[0] if ag is not None else None
    for j in range(1, len(av)):
        v = av[j]
        w = (v < m) if less else (v > m)
        if g is not None:
            g = (_pick(w, ag[j][0], g[0]), _pick(w, ag[j][1], g[1]))
        m = np.where(w, v, m)
    return m, g


def _op_smooth(node, av, ag, x, y, ctx):
    """An exponential smooth chain as a log-sum-exp relative to its extremum ``m``: ``m -+
    log(sum exp(-k |a_i - m|)) / k``, the gradient the weighted mean of the operands'. The
    kernels stream the same sum operand by operand (rescaling when the extremum changes): the
    same value to rounding, with half the array operations here."""
    less = node.op == "smin"
    k = node.attr
    m = av[0]
    for v in av[1:]:
        m = np.minimum(m, v) if less else np.maximum(m, v)
    s = 0.0
    gx = gy = None
    for j, v in enumerate(av):
        e = np.exp(np.abs(v - m) * -k)
        s = s + e
        if ag is not None:
            gx = _add_c(gx, _sc(ag[j][0], e))
            gy = _add_c(gy, _sc(ag[j][1], e))
    ls = np.log(s) * (1.0 / k)
    v = m - ls if less else m + ls
    if ag is None:
        return v, None
    si = 1.0 / s
    return v, (_sc(gx, si), _sc(gy, si))


_UP = 2.0**600


def _op_length(node, av, ag, x, y, ctx):
    a, b = av
    v = np.sqrt(a * a + b * b)
    # The kernels' rare branch (see fastsdf.expr.ops._emit_length), on the points that take it.
    bad = np.flatnonzero(~((v > 1e-150) & (v < 1e150)))
    if ag is None:
        if len(bad):
            a, b = np.broadcast_arrays(a, b)
            v[bad] = np.hypot(a[bad], b[bad])
        return v, None
    ri = 1.0 / v
    p, q = a * ri, b * ri
    if len(bad):
        a, b, p, q = np.broadcast_arrays(a, b, p, q)
        p, q = p.copy(), q.copy()
        ab, bb = a[bad], b[bad]
        hv = np.hypot(ab, bb)
        v[bad] = hv
        sc = np.where(hv < 1e-150, _UP, 1.0)
        pp, qq = ab * sc, bb * sc
        h = np.hypot(pp, qq)
        pos = h > 0.0
        hs = np.where(pos, h, 1.0)
        p[bad] = np.where(pos, pp / hs, 1.0)
        q[bad] = np.where(pos, qq / hs, 0.0)
    (ax, ay), (bx, by) = ag
    return v, (_add_c(_sc(ax, p), _sc(bx, q)), _add_c(_sc(ay, p), _sc(by, q)))


def _op_select(node, av, ag, x, y, ctx):
    pick = av[0] > 0.0
    v = np.where(pick, av[1], av[2])
    if ag is None:
        return v, None
    return v, (_pick(pick, ag[1][0], ag[2][0]), _pick(pick, ag[1][1], ag[2][1]))


def _op_param(node, av, ag, x, y, ctx):
    name, default = node.attr
    v = float((ctx[1] or {}).get(name, default))
    return v, (_ZERO if ag is not None else None)


def _generic(node, av, ag, x, y, ctx):
    """Any other operation by its NumPy reference (:mod:`fastsdf.expr.ops`)."""
    shape = np.broadcast(x, y).shape
    args = [np.broadcast_to(np.asarray(a, dtype=np.float64), shape) for a in av]
    v, rule = OPS[node.op].np(node, args, ag is not None)
    if ag is None:
        return v, None
    comps = []
    for c in (0, 1):
        gs = [a[c] for a in ag]
        if callable(rule):
            if all(gi is None for gi in gs):
                comps.append(None)
                continue
            comps.append(
                rule(
                    [
                        np.zeros(shape)
                        if gi is None
                        else np.broadcast_to(np.asarray(gi, dtype=np.float64), shape)
                        for gi in gs
                    ]
                )
            )
            continue
        acc = None
        for p, gi in zip(rule, gs):
            if p is not None and gi is not None:
                acc = _add_c(acc, p * gi)
        comps.append(acc)
    return v, tuple(comps)


_OPS = {
    "sym": _op_sym,
    "add": _op_add,
    "sub": _op_sub,
    "mul": _op_mul,
    "div": _op_div,
    "neg": _op_neg,
    "abs": _op_abs,
    "min": _op_hard,
    "max": _op_hard,
    "smin": _op_smooth,
    "smax": _op_smooth,
    "length": _op_length,
    "select": _op_select,
    "param": _op_param,
}


def _full(v, n):
    return np.broadcast_to(np.asarray(v if v is not None else 0.0, dtype=np.float64), (n,))


# ---------------------------------------------------------------------------------------------
# Pruned evaluation of a root chain with many operands of one shape.


class _Group:
    """Operands of one shape: the shape's program (constants as slots) and their constants as
    a table, one row per member (chain positions ``pos``)."""

    def __init__(self, prog: _Program, pos: list, rows: list, lip: float | None):
        self.prog = prog
        self.pos = np.asarray(pos, dtype=np.int64)
        table = np.asarray(rows, dtype=np.float64).reshape(len(rows), -1)
        # Columns equal in every member are passed as numbers (bitwise equal: keeps -0.0);
        # the others as contiguous columns, gathered per pair.
        self.cols: list = []
        bits = table.view(np.int64)
        for j in range(table.shape[1]):
            if np.all(bits[:, j] == bits[0, j]):
                self.cols.append(float(table[0, j]))
            else:
                self.cols.append(np.ascontiguousarray(table[:, j]))
        self.lip = lip

    def consts(self, members: np.ndarray | None) -> list:
        """Constant slots for the rows ``members`` (arrays) or, if None, for every member."""
        if members is None:
            return self.cols
        return [c if isinstance(c, float) else c.take(members) for c in self.cols]


def _matcher(prog: _Program) -> Callable:
    """A function ``operand -> constants or None``: the operand's constants if it has the
    shape of ``prog`` (a program with constant slots), else None.

    It follows the program's references from the root, and is generated as straight-line
    Python for the shape (one test per node and argument: matching thousands of operands is
    on the path of the first answer)."""
    steps = prog.steps
    last = len(steps) - 1
    leaves = [node if node.op in ("sym", "param") else None for node, _ in steps]
    attrs = [node.attr for node, _ in steps]
    if leaves[last] is not None:
        return lambda operand: [] if operand is leaves[last] else None
    body, known, slots = [], {last}, {}
    for i in range(last, -1, -1):
        node, refs = steps[i]
        if leaves[i] is not None:
            continue
        same = "is not None" if node.attr is None else f"!= A[{i}]"
        body.append(f"if n{i}.op != {node.op!r} or n{i}.attr {same}: return None")
        body.append(f"k = n{i}.args")
        if node.op in _CHAINS:  # a chain nested in its own kind flattens as the program did
            body += [
                "for a in k:",
                f"    if a.op == {node.op!r} and a.attr == A[{i}]:",
                f"        k = F(n{i})",
                "        break",
            ]
        body.append(f"if len(k) != {len(refs)}: return None")
        for pos, (kind, j) in enumerate(refs):
            if kind == "c":
                slots[j] = f"c{j}"
                body.append(f"c{j} = k[{pos}]")
                body.append(f"if c{j}.op != 'const': return None")
            elif leaves[j] is not None:
                body.append(f"if k[{pos}] is not L[{j}]: return None")
            elif j in known:
                body.append(f"if k[{pos}] is not n{j}: return None")
            else:
                known.add(j)
                body.append(f"n{j} = k[{pos}]")  # its operation is tested at its own step
    consts = ", ".join(f"{slots[j]}.attr" for j in range(len(prog.consts)))
    body.append(f"return [{consts}]")
    src = f"def match(n{last}):\n" + "\n".join("    " + line for line in body) + "\n"
    env = {"A": attrs, "L": leaves, "F": _flatten}
    exec(compile(src, "<fastsdf.backends.npeval matcher>", "exec"), env)
    fn = env["match"]

    def match(operand):
        try:
            return fn(operand)
        except (ValueError, TypeError):  # attributes that do not compare (array data)
            return None

    return match


class _Chain:
    """A hard ``min``/``max`` chain: groups of same-shape operands (pruned, each of at least
    :data:`GROUP_MIN`) and the other operands; ``useful`` says whether any group exists."""

    def __init__(self, root: Expr, operands: list, xname: str):
        from fastsdf.expr.interval import LIPSCHITZ_RULES

        self.op = root.op
        self.n = len(operands)
        groups: list = []  # [prog, match, pos, rows, lips]
        by_key: dict = {}  # candidates by the operations of the root and its arguments
        others = []
        for p, operand in enumerate(operands):
            if operand.op == "const" or getattr(operand, "tree", 0) > 4 * MAX_SHAPE_NODES:
                others.append((p, operand))  # a constant, or a large rest of the scene
                continue
            key = (operand.op, tuple(a.op for a in operand.args))
            cands = by_key.setdefault(key, [])
            hit = None
            for g in cands:
                c = g[1](operand)
                if c is not None:
                    hit = (g, c)
                    break
            if hit is None:
                prog = _Program(operand, xname, slots=True)
                if len(prog.steps) > MAX_SHAPE_NODES or prog.has_prim:
                    others.append((p, operand))
                    continue
                g = [prog, _matcher(prog), [], [], []]
                groups.append(g)
                cands.append(g)
                hit = (g, list(prog.consts))
            g, c = hit
            g[2].append(p)
            g[3].append(c)
            # A Lipschitz constant noted by the modelling layer (a negated SDF keeps it).
            g[4].append(LIPSCHITZ_RULES.get(operand.args[0] if operand.op == "neg" else operand))
        self.groups = []
        if not any(len(g[2]) >= GROUP_MIN for g in groups):
            self.others = []  # nothing to prune: the caller evaluates the chain as it is
            return
        for prog, _, pos, rows, lips in groups:
            if len(pos) >= GROUP_MIN:
                lip = None if any(L is None for L in lips) else max(lips)
                self.groups.append(_Group(prog, pos, rows, lip))
            else:
                others.extend((p, operands[p]) for p in pos)
        others.sort(key=lambda t: t[0])
        self.others = [
            (p, _Program(o, xname, prune=True)) if o.op != "const" else (p, float(o.attr))
            for p, o in others
        ]
        self.ellipse = any(not isinstance(q, float) and q.ellipse for _, q in self.others)

    @property
    def size(self) -> int:
        """Nodes evaluated per point without pruning."""
        return sum(len(g.prog.steps) * len(g.pos) for g in self.groups) + sum(
            1 if isinstance(q, float) else q.size for _, q in self.others
        )

    def cost(self, n: int) -> float:
        """Estimated seconds for ``n`` points (see :meth:`NumpyScene.cost`)."""
        return sum(
            len(g.prog.steps) * (PER_PRUNED_NODE_POINT * n + 2e-6 * len(g.pos)) for g in self.groups
        ) + sum(_general_cost(q, n) for _, q in self.others if not isinstance(q, float))

    def evaluate(
        self, xs: Any, ys: Any, grad: bool, params: dict | None, prune: bool = True
    ) -> tuple[Any, Any]:
        """Value and gradient (components: arrays, floats or None) at the points: each group's
        extremum (pruned), then every operand in chain order, streamed with the kernels' tie
        rule (the earlier operand wins)."""
        xs, ys = np.broadcast_arrays(
            np.asarray(xs, dtype=np.float64), np.asarray(ys, dtype=np.float64)
        )
        sign = 1.0 if self.op == "min" else -1.0
        parts = []  # (chain position, value, gradient)
        for grp in self.groups:
            v, gg, pos = _eval_group(grp, sign, xs, ys, grad, prune)
            parts.append((pos, v, gg))
        for p, prog in self.others:
            if isinstance(prog, float):
                parts.append((np.full(len(xs), p), prog, _ZERO))
                continue
            v, gg = prog.run(xs, ys, prog.consts, grad, params, prune)
            parts.append((np.full(len(xs), p), v, gg))
        m: Any = None
        mg: Any = None
        mp: Any = None
        for pos, v, gg in parts:
            v = np.broadcast_to(v, xs.shape)
            if m is None:
                m, mp, mg = v, pos, gg
                continue
            key_v, key_m = (v, m) if sign > 0 else (-v, -m)
            w = (key_v < key_m) | ((key_v == key_m) & (pos < mp))
            if grad:
                mg = (_pick(w, gg[0], mg[0]), _pick(w, gg[1], mg[1]))
            m = np.where(w, v, m)
            mp = np.where(w, pos, mp)
        return m, (mg if grad else None)

    @property
    def useful(self) -> bool:
        return bool(self.groups)


def _group_bounds(
    group: _Group,
    members: np.ndarray | None,
    cx: np.ndarray,
    cy: np.ndarray,
    hx: np.ndarray,
    hy: np.ndarray,
    scale: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """Sound bounds ``(lo, hi)`` of the members ``members`` over the tiles of centres ``cx,
    cy`` (arrays over the pairs) and half-sizes ``hx, hy``."""
    half = math.hypot(hx, hy)
    v, _ = group.prog.run(cx, cy, group.consts(members), False)
    v = np.broadcast_to(v, cx.shape)
    if group.lip is not None:
        r = group.lip * half
        m = 1e-10 * (np.abs(v) + r + scale) + 1e-290
        lo, hi = v - r - m, v + r + m
        bad = ~np.isfinite(v)
        if bad.any():
            lo = np.where(bad, -np.inf, lo)
            hi = np.where(bad, np.inf, hi)
        return lo, hi
    return _interval_bounds(group, members, cx, cy, hx, hy)


def _interval_bounds(
    group: _Group,
    members: np.ndarray | None,
    cx: np.ndarray,
    cy: np.ndarray,
    hx: np.ndarray,
    hy: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """Interval arithmetic over the shape's program (the rules of :mod:`fastsdf.expr.ops`) for the
    tiles ``[cx - hx, cx + hx] x [cy - hy, cy + hy]`` (``hx, hy`` include a sliver)."""
    consts = group.consts(members)
    lo_s: list = []
    hi_s: list = []
    with np.errstate(all="ignore"):
        for node, refs in group.prog.steps:
            if node.op == "sym":
                isx = node.attr == group.prog.xname
                c, h = (cx, hx) if isx else (cy, hy)
                lo, hi = c - h, c + h
            else:
                alo = [lo_s[j] if k == "n" else np.asarray(consts[j]) for k, j in refs]
                ahi = [hi_s[j] if k == "n" else np.asarray(consts[j]) for k, j in refs]
                rule = OPS[node.op].interval
                lo, hi = rule(node, alo[:2], ahi[:2])
                for j in range(2, len(refs)):  # a flattened chain, pairwise
                    lo, hi = rule(node, [lo, alo[j]], [hi, ahi[j]])
                lo = np.where(np.isnan(lo), -np.inf, lo)
                hi = np.where(np.isnan(hi), np.inf, hi)
            lo_s.append(lo)
            hi_s.append(hi)
    return np.broadcast_to(lo_s[-1], cx.shape), np.broadcast_to(hi_s[-1], cx.shape)


def _seg_first_min(v, starts, counts):
    """Per segment (``starts``, ``counts`` > 0) of ``v``: the index of its first minimum
    (NaN values never win unless the segment has nothing else)."""
    key = np.where(np.isnan(v), np.inf, v)
    mins = np.minimum.reduceat(key, starts)
    idx = np.arange(len(v))
    hit = np.where(key == np.repeat(mins, counts), idx, len(v))
    return np.minimum.reduceat(hit, starts)


def _spread(v):
    """The bits of ``v`` (< 256) spread to the even bit positions (Morton order)."""
    v = (v | (v << 4)) & 0x0F0F
    v = (v | (v << 2)) & 0x3333
    return (v | (v << 1)) & 0x5555


def _runs(codes):
    """For sorted ``codes``: the index of the first element of each run of equal codes."""
    if not len(codes):
        return np.zeros(0, dtype=np.int64)
    return np.flatnonzero(np.concatenate(([True], codes[1:] != codes[:-1])))


def _prune(
    group: _Group, sign: float, xs: np.ndarray, ys: np.ndarray, bounds: tuple, splits: Sequence[int]
) -> tuple:
    """Leaf tiles of the points and the surviving members per leaf: ``(leaf of each point,
    offsets, act)``: leaf ``t``'s members are ``act[offs[t]:offs[t + 1]]``, in chain order.

    The tiles are refined level by level (``splits``: children per side at each level, powers
    of two) and only where there are points; each level bounds the members its parent kept.
    Tiles are numbered in Morton order, so that each level's tiles, sorted, list their
    children next to each other and their parents in the previous level's order."""
    (x0, x1), (y0, y1) = bounds
    M = len(group.pos)
    scale = abs(x0) + abs(x1) + abs(y0) + abs(y1)
    nx = int(np.prod(splits))
    tx = np.clip(((xs - x0) * (nx / (x1 - x0))).astype(np.int64), 0, nx - 1)
    ty = np.clip(((ys - y0) * (nx / (y1 - y0))).astype(np.int64), 0, nx - 1)
    code = _spread(tx) | (_spread(ty) << 1)
    # 16-bit codes (nx <= 256) sort by radix
    order = np.argsort(code.astype(np.uint16) if nx <= 256 else code, kind="stable")
    sc = code[order]
    first = _runs(sc)  # the occupied leaves, in Morton order
    leaf_of_sorted = np.cumsum(np.concatenate(([0], sc[1:] != sc[:-1])))
    leaf = np.empty(len(xs), dtype=np.int64)
    leaf[order] = leaf_of_sorted
    leaves = sc[first]
    ltx, lty = tx[order[first]], ty[order[first]]
    # Level 0: one tile, every member.
    offs = np.array([0, M], dtype=np.int64)
    act = np.arange(M, dtype=np.int64)
    n = 1
    prev_codes = np.zeros(1, dtype=np.int64)
    for f in splits:
        n *= f
        shift = nx // n  # leaves per tile side at this level
        bits = 2 * (shift.bit_length() - 1)
        lc = leaves >> bits
        heads = _runs(lc)  # this level's occupied tiles
        codes = lc[heads]
        pbits = 2 * (f.bit_length() - 1)
        parent_codes = codes >> pbits
        # parents are the previous level's tiles, in the same (sorted) order
        ppos = np.searchsorted(prev_codes, parent_codes)
        counts = offs[ppos + 1] - offs[ppos]
        P = int(counts.sum())
        T = len(codes)
        pair_tile = np.repeat(np.arange(T), counts)
        starts = np.zeros(T, dtype=np.int64)
        np.cumsum(counts[:-1], out=starts[1:])
        within = np.arange(P) - np.repeat(starts, counts)
        members = act[np.repeat(offs[ppos], counts) + within]
        w, h = (x1 - x0) / n, (y1 - y0) / n
        cx = x0 + ((ltx[heads] // shift) + 0.5) * w
        cy = y0 + ((lty[heads] // shift) + 0.5) * h
        # half-sizes with a sliver: a point binned across a rounding edge is still inside
        hx, hy = 0.5 * w * (1.0 + 1e-9), 0.5 * h * (1.0 + 1e-9)
        lo, hi = _group_bounds(group, members, cx[pair_tile], cy[pair_tile], hx, hy, scale)
        if sign < 0:
            lo, hi = -hi, -lo
        H = np.minimum.reduceat(hi, starts)
        # Strictly above the smallest upper bound: never the extremum (nor tied with it).
        keep = ~(lo > np.repeat(H, counts))
        kc = np.add.reduceat(keep.astype(np.int64), starts)
        act = members[keep]
        offs = np.zeros(T + 1, dtype=np.int64)
        np.cumsum(kc, out=offs[1:])
        prev_codes = codes
    return leaf, offs, act


def _splits(npts: int) -> list:
    """Refinement per level: 4 x 4 first, then halving the tiles down to leaves of about
    ``LEAF_POINTS`` points (at most 256 x 256)."""
    out, n = [4], 4
    while n < 256 and npts / (4 * n * n) >= LEAF_POINTS:
        out.append(2)
        n *= 2
    return out


#: Points per leaf tile that the refinement aims at.
LEAF_POINTS = 4


def _snap(xs, ys):
    """A rectangle holding the points (widened by a sliver), or None where its size is not
    finite (coordinates near the float range: such calls are not pruned)."""
    out = []
    for v in (xs, ys):
        lo, hi = float(v.min()), float(v.max())
        span = max(hi - lo, 1e-9 * max(abs(lo), abs(hi)), 1e-200)
        a, b = lo - 1e-3 * span, hi + 1e-3 * span  # strictly around the points
        if not (math.isfinite(b - a) and abs(a) < 1e300 and abs(b) < 1e300):
            return None
        out.append((a, b))
    return tuple(out)


def _eval_group(
    group: _Group, sign: float, xs: np.ndarray, ys: np.ndarray, grad: bool, prune: bool
) -> tuple:
    """The extremum over the group's members at finite points: value, gradient and the chain
    position of the winner per point."""
    n = len(xs)
    M = len(group.pos)
    bounds = _snap(xs, ys) if prune and n else None
    if bounds is not None:
        tile, offs, act = _prune(group, sign, xs, ys, bounds, _splits(n))
        counts = (offs[1:] - offs[:-1])[tile]
        starts_t = offs[:-1][tile]
    else:
        counts = np.full(n, M, dtype=np.int64)
        starts_t = np.zeros(n, dtype=np.int64)
        act = np.arange(M, dtype=np.int64)
    best = np.empty(n, dtype=np.int64)
    # pairs in chunks of points (memory: pairs x a few arrays)
    chunk = max(1, int(4_000_000 // max(1, int(counts.mean()) if n else 1)))
    for a in range(0, n, chunk):
        b = min(n, a + chunk)
        c = counts[a:b]
        P = int(c.sum())
        seg = np.zeros(b - a, dtype=np.int64)
        np.cumsum(c[:-1], out=seg[1:])
        pt = np.repeat(np.arange(a, b), c)
        within = np.arange(P) - np.repeat(seg, c)
        mem = act[np.repeat(starts_t[a:b], c) + within]
        v, _ = group.prog.run(xs[pt], ys[pt], group.consts(mem), False)
        v = np.broadcast_to(v, (P,))
        first = _seg_first_min(sign * v if sign < 0 else v, seg, c)
        best[a:b] = mem[np.minimum(first, P - 1)]
    v, g = group.prog.run(xs, ys, group.consts(best), grad)
    return np.broadcast_to(v, (n,)), g, group.pos[best]


def _general_cost(prog: _Program, n: int) -> float:
    """Estimated seconds of ``prog`` on ``n`` points (see :meth:`NumpyScene.cost`)."""
    steps = len(prog.steps) - len(prog.chains)
    per = PER_NODE_POINT + (5e-6 if prog.ellipse else 0.0)
    return steps * (PER_NODE_CALL * (n // BLOCK + 1) + per * n) + sum(
        c.cost(n) for c in prog.chains.values()
    )


# ---------------------------------------------------------------------------------------------


class NumpyScene:
    """The NumPy evaluator of one expression of two coordinates (see the module docstring).

    ``scene(x, y)`` returns the value (distance, negative inside) as float64 with ``x``'s shape
    (a scalar gives shape ``(1,)``); ``scene(x, y, compute_gradient=True)`` returns ``(d,
    grad)`` with ``grad[..., 0] = dd/dx``. ``params`` gives runtime parameter values by name
    (the others take their defaults). ``prune=False`` evaluates every operand of a pruned
    chain (the same bits, slower).

    :meth:`cost` estimates the seconds of a call; ``'auto'`` compares it with the tape's.
    """

    def __init__(self, expr: Expr, symbol_names: Sequence[str]):
        names = tuple(symbol_names)
        if len(names) != 2:
            raise ValueError(f"symbol_names must name two symbols, got {symbol_names!r}")
        self.expr = expr
        self.xname = names[0]
        self._prog = _Program(expr, self.xname, prune=True)

    @property
    def chain(self) -> _Chain | None:
        """The pruned chain at the root (None if the root is not one)."""
        return self._prog.chains.get(len(self._prog.steps) - 1)

    @property
    def pruned(self) -> bool:
        """Whether some chain is evaluated with pruning (at the root or below it)."""
        return bool(self._prog.chains)

    @property
    def nodes(self) -> int:
        """Nodes of the programs evaluated per point (a pruned chain's shapes counted once)."""

        def count(prog):
            return (
                len(prog.steps)
                - len(prog.chains)
                + sum(
                    sum(len(g.prog.steps) for g in c.groups)
                    + sum(1 if isinstance(q, float) else count(q) for _, q in c.others)
                    for c in prog.chains.values()
                )
            )

        return count(self._prog)

    @property
    def size(self) -> int:
        """Nodes evaluated per point without pruning (the scene's size)."""
        return self._prog.size

    @property
    def has_ellipse(self) -> bool:
        """Whether an ellipse primitive is evaluated (its NumPy reference is slow)."""
        return self._prog.ellipse

    def cost(self, n: int) -> float:
        """An estimate of the seconds a call on ``n`` points takes, value + gradient (from
        ``python -m bench.bench_tape`` on a 2-core AMD EPYC: about 4 ns per node and point, an
        ellipse primitive far more; a pruned chain about 60 ns per node of its shape and
        point, with a few survivors per point)."""
        return _general_cost(self._prog, n)

    def run(
        self,
        xs: np.ndarray,
        ys: np.ndarray,
        out: np.ndarray,
        grad: np.ndarray | None = None,
        params: dict | None = None,
        prune: bool = True,
    ) -> None:
        """Evaluate at flat float64 points into ``out`` (and ``grad``, shape (n, 2))."""
        ok = np.isfinite(xs) & np.isfinite(ys)
        allok = bool(ok.all())
        if not allok:
            xs, ys = xs[ok], ys[ok]
        m = xs.shape[0]
        d = np.empty(m)
        g = np.empty((m, 2)) if grad is not None else None
        prog = self._prog
        # Blocks that stay in the cache; a program with pruned chains runs on all points at
        # once (pruning sorts the points into tiles of the whole set).
        block = max(m, 1) if prog.chains else BLOCK
        with np.errstate(all="ignore"):
            for a in range(0, m, block):
                b = min(m, a + block)
                v, gg = prog.run(xs[a:b], ys[a:b], prog.consts, g is not None, params, prune)
                d[a:b] = v
                if g is not None:
                    g[a:b, 0] = 0.0 if gg[0] is None else gg[0]
                    g[a:b, 1] = 0.0 if gg[1] is None else gg[1]
        if allok:
            out[:] = d
            if grad is not None:
                grad[:] = g
            return
        out[:] = np.nan
        out[ok] = d
        if grad is not None:
            grad[:] = np.nan
            grad[ok] = g

    def __call__(
        self,
        x: ArrayLike,
        y: ArrayLike,
        compute_gradient: bool = False,
        params: dict | None = None,
        prune: bool = True,
    ) -> np.ndarray | tuple[np.ndarray, np.ndarray]:
        from fastsdf.expr.points import as_points

        xs, ys, shape = as_points(x, y)
        n = xs.shape[0]
        out = np.empty(n)
        if compute_gradient:
            grad = np.empty((n, 2))
            self.run(xs, ys, out, grad, params, prune)
            return out.reshape(shape), grad.reshape(shape + (2,))
        self.run(xs, ys, out, None, params, prune)
        return out.reshape(shape)


def compile_numpy(expr: Expr, symbol_names: Sequence[str]) -> NumpyScene:
    """The :class:`NumpyScene` of ``expr`` over the two named coordinate symbols (x, y)."""
    return NumpyScene(expr, symbol_names)
