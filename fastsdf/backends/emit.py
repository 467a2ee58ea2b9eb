"""The emitter: a :class:`fastsdf.backends.lower.Program` becomes statements
(:mod:`fastsdf.backends.code`) of the per-point code of one kind: the value (``'v'``), the value
and gradient (``'vg'``), or those and the time derivative (``'vgt'``).

Operations come from the op table (:mod:`fastsdf.expr.ops`, each entry's ``emit``); the emitter
applies their gradient rules to every component alike (forward mode, one component per
coordinate and one for time) and writes the n-ary chains itself. Straight-line code is in SSA
form (every variable assigned once, except the accumulators carried through a loop over a
table): numba repairs each reassigned variable with a pass over the whole function, which made
compile time quadratic in the length of a scene. A smooth chain is an online log-sum-exp (the
streaming-softmax recurrence): one ``exp`` per operand and one ``log`` per chain, with values
that never overflow for any ``k > 0``; mathematically the notebook's nested
``-log(exp(-k a) + exp(-k b)) / k``.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from fastsdf.backends.code import (
    Assign,
    Code,
    Length,
    Loop,
    Store,
    call,
    const,
    fold_entry,
    num,
    read,
    table,
    var,
)
from fastsdf.backends.lower import Chain, FoldPlan, Program
from fastsdf.expr.graph import Expr
from fastsdf.expr.ops import OPS

__all__ = [
    "Body",
    "Emitter",
    "Val",
    "Writer",
    "KIND_COMPONENTS",
    "chain_step",
    "chain_finish",
    "flagged",
]

_HUGE = 1.7976931348623157e308
#: The emitted names of the coordinates (the generated functions' arguments, and the suffixes
#: of gradient variables: ``v3x`` is dv3/dx).
_AXES = ("x", "y", "z")


def KIND_COMPONENTS(program: Program, kind: str) -> tuple:
    """The gradient components a kind of function carries: one per coordinate, and time for
    ``'vgt'``."""
    return _AXES[: program.ncomp] + (("t",) if kind == "vgt" else ())


class Val:
    """An emitted value: expressions for the value ``v`` and the gradient components ``g``
    (one per component; None is known to be zero; ``g`` None: all zero)."""

    __slots__ = ("v", "g")

    def __init__(self, v: Code, g: tuple | None = None) -> None:
        self.v, self.g = v, g

    def grads(self, n: int) -> tuple:
        """The ``n`` gradient components (all None for a constant)."""
        return self.g if self.g is not None else (None,) * n


def _prod(g: Code | None, c: Code | None) -> Code | None:
    """``g * c`` where either may be None (zero) or the literal 1.0 (and -1.0 negates)."""
    if g is None or c is None:
        return None
    if c.is_num(1.0):
        return g
    if c.is_num(-1.0):
        return _neg(g)
    if g.is_num(1.0):
        return c
    return g * c


def _neg(g: Code | None) -> Code | None:
    if g is None:
        return None
    if g.is_num(1.0):
        return num(-1.0)
    return g.args[0] if g.op == "neg" else -g


def _sum(*terms: Code | None) -> Code | None:
    """A sum of terms (None: zero); a negated term is subtracted."""
    kept = [t for t in terms if t is not None]
    if not kept:
        return None
    out = kept[0]
    for t in kept[1:]:
        out = out - t.args[0] if t.op == "neg" else out + t
    return out


def _chain_rule(rule: Any, args: list, ncomp: int) -> list:
    """Gradient components of a node from its op's gradient rule (see fastsdf.expr.ops)."""
    if rule is None:
        return [None] * ncomp
    if callable(rule):
        return [rule([a.grads(ncomp)[c] for a in args]) for c in range(ncomp)]
    return [_sum(*(_prod(a.grads(ncomp)[c], p) for a, p in zip(args, rule))) for c in range(ncomp)]


def _zero(g: Code | None) -> Code:
    return num(0.0) if g is None else g


def _as_float(c: Code) -> Code:
    """Literal results wrapped so that numba types every returned value as float64."""
    return call("float", c) if c.op == "num" else c


class Body:
    """Statements of one function: ``stmts``; ``results`` (the value, then the gradient
    components); ``nparams``: parameters read once per call from the tuple ``prm`` (as
    ``_p0``, ``_p1``, ...); ``fold``: the subexpressions evaluated in loops first (None: none)."""

    def __init__(self, stmts: list, results: list, nparams: int, fold: FoldPlan | None) -> None:
        self.stmts, self.results, self.nparams, self.fold = stmts, results, nparams, fold


class Writer:
    """Names and statements, what the op table's emitters write with (``fastsdf.expr.ops``
    imports no backend): ``kind`` ``'v'``, ``'vg'`` or ``'vgt'``; ``tables`` (shared by the
    functions of one module: bytes -> name) names constant tables."""

    def __init__(self, kind: str, tables: dict | None = None) -> None:
        self.kind = kind
        self.grad = kind != "v"
        self.time = kind == "vgt"
        self.tables = {} if tables is None else tables
        self.n = 0

    num = staticmethod(num)

    @staticmethod
    def const(value: Any) -> Code:
        """A number of the scene (:func:`fastsdf.backends.code.const`); a value given as an
        expression already (a ``k`` read at run time) is passed on."""
        return value if isinstance(value, Code) else const(value)

    call = staticmethod(call)
    var = staticmethod(var)

    def sel(self, cond: Code, a: Any, b: Any) -> Code:
        """``a if cond else b``, branch-free."""
        return call("sel", cond, a, b)

    def table_arg(self, rows: np.ndarray | list) -> Code:
        """A constant table as an argument (a compiled primitive's structure)."""
        return table(self.table(rows))

    def _name(self, prefix: str = "v") -> str:
        self.n += 1
        return f"{prefix}{self.n}"

    def assign(self, out: list, name: str, value: Code) -> Code:
        """Append ``name = value`` to ``out``; returns the variable."""
        out.append(Assign((name,), value))
        return var(name)

    def assign_many(self, out: list, names: Sequence[str], value: Code) -> list[Code]:
        """Append ``a, b, ... = value`` (a call returning a tuple); returns the variables."""
        out.append(Assign(tuple(names), value))
        return [var(n) for n in names]

    def length(self, out: list, r: str, a: Code, b: Code) -> list:
        """Append ``r = length(a, b)`` (see :class:`fastsdf.backends.code.Length`); returns its
        partials ``[a / r, b / r]`` (with the gradient)."""
        out.append(Length(r, a, b, self.grad))
        return [var(f"{r}p"), var(f"{r}q")] if self.grad else []

    def table(self, rows: np.ndarray | list) -> str:
        """The name of a constant table (one per distinct content in a module)."""
        arr = np.asarray(rows, dtype=np.float64)
        key = (arr.shape, arr.tobytes())
        name = self.tables.get(key)
        if name is None:
            name = f"_T{len(self.tables)}"
            self.tables[key] = name
        return name


def chain_step(
    em: Writer,
    out: list,
    op: str,
    v: Code,
    grads: Sequence,
    cur: dict,
    new: dict,
    nk: Code | None,
    comps: Sequence[str],
    zero: Sequence = (),
) -> None:
    """One operand of an n-ary ``min``/``max``/``smin``/``smax`` chain streamed into its
    accumulator: the one definition of the update, which the straight-line code and the
    combine programs' interpreter (:mod:`fastsdf.backends.kernel.combine`) both render.

    ``v`` is the operand's value and ``grads`` its gradient components (None: known zero);
    ``cur`` the accumulator (``'m'`` the running value, ``'s'`` a smooth chain's sum of
    weights, and one entry per gradient component ``comps``); ``new`` the names of the
    updated entries (and of ``'w'``, the comparison, and ``'e'``, the weight); ``nk`` is
    ``-k``, a smooth chain's sharpness (a literal, or a value read at run time); ``zero``, per
    component, a flag read at run time that the operand's component is known to be zero: its
    product with the weight is then left out, as the straight-line code leaves out the term of
    a zero component.

    The smooth update is the online log-sum-exp: where the operand beats the running value the
    sum is rescaled, ``s e + 1``, else ``s + e``, with ``e = exp(-k |v - m|) <= 1``, so nothing
    overflows for any k; :func:`chain_finish` adds ``-+ log(s) / k``. The earlier operand wins
    ties."""
    less = op in ("min", "smin")
    m = cur["m"]
    w = em.assign(out, new["w"], v < m if less else v > m)
    smooth = op in ("smin", "smax")
    if smooth:
        assert nk is not None  # (a smooth chain has a sharpness)
        s = cur["s"]
        e = em.assign(out, new["e"], call("exp", nk * call("abs", v - m)))
        out.append(Assign((new["s"],), call("sel", w, s * e + 1.0, s + e)))
    for c, sfx in enumerate(comps):
        comp, acc = _zero(grads[c]), cur[sfx]
        if not smooth:
            value = call("sel", w, comp, acc)
        else:
            blend = None if comp.is_num(0.0) else _prod(comp, e)
            if zero and blend is not None:
                blend = call("sel", zero[c], 0.0, blend)
            value = call("sel", w, acc * e + comp, acc + _zero(blend))
        out.append(Assign((new[sfx],), value))
    out.append(Assign((new["m"],), call("sel", w, v, m)))


def chain_finish(
    em: Writer, out: list, op: str, cur: dict, ik: Code, r: str, comps: Sequence[str]
) -> Val:
    """A smooth chain's result from its accumulator ``cur`` (see :func:`chain_step`):
    ``m -+ log(s) / k`` (``ik`` is ``1 / k``: multiplying instead of dividing shortens the
    latency chain exp -> log -> next blend, by at most one rounding) and the gradient
    divided by the sum of weights."""
    log = call("log", cur["s"]) * ik
    rv = em.assign(out, r, cur["m"] - log if op == "smin" else cur["m"] + log)
    if not comps:
        return Val(rv)
    ri = em.assign(out, f"{r}i", 1.0 / cur["s"])
    return Val(rv, tuple(em.assign(out, f"{r}{sfx}", cur[sfx] * ri) for sfx in comps))


def flagged(flags: Sequence[Code], value: Any) -> Code:
    """An expression whose terms depend on whether components are known to be zero, with
    the knowledge read at run time (``flags``: booleans): a select over ``value(dead)`` for
    every combination ``dead`` (a tuple of bools, one per flag; None from ``value`` is 0.0),
    each exactly what the straight-line code writes for that combination."""

    def choose(dead: tuple) -> Code:
        if len(dead) == len(flags):
            return _zero(value(dead))
        return call("sel", flags[len(dead)], choose((*dead, True)), choose((*dead, False)))

    return choose(())


class Emitter(Writer):
    """Emits the statements of one kind of per-point function of a Program.

    :meth:`plain`: straight-line code with loops over tables; :meth:`folded`: a long scene's
    small subexpressions in loops first (stored per point), then the straight-line code that
    combines them; :meth:`fold_loops`: those loops alone (a combine program does the rest).
    ``tables`` (shared by the functions of one module: bytes -> name) names constant tables.
    """

    def __init__(self, program: Program, kind: str, tables: dict) -> None:
        super().__init__(kind, tables)
        self.program = program
        self.comps = KIND_COMPONENTS(program, kind)
        n = len(self.comps)
        self.syms = {
            name: Val(var(axis), tuple(num(1.0) if j == i else None for j in range(n)))
            for i, (name, axis) in enumerate(zip(program.coords, _AXES))
        }
        # Parameters are read from the argument tuple prm once per call (bound to _p<i>); the
        # time is the argument t.
        self.params = {name: Val(var(f"_p{i}", "b")) for i, name in enumerate(program.params or ())}
        t_grad = tuple(None for _ in program.coords) + (num(1.0),)
        self.params["t"] = Val(var("t", "b"), t_grad if self.time else None)

    def _grad(self, out: list, name: str, comps: list) -> tuple | None:
        """Assign gradient expressions to variables named after ``name`` (if nonzero)."""
        if not self.grad:
            return None

        def keep(e: Code | None) -> bool:  # nothing to compute: no new variable needed
            return e is None or e.op == "var" or e.is_num(1.0)

        return tuple(
            e if keep(e) else self.assign(out, f"{name}{suffix}", e)
            for e, suffix in zip(comps, self.comps)
        )

    # -- one operation ------------------------------------------------------------------------
    def op(self, out: list, node: Any, a: list) -> Val:
        """Emit ``node`` (an expression node, or anything with its ``op`` and ``attr``) given
        its argument values ``a``."""
        spec = OPS[node.op]
        r = self._name()  # taken for chains too: keeps generated names stable
        if spec.chain:
            return self.chain(out, node.op, node.attr, [("val", v) for v in a])
        assert spec.emit is not None  # (every operation but the chains has an emitter)
        rule = spec.emit(self, out, node, a, r)
        if not self.grad:
            return Val(var(r))
        comps = _chain_rule(rule, a, len(self.comps))
        return Val(var(r), self._grad(out, r, comps))

    def leaf(self, node: Expr) -> Val:
        """A coordinate symbol or a parameter."""
        if node.op == "sym":
            return self.syms[node.attr]
        return self.params[node.attr[0]]

    def template(self, body: list, steps: list, consts: list) -> Val:
        """Emit one operand of a loop: its steps, with the j-th constant ``consts[j]``."""
        vals: list[Val] = []
        for node, refs in steps:
            if node.op in ("sym", "param"):
                vals.append(self.leaf(node))
                continue
            args = [Val(consts[j]) if kind == "c" else vals[j] for kind, j in refs]
            vals.append(self.op(body, node, args))
        return vals[-1]

    def _constants(self, tab: np.ndarray, refs: list, index: Code) -> list:
        """A loop's constants: literals, or elements of its table at row ``index``."""
        name = self.table(tab) if tab.shape[1] else ""
        return [const(v) if kind == "l" else read(name, index, v) for kind, v in refs]

    # -- n-ary chains ---------------------------------------------------------------------------
    def chain(self, out: list, op: str, k: float, items: list) -> Val:
        """Emit an n-ary min/max/smin/smax over ``items``: ``("val", Val)`` for an operand
        computed already, ``("group", Group)`` for a loop over same-shape operands.

        Straight-line updates are in SSA form (new variables ``w<n>m``, ``w<n>s``, ``w<n>x``,
        ... per operand); only the accumulators carried through a loop (``c<n>m``, ...) are
        reassigned."""
        g = self.grad
        c = self._name("c")
        base = {"m": f"{c}m", "s": f"{c}s"}
        base.update((sfx, f"{c}{sfx}") for sfx in self.comps)
        smooth = op in ("smin", "smax")
        less = op in ("min", "smin")
        keys = ["m"] + (["s"] if smooth else []) + (list(self.comps) if g else [])
        ncomp = len(self.comps)
        cur: dict[str, Code]
        if items[0][0] == "val":
            first = items[0][1]
            items = items[1:]
            cur = {"m": first.v, "s": num(1.0)}
            cur.update(zip(self.comps, (_zero(comp) for comp in first.grads(ncomp))))
        else:
            cur = {"m": num(_HUGE if less else -_HUGE), "s": num(0.0)}
            cur.update((sfx, num(0.0)) for sfx in self.comps)

        def update(body: list, v: Val, new: dict | None) -> None:
            w = self._name("w")
            names = {key: f"{w}{key}" for key in keys} if new is None else dict(new)
            names.update(w=w, e=f"{w}e")
            grads = v.grads(ncomp) if g else ()
            comps = self.comps if g else ()
            nk = -const(k) if smooth else None
            chain_step(self, body, op, v.v, grads, dict(cur), names, nk, comps)
            cur.update((key, var(names[key])) for key in keys)

        for item in items:
            if item[0] == "val":
                update(out, item[1], None)
                continue
            group = item[1]
            for key in keys:  # the loop-carried accumulators, assigned before the loop
                out.append(Assign((base[key],), cur[key]))
                cur[key] = var(base[key])
            index = var(self._name("i"), "i")
            body: list = []
            val = self.template(body, group.steps, self._constants(group.table, group.refs, index))
            update(body, val, {key: base[key] for key in keys})
            out.append(Loop(index, body, group=group.index))
        if not smooth:
            return Val(cur["m"], tuple(cur[sfx] for sfx in self.comps) if g else None)
        comps = self.comps if g else ()
        return chain_finish(self, out, op, cur, const(1.0 / k), self._name(), comps)

    def ordered_chain(self, out: list, op: str, k: float, items: list) -> Val:
        """Emit the left fold of the blend ``op`` (qmin, cmin) over ``items`` (as
        :meth:`chain`): each step is the binary operation's own code, so the results are those
        of the nested binary operations. A loop carries the running value and gradient in
        variables reassigned per row; a chain that opens with a loop starts from +huge (the
        blend of +huge and ``a`` is ``a``: ``|a - huge| > k``)."""
        node: Any = _OpNode(op, k)
        n = len(self.comps)
        c = self._name("c")
        base = {"m": f"{c}m"}
        base.update((sfx, f"{c}{sfx}") for sfx in self.comps)
        cur: Val | None = None
        for item in items:
            if item[0] == "val":
                cur = item[1] if cur is None else self.op(out, node, [cur, item[1]])
                continue
            group = item[1]
            if cur is None:
                cur = Val(num(_HUGE), (None,) * n if self.grad else None)
            out.append(Assign((base["m"],), cur.v))
            if self.grad:
                out.extend(
                    Assign((base[sfx],), _zero(comp)) for sfx, comp in zip(self.comps, cur.grads(n))
                )
            index = var(self._name("i"), "i")
            body: list = []
            val = self.template(body, group.steps, self._constants(group.table, group.refs, index))
            carried = Val(
                var(base["m"]),
                tuple(var(base[sfx]) for sfx in self.comps) if self.grad else None,
            )
            new = self.op(body, node, [carried, val])
            body.append(Assign((base["m"],), new.v))
            if self.grad:
                body.extend(
                    Assign((base[sfx],), _zero(comp)) for sfx, comp in zip(self.comps, new.grads(n))
                )
            out.append(Loop(index, body, group=group.index))
            cur = carried
        assert cur is not None  # (a chain has operands)
        return cur

    # -- whole functions ------------------------------------------------------------------------
    def _node(self, out: list, node: Expr, done: dict, fold: FoldPlan | None) -> Val:
        folded = fold.at.get(node) if fold is not None else None
        if fold is not None and folded is not None:  # evaluated in a loop already: read it
            gi, j = folded
            group = fold.groups[gi]
            r = self._name()
            base = j * group.size
            rv = self.assign(out, r, fold_entry(gi, base))
            comps: list = [None] * len(self.comps)
            for slot, c in enumerate(group.stored[1:], 1):
                comps[c] = self.assign(out, f"{r}{self.comps[c]}", fold_entry(gi, base + slot))
            return Val(rv, tuple(comps) if self.grad else None)
        if node.op == "const":
            return Val(const(node.attr))
        if node.op in ("sym", "param"):
            return self.leaf(node)
        chain = self.program.chains.get(node)
        if chain is None:
            return self.op(out, node, [done[a] for a in node.args])
        return self._chain(out, chain, done)

    def _chain(self, out: list, chain: Chain, done: dict) -> Val:
        items = [("val", done[ref]) if kind == "node" else (kind, ref) for kind, ref in chain.items]
        if chain.ordered:
            return self.ordered_chain(out, chain.op, chain.k, items)
        return self.chain(out, chain.op, chain.k, items)

    def _check_live(self, node: Expr, val: Val) -> None:
        """The emitted gradient components are the ones the Program says can be nonzero."""
        live = self.program.live[node]
        idx = tuple(range(self.program.ncomp)) + ((len(live) - 1,) if self.time else ())
        got = val.grads(len(self.comps))
        assert all((got[i] is not None) == live[c] for i, c in enumerate(idx)), (node.op, live)

    def _straight(self, out: list, order: list, fold: FoldPlan | None) -> Val:
        done: dict[Expr, Val] = {}
        for node in order:
            val = self._node(out, node, done, fold)
            if self.grad and (fold is None or node not in fold.at):
                self._check_live(node, val)
            done[node] = val
        return done[self.program.root]

    def _results(self, res: Val) -> list:
        out = [_as_float(res.v)]
        if self.grad:
            out += [_as_float(_zero(c)) for c in res.grads(len(self.comps))]
        return out

    def plain(self) -> Body:
        """The per-point statements: straight-line code with loops over tables."""
        out: list = []
        res = self._straight(out, self.program.order, None)
        return Body(out, self._results(res), len(self.program.params or ()), None)

    def fold_loops(self, fold: FoldPlan) -> list:
        """The loops that evaluate ``fold``'s subexpressions, storing value and gradient per
        member (see :class:`fastsdf.backends.code.Store`)."""
        out: list = []
        for group in fold.groups:
            index = var(self._name("i"), "i")
            body: list = []
            val = self.template(body, group.steps, self._constants(group.table, group.refs, index))
            comps = val.grads(len(self.comps)) if self.grad else (None,) * len(self.comps)
            if fold.singles and self.grad:  # combine programs read value and every component
                comps = tuple(_zero(comp) for comp in comps)
            kept = [c for c in range(len(self.comps)) if comps[c] is not None]
            assert (None, *kept) == group.stored, (kept, group.stored)
            body.append(Store(group.index, index, group.size, 0, val.v))
            for slot, c in enumerate(kept, 1):
                body.append(Store(group.index, index, group.size, slot, _zero(comps[c])))
            out.append(Loop(index, body, count=len(group.members)))
        return out

    def folded(self, fold: FoldPlan) -> Body:
        """The subexpressions of ``fold`` in loops first, then the straight-line code over
        their stored values."""
        out = self.fold_loops(fold)
        res = self._straight(out, fold.order, fold)
        return Body(out, self._results(res), len(self.program.params or ()), fold)


class _OpNode:
    """What the emitters of :mod:`fastsdf.expr.ops` read of a node (its op and attribute),
    for the steps of a chain that has no node of its own."""

    __slots__ = ("op", "attr")

    def __init__(self, op: str, attr: Any) -> None:
        self.op, self.attr = op, attr
