"""Code generation: an expression DAG becomes Python source that numba compiles.

Design (docs/codegen.md and docs/design.md give the measurements behind it):

* The DAG is flattened into a tape of SSA assignments, one per reachable node, so shared
  subexpressions are computed once and unreachable nodes never appear. Gradients are carried in
  forward mode beside each value; a component known to be zero is not emitted at all.
* Chains of one associative operation (``min``, ``max``, and ``smin``/``smax`` with one ``k``;
  a long union is such a chain) are flattened into one n-ary operation. Operands whose
  expressions have the same *shape* (the same operations, differing only in constants, e.g. 20
  rotated boxes) become one ``for`` loop over a constant table holding each operand's numbers.
  Generated code therefore grows with the number of distinct shapes, not with the number of
  primitives, which is what keeps numba's compile time flat (a straight-line function per scene
  compiles in time that grows much faster than the scene).
* Straight-line code is in SSA form: every variable is assigned once (a chain's running
  minimum and gradient get a new name per operand), except the accumulators of loops over
  tables. numba repairs every reassigned variable with a pass over the whole function, which
  made compile time quadratic in the length of a scene without repeated structure.
* A long body (a scene without repeated structure next to each other, over FOLD_MIN_LINES
  lines) gets block kernels that first evaluate, in loops over tables, every group of
  same-shape subexpressions wherever they stand in the scene (the primitives: each transformed
  box, each circle), storing value and gradient per point; the straight-line code that remains
  only combines them. numba's compile time then follows the combining operations and the
  number of distinct shapes. The per-point functions keep the plain straight-line code (the
  tests compare the two, bit for bit).
* A smooth chain is evaluated as an online log-sum-exp (the streaming-softmax recurrence):
  one ``exp`` per operand and one ``log`` per chain, with values that never overflow for any
  ``k > 0``. This is mathematically the notebook's nested ``-log(exp(-k a) + exp(-k b)) / k``.
* Per-point functions are plain ``@njit`` functions (branch-free selects, no ``parallel``), and
  tiny ``prange`` kernels call them; long generated code inside a ``parallel=True`` body is what
  makes numba's compile time explode. For scenes without parameters the ``prange`` kernels are
  scene-independent (:mod:`fastsdf.backends.kernel.drive`, compiled once per installation) and call
  the scene's block functions by address.
* Each module is written to a content-hashed file in the cache directory
  (:mod:`fastsdf.backends.kernel.cache`) and compiled with ``cache=True``; every function compiles
  lazily, so a value-only call never compiles gradient code.
"""

from __future__ import annotations

import platform
import re
from collections.abc import Callable, Sequence
from typing import Any

import numba
import numpy as np

from fastsdf.backends.kernel.cache import hashed_import
from fastsdf.backends.kernel.simd import (
    block_source,
    drive_import,
    program_source,
    vectorizable,
    vmath_import,
)
from fastsdf.expr.graph import Expr, dag_size, gc_paused, parameters
from fastsdf.expr.ops import OPS, lit
from fastsdf.version import __version__

__all__ = ["generate_module_source", "MIN_LOOP", "PointCode", "point_code", "table_source"]

#: Same-shape operands of a chain needed before they are folded into a loop over a table.
MIN_LOOP = 4
#: Chain operands with more nodes than this (as a tree) are never folded into loops.
MAX_TEMPLATE_NODES = 128
#: Per-point functions longer than this (in generated lines) are not interleaved.
LONG_BODY_LINES = 400
#: Scenes whose per-point code is longer than this (lines) get block kernels that evaluate
#: same-shape subexpressions anywhere in the scene in loops first (see ``_Emitter._prefold``).
FOLD_MIN_LINES = 400
#: At most this many values per point (scratch rows of BLOCK floats, per thread) are stored by
#: those loops; groups beyond it stay straight-line code.
MAX_FOLD_ROWS = 1536
#: The same for the subexpressions under a combine program (all of the scene's primitives;
#: 8192 rows are 32 MiB of scratch space per thread).
MAX_PROGRAM_ROWS = 8192
#: Long bodies that are trees of blends run their blends as a combine program (see
#: ``_Emitter.program``); False keeps straight-line block code (kept to compare the two).
COMBINE_PROGRAMS = True

_CHAIN_OPS = ("min", "max", "smin", "smax", "qmin", "cmin")
#: Chains of the polynomial blends are left folds (the blends are not associative): flattened
#: along the left operand only, never reordered; consecutive same-shape operands become loops.
_ORDERED_OPS = ("qmin", "cmin")
_HUGE = "1.7976931348623157e+308"
#: The chains a combine program runs (see ``_Emitter.program``).
_PROGRAM_OPS = ("min", "max", "smin", "smax", "qmin", "cmin")


_lit = lit


class _OpNode:
    """What the emitters of :mod:`fastsdf.expr.ops` read of a node (its op and attribute), for the
    steps of a chain that has no node of its own."""

    __slots__ = ("op", "attr")

    def __init__(self, op: str, attr: Any) -> None:
        self.op, self.attr = op, attr


class _Val:
    """An emitted value: Python expressions (usually variable names) for the value ``v`` and
    the gradient components ``g`` (one per coordinate: x, y). A component of ``None`` is known
    to be zero; ``"1.0"`` is a literal one.
    """

    __slots__ = ("v", "g")

    def __init__(self, v: str, g: tuple | None = None) -> None:
        self.v, self.g = v, g

    def grads(self, n: int) -> tuple:
        """The ``n`` gradient components (all None for a constant)."""
        return self.g if self.g is not None else (None,) * n


def _prod(g, c):
    """Source for ``g * c`` where g may be None (zero) or '1.0', and c '1.0' or '-1.0'."""
    if g is None or c is None:
        return None
    if c == "1.0":
        return g
    if c == "-1.0":
        return _neg(g)
    if g == "1.0":
        return c
    return f"{g} * {c}"


def _sum(*terms):
    """Source for a sum of terms (strings or None); terms starting with '-' are subtracted."""
    terms = [t for t in terms if t is not None]
    if not terms:
        return None
    out = terms[0]
    for t in terms[1:]:
        out = f"{out} - {t[1:]}" if t.startswith("-") else f"{out} + {t}"
    return out


def _neg(g):
    if g is None:
        return None
    if g == "1.0":
        return "(-1.0)"
    return f"-({g})" if not g.startswith("-") else g[1:]


def _chain_rule(rule, args, ncomp):
    """Gradient component sources of a node from its op's gradient rule (see fastsdf.expr.ops)."""
    if rule is None:
        return [None] * ncomp
    if callable(rule):
        return [rule([a.grads(ncomp)[c] for a in args]) for c in range(ncomp)]
    return [_sum(*(_prod(a.grads(ncomp)[c], p) for a, p in zip(args, rule))) for c in range(ncomp)]


def _zero(g):
    return "0.0" if g is None else g


# ---------------------------------------------------------------------------------------------
# Shapes of subexpressions (structure with constants abstracted).


def _template(root: Expr) -> tuple[tuple, list, list]:
    """Linearize the sub-DAG of ``root`` with constants abstracted.

    Returns ``(signature, steps, constants)``: ``steps`` lists ``(node, argrefs)`` in
    evaluation order, where each argref is ``('c', j)`` for the j-th constant (every occurrence
    counted separately, so equal constants do not change the shape) or ``('n', i)`` for the
    value of step i. Two roots with equal signatures evaluate by the same code.
    """
    # (nodes hash by identity: dicts keyed by node, not by id(), save a call per lookup)
    local: dict[Expr, int] = {}
    steps: list[tuple] = []
    sig: list[tuple] = []
    consts: list[float] = []

    def record(node: Expr) -> None:
        arg_refs = []
        for a in node.args:
            if a.op == "const":
                arg_refs.append(("c", len(consts)))
                consts.append(a.attr)
            else:
                arg_refs.append(("n", local[a]))
        refs = tuple(arg_refs)
        local[node] = len(steps)
        steps.append((node, refs))
        sig.append((node.op, node.attr if node.op != "const" else None, refs))

    def visit(node: Expr) -> None:
        for a in node.args:
            if a.op != "const" and a not in local:
                visit(a)
        record(node)

    # Templates are of small subexpressions (a primitive): a recursive walk is the fastest;
    # a deep one falls back to an iterative walk in the same order.
    try:
        visit(root)
    except RecursionError:
        for kept in (local, steps, sig, consts):
            kept.clear()
        stack = [(root, False)]
        while stack:
            node, expanded = stack.pop()
            if node in local:
                continue
            if expanded:
                record(node)
                continue
            stack.append((node, True))
            stack.extend((a, False) for a in reversed(node.args) if a.op != "const")
    return tuple(sig), steps, consts


def _varying_columns(rows: list) -> tuple[np.ndarray, list]:
    """Split a group's constants into a table of the columns that differ between members and
    literals for the columns that are the same in every member (e.g. the 0 of ``max(q, 0)``).

    Returns ``(table_rows, refs)`` where ``refs[j]`` is ``('t', column)`` or ``('l', value)``.
    """
    arr = np.asarray(rows, dtype=np.float64)
    refs: list[tuple] = []
    columns: list[np.ndarray] = []
    for j in range(arr.shape[1]):
        col = arr[:, j]
        if np.all(col.view(np.int64) == col[0:1].view(np.int64)):  # bitwise: keeps -0.0 apart
            refs.append(("l", float(col[0])))
        else:
            refs.append(("t", len(columns)))
            columns.append(col)
    table = np.stack(columns, axis=1) if columns else np.zeros((arr.shape[0], 0))
    return table, refs


def _foldable(root: Expr, memo: dict | None = None) -> bool:
    """Whether every chain in the small subexpression ``root`` is emitted as it stands (no
    operand of the same operation to flatten, too few operands to fold into a loop), so that its
    template's code is exactly its straight-line code. ``memo`` (node -> bool) is shared between
    calls: each node is examined once however many candidates contain it."""
    memo = {} if memo is None else memo
    stack = [root]
    while stack:
        node = stack[-1]
        if node in memo:
            stack.pop()
            continue
        todo = [a for a in node.args if a not in memo]
        if todo:
            stack.extend(todo)
            continue
        stack.pop()
        ok = all(memo[a] for a in node.args)
        if ok and node.op in _CHAIN_OPS:
            ok = not (
                len(node.args) >= MIN_LOOP
                or any(a.op == node.op and a.attr == node.attr for a in node.args)
            )
        memo[node] = ok
    return memo[root]


def _flatten_chain(node: Expr) -> list:
    """Operands of the maximal chain of ``node``'s operation (same op and k), left to right
    (for the left folds of ``_ORDERED_OPS``: along the left operands only)."""
    if node.op in _ORDERED_OPS:
        out, n = [], node
        while n.op == node.op and n.attr == node.attr:
            out.append(n.args[1])
            n = n.args[0]
        out.append(n)
        return out[::-1]
    out, stack = [], [node]
    while stack:
        n = stack.pop()
        if n.op == node.op and n.attr == node.attr:
            stack.extend(reversed(n.args))
        else:
            out.append(n)
    return out


# ---------------------------------------------------------------------------------------------
# Emission.


class _Emitter:
    """Emits the body of one per-point function (value only, or value and gradient).

    Operations come from the table of :mod:`fastsdf.expr.ops`; the emitter applies their gradient
    rules to every coordinate component alike (``COMPONENTS``: variable suffixes, one per
    coordinate) and emits the n-ary chains (min, max, smin, smax) itself.
    """

    #: The coordinates: argument names of the generated functions, also the suffixes of
    #: gradient variables (``v3x`` is dv3/dx).
    COMPONENTS: tuple[str, ...] = ("x", "y")

    def __init__(
        self,
        symbol_names: Sequence[str],
        grad: bool,
        tables: dict,
        param_names: Sequence[str] = (),
        time: bool = False,
        fold: bool = False,
        memo: dict | None = None,
    ):
        self.grad = grad
        # fold: evaluate same-shape subexpressions anywhere in the scene in loops first (into
        # the per-point arrays _F<g>); the straight-line code then only reads their entries.
        self.fold = fold
        self.fold_of: dict[int, tuple] = {}
        self.fold_sizes: list[int] = []
        self.fold_zero: dict[int, tuple] = {}
        if time:  # also carry d/dt: a third forward-mode component, seeded by the time t
            self.COMPONENTS = self.COMPONENTS + ("t",)
        n = len(self.COMPONENTS)
        self.syms = {
            name: _Val(var, tuple("1.0" if j == i else None for j in range(n)))
            for i, (name, var) in enumerate(zip(symbol_names, self.COMPONENTS))
        }
        # Parameters are read from the argument tuple prm once per call (bound to _p<i>); the
        # time is the argument t.
        self.params = {name: _Val(f"_p{i}") for i, name in enumerate(param_names)}
        self.params["t"] = _Val("t", (None, None, "1.0") if time else None)
        self.tables = tables  # shared across functions of one module: bytes -> name
        self.lines: list[str] = []
        self.n = 0
        # Loops over tables ("groups"), in emission order: each iterates the rows listed in
        # _act[_off[g]:_off[g + 1]], so a caller can pass a pruned list without recompiling.
        self.groups: list[dict] = []
        # Shapes, sizes and chain plans depend on the expression alone: the emitters of one
        # module share them (``memo``), so the four functions of a scene find each once.
        self.memo = {} if memo is None else memo
        self._foldables: dict = self.memo.setdefault("foldable", {})  # node -> _foldable
        self._templates: dict = self.memo.setdefault("templates", {})
        self._plans: dict = self.memo.setdefault("plans", {})

    def _name(self, prefix="v"):
        self.n += 1
        return f"{prefix}{self.n}"

    def assign(self, out: list, name: str, expr: str) -> str:
        """Append ``name = expr`` to ``out``; returns ``name``."""
        out.append(f"{name} = {expr}")
        return name

    _assign = assign

    def _grad(self, out, name, comps):
        """Assign gradient expressions to variables named after ``name`` (if nonzero)."""
        if not self.grad:
            return None

        def keep(expr):  # nothing to compute: no new variable needed
            return expr is None or expr == "1.0" or expr.isidentifier()

        return tuple(
            e if keep(e) else self.assign(out, f"{name}{suffix}", e)
            for e, suffix in zip(comps, self.COMPONENTS)
        )

    # -- one operation ------------------------------------------------------------------------
    def op(self, out: list, node: Expr, a: list) -> _Val:
        """Emit ``node`` given its argument values ``a``; returns the result."""
        spec = OPS[node.op]
        r = self._name()  # taken for chains too: keeps generated names (and cache keys) stable
        if spec.chain:
            return self.chain(out, node.op, node.attr, [("val", v) for v in a])
        assert spec.emit is not None  # (every operation but the chains has an emitter)
        rule = spec.emit(self, out, node, a, r)
        if not self.grad:
            return _Val(r)
        comps = _chain_rule(rule, a, len(self.COMPONENTS))
        return _Val(r, self._grad(out, r, comps))

    # -- n-ary chains -------------------------------------------------------------------------
    def chain(self, out: list, op: str, k: float, items: list) -> _Val:
        """Emit an n-ary min/max/smin/smax over ``items``.

        Each item is ``("val", _Val)`` for an operand already computed, or
        ``("loop", steps_list, table_name, count)`` for a group of same-shape operands.

        Straight-line code is emitted in SSA form: every update of the running minimum, sum and
        gradient gets new variables (``w<n>m``, ``w<n>s``, ``w<n>x``, ...) instead of reassigning
        one. numba repairs each reassigned variable with a pass over the whole function, so
        reassignments make its compile time quadratic in the length of the function. Only the
        accumulators carried through a loop over a table (``c<n>m``, ...) are reassigned.
        """
        g = self.grad
        c = self._name("c")
        base = {"m": f"{c}m", "s": f"{c}s"}
        base.update((suffix, f"{c}{suffix}") for suffix in self.COMPONENTS)
        smooth = op in ("smin", "smax")
        less = "<" if op in ("min", "smin") else ">"
        keys = ["m"] + (["s"] if smooth else []) + (list(self.COMPONENTS) if g else [])
        first = items[0][1] if items[0][0] == "val" else None
        # cur: the expression (variable or literal) holding each running quantity
        if first is not None:
            items = items[1:]
            cur = {"m": first.v, "s": "1.0"}
            first_grads = first.grads(len(self.COMPONENTS))
            cur.update(zip(self.COMPONENTS, (_zero(comp) for comp in first_grads)))
        else:
            cur = {"m": _HUGE if less == "<" else f"-{_HUGE}", "s": "0.0"}
            cur.update((suffix, "0.0") for suffix in self.COMPONENTS)

        def update(body: list, v: _Val, new: dict | None) -> None:
            w = self._name("w")
            new = new or {key: f"{w}{key}" for key in keys}
            m = cur["m"]
            body.append(f"{w} = {v.v} {less} {m}")
            if smooth:
                e = f"{w}e"
                s = cur["s"]
                body.append(f"{e} = math.exp(-{_lit(k)} * abs({v.v} - {m}))")
                body.append(f"{new['s']} = _sel({w}, {s} * {e} + 1.0, {s} + {e})")
                if g:
                    for suffix, comp in zip(self.COMPONENTS, v.grads(len(self.COMPONENTS))):
                        comp, acc = _zero(comp), cur[suffix]
                        blend = _prod(comp, e) if comp != "0.0" else "0.0"
                        body.append(
                            f"{new[suffix]} = _sel({w}, {acc} * {e} + {comp}, {acc} + {blend})"
                        )
            elif g:
                for suffix, comp in zip(self.COMPONENTS, v.grads(len(self.COMPONENTS))):
                    body.append(f"{new[suffix]} = _sel({w}, {_zero(comp)}, {cur[suffix]})")
            body.append(f"{new['m']} = _sel({w}, {v.v}, {m})")
            cur.update(new)

        for item in items:
            if item[0] == "val":
                update(out, item[1], None)
            else:
                _, steps, consts, count, group = item
                # the loop-carried accumulators: one variable each, assigned before the loop
                for key in keys:
                    out.append(f"{base[key]} = {cur[key]}")
                    cur[key] = base[key]
                loop = self._name("i")
                body: list[str] = [f"{loop} = _act[{loop}q]"]
                val = self.template(body, steps, [c.format(row=loop) for c in consts])
                update(body, val, {key: base[key] for key in keys})
                out.append(f"for {loop}q in range(_off[{group}], _off[{group + 1}]):")
                out.extend("    " + line for line in body)
        if not smooth:
            return _Val(cur["m"], tuple(cur[suffix] for suffix in self.COMPONENTS) if g else None)
        r = self._name()
        sign = "-" if op == "smin" else "+"
        # Multiplying by 1/k instead of dividing shortens the latency chain (the kernel is bound
        # by exp -> log -> next blend); it changes the result by at most one rounding.
        out.append(f"{r} = {cur['m']} {sign} math.log({cur['s']}) * {_lit(1.0 / k)}")
        if g:
            out.append(f"{r}i = 1.0 / {cur['s']}")
            for suffix in self.COMPONENTS:
                out.append(f"{r}{suffix} = {cur[suffix]} * {r}i")
            return _Val(r, tuple(f"{r}{suffix}" for suffix in self.COMPONENTS))
        return _Val(r)

    def template(self, body: list, steps: list, consts: list) -> _Val:
        """Emit one operand of a loop group: its steps, with the j-th constant as ``consts[j]``
        (a literal, or a table element indexed by the loop variable)."""
        vals: list[_Val] = []
        for node, refs in steps:
            if node.op in ("sym", "param"):
                vals.append(self.leaf(node))
                continue
            args = [_Val(consts[j]) if kind == "c" else vals[j] for kind, j in refs]
            vals.append(self.op(body, node, args))
        return vals[-1]

    def leaf(self, node: Expr) -> _Val:
        """A coordinate symbol or a parameter."""
        if node.op == "sym":
            return self.syms[node.attr]
        return self.params[node.attr[0]]

    def table(self, rows: np.ndarray | list) -> str:
        arr = np.asarray(rows, dtype=np.float64)
        key = (arr.shape, arr.tobytes())
        name = self.tables.get(key)
        if name is None:
            name = f"_T{len(self.tables)}"
            self.tables[key] = name
        return name

    # -- the whole function -------------------------------------------------------------------
    def emit(self, root: Expr) -> _Val:
        """Emit code for ``root`` (iteratively, flattening chains); returns its value."""
        done: dict[int, _Val] = {}
        plans: dict[int, tuple] = {}
        if self.fold:
            self._prefold(root, plans)
        stack = [root]
        while stack:
            node = stack[-1]
            if id(node) in done:
                stack.pop()
                continue
            plan = plans.get(id(node))
            if plan is None:
                plan = plans[id(node)] = self._plan(node)
            deps, _ = plan
            missing = [d for d in deps if id(d) not in done]
            if missing:
                stack.extend(reversed(missing))
                continue
            stack.pop()
            done[id(node)] = self._emit_planned(node, plan, done)
        return done[id(root)]

    def _prefold(self, root: Expr, plans: dict, singles: bool = False) -> None:
        """Find the subexpressions to evaluate in loops and emit those loops.

        Candidates are the maximal small subexpressions (at most MAX_TEMPLATE_NODES nodes as a
        tree, under a larger one) that the straight-line code would emit, typically each
        primitive of a scene with no repeated structure (a transformed box, a circle, a cut).
        Those with the same shape (see :func:`_template`) become one loop over a table of their
        constants that stores value and gradient in the array ``_F<g>`` (row ``j``: member j),
        so the straight-line code grows with the combining operations, not with the primitives.
        A subexpression whose straight-line code would differ from its template's (a chain that
        would be flattened or folded) is left alone: the results are the same bits either way.
        ``singles``: also shapes with one member (a loop of one row), for combine programs.
        """

        def too_big(node):
            if self._size(node) <= MAX_TEMPLATE_NODES:
                return False
            # For a program: a primitive larger as a tree than as a DAG (a transformed capsule
            # shares its subexpressions) is still one subexpression; blends never are.
            return (
                not singles
                or node.op in _CHAIN_OPS
                or node.op == "neg"
                or dag_size(node, MAX_TEMPLATE_NODES) > MAX_TEMPLATE_NODES
            )

        # The candidates depend on the expression alone: found once per module (the value and
        # the gradient functions share them through the memo).
        key = ("prefold", id(root), singles)
        shapes = self.memo.get(key)
        if shapes is None:
            shapes = self.memo[key] = self._candidates(root, plans, singles, too_big)
        ncomp = len(self.COMPONENTS)
        rows_left = MAX_PROGRAM_ROWS if singles else MAX_FOLD_ROWS
        for steps, members, rows in shapes.values():
            if (
                len(members) < (1 if singles else 2)
                or len(members) * (1 + ncomp * self.grad) > rows_left
            ):
                continue
            rows_left -= len(members) * (1 + ncomp * self.grad)
            table, refs = _varying_columns(rows)
            name = self.table(table) if table.shape[1] else None
            loop = self._name("i")
            consts = [_lit(v) if kind == "l" else f"{name}[{loop}, {v}]" for kind, v in refs]
            body: list[str] = []
            val = self.template(body, steps, consts)
            comps = val.grads(ncomp) if self.grad else (None,) * ncomp
            zero = tuple(comp is None or comp == "0.0" for comp in comps)
            if singles and self.grad:  # combine programs read value, x, y in consecutive rows
                comps = tuple(_zero(comp) for comp in comps)
            stored: tuple = (None,) + tuple(c for c in range(ncomp) if comps[c] is not None)
            g = len(self.fold_sizes)
            size = len(stored)
            body.append(f"_F{g}[{loop} * {size}] = {val.v}")
            for slot, c in enumerate(stored[1:], 1):
                body.append(f"_F{g}[{loop} * {size} + {slot}] = {comps[c]}")
            self.lines.append(f"for {loop} in range({len(members)}):")
            self.lines.extend("    " + line for line in body)
            self.fold_sizes.append(len(members) * size)
            for j, member in enumerate(members):
                self.fold_of[id(member)] = (g, j, stored)
                self.fold_zero[id(member)] = zero
                plans[id(member)] = ([], None)

    def _candidates(self, root: Expr, plans: dict, singles: bool, too_big: Callable) -> dict:
        """:meth:`_prefold`'s candidates: ``{signature: (steps, members, rows)}`` in the order
        of their first member."""
        seen: set[Expr] = set()
        order: list[Expr] = []
        under_big: set[Expr] = set()
        stack = [root]
        while stack:
            node = stack.pop()
            if node in seen:
                continue
            seen.add(node)
            order.append(node)
            plan = plans.get(id(node))
            if plan is None:
                plan = plans[id(node)] = self._plan(node)
            # For a program: larger subexpressions (a transformed capsule counts more than
            # MAX_TEMPLATE_NODES as a tree), and the operands of the root, and of every
            # expression that is not a candidate, are candidates (also in a small scene).
            big = too_big(node) or (
                singles
                and (node is root or node.op in _CHAIN_OPS and not _foldable(node, self._foldables))
            )
            if big:
                under_big.update(plan[0])
            stack.extend(plan[0])
        shapes: dict = {}
        for node in order:
            if (
                node not in under_big
                or node.op in ("const", "sym", "param")
                or too_big(node)
                or not _foldable(node, self._foldables)
            ):
                continue
            sig, steps, consts = self._template(node)
            shapes.setdefault(sig, (steps, [], []))
            shapes[sig][1].append(node)
            shapes[sig][2].append(consts)
        return shapes

    def program(self, root: Expr) -> tuple[list, int] | None:
        """The combine program of ``root`` for the block kernels, or None.

        Every maximal small subexpression is evaluated in a loop over a table first (see
        :meth:`_prefold`, one-member shapes included); if what remains is a tree of chains
        (min, max, smin, smax; no loops over tables) over those results, it becomes a list of
        steps for the installation's interpreter (:func:`fastsdf.backends.kernel.drive._combine`)
        instead of straight-line code. Steps are tuples ``(op, operand, acc, k, zero)``: ``operand``
        the first of the operand's rows (value, then one per gradient component), ``acc`` the first
        of the accumulator's rows (m, the gradient components, s), ``zero`` which of the
        operand's gradient components are known to be zero. A row is ``('F', group, entry)``
        (a folded subexpression's entry) or ``('A', n)`` (accumulator rows). The last step is
        ``('out', operand)``. Returns ``(steps, accumulator_rows)``.
        """
        plans: dict = {}
        self._prefold(root, plans, singles=True)
        if not self.fold_sizes or id(root) in self.fold_of:
            return None
        ncomp = len(self.COMPONENTS)
        # post-order over the chains above the folded subexpressions; uses of each chain
        order: list[Expr] = []
        uses: dict[int, int] = {}
        seen: set[int] = set()
        stack = [(root, False)]
        while stack:
            node, expanded = stack.pop()
            if expanded:
                order.append(node)
                continue
            if id(node) in seen:
                continue
            seen.add(id(node))
            plan = plans.get(id(node)) or self._plan(node)
            deps, items = plan
            if node.op == "neg":  # e.g. a - b = max(a, -b) with b a large subexpression
                if deps[0].op == "const":
                    return None
            elif (
                node.op not in _PROGRAM_OPS
                or items is None
                or len(items) < 2
                or any(item[0] != "node" or item[1].op == "const" for item in items)
            ):
                return None
            stack.append((node, True))
            for dep in reversed(list({id(d): d for d in deps}.values())):
                if id(dep) in self.fold_of:
                    continue
                uses[id(dep)] = uses.get(id(dep), 0) + 1
                stack.append((dep, False))
        free: list = []
        count = [0]
        result: dict = {}
        width = 2 + ncomp * self.grad  # rows of an accumulator: m, gradient components, s

        def alloc():
            if free:
                return free.pop()
            count[0] += 1
            return ("A", (count[0] - 1) * width)

        zeros: dict = {}  # gradient components known to be zero, of a program node's result

        def operand(node):
            folded = self.fold_of.get(id(node))
            if folded is None:
                return result[id(node)], zeros.get(id(node), (False,) * ncomp)
            g, j, stored = folded
            return ("F", g, j * len(stored)), self.fold_zero[id(node)]

        steps = []
        for node in order:
            deps, items = plans.get(id(node)) or self._plan(node)
            if node.op == "neg":
                arg = deps[0]
                row, zero = operand(arg)
                if id(arg) not in self.fold_of and uses[id(arg)] == 1:
                    acc = row  # in place
                else:
                    acc = alloc()
                steps.append(("neg", row, acc, None, zero))
                result[id(node)] = acc
                zeros[id(node)] = zero
                if id(arg) in result:
                    uses[id(arg)] -= 1
                    if uses[id(arg)] == 0 and result[id(arg)] is not acc:
                        free.append(result[id(arg)])
                continue
            assert items is not None  # (the other nodes here are chains)
            operands = [item[1] for item in items]
            first = operands[0]
            acc = None
            if (
                id(first) not in self.fold_of
                and uses[id(first)] == 1
                and sum(o is first for o in operands) == 1
            ):
                acc = result[id(first)]  # its last use: accumulate in place
            smooth = node.op in ("smin", "smax")
            pair = smooth and len(operands) == 2  # one fused step: blend and finish
            if acc is None:
                acc = alloc()
                steps.append(("init", operand(first)[0], acc, None, None))
            elif smooth and not pair:  # in place: only s = 1
                steps.append(("init", acc, acc, None, None))
            if node.op in _ORDERED_OPS:
                # a left fold of polynomial blends: the running value's gradient components
                # known to be zero are tracked too (the straight-line code drops their terms)
                za = operand(first)[1]
                for other in operands[1:]:
                    row, zb = operand(other)
                    steps.append((node.op, row, acc, node.attr, zb + za))
                    za = tuple(a and b for a, b in zip(za, zb))
                zeros[id(node)] = za
            elif pair:
                row, zero = operand(operands[1])
                steps.append((node.op + "2", row, acc, node.attr, zero))
            else:
                for other in operands[1:]:
                    row, zero = operand(other)
                    steps.append((node.op, row, acc, node.attr, zero))
                if smooth:
                    steps.append(("fin_" + node.op, None, acc, node.attr, None))
            result[id(node)] = acc
            for dep in set(map(id, operands)):
                if dep in result and dep != id(node):
                    uses[dep] -= 1
                    if uses[dep] == 0 and result[dep] is not acc:
                        free.append(result[dep])
        steps.append(("out", operand(root)[0], None, None, None))
        return steps, count[0] * width

    def _size(self, root: Expr) -> int:
        """Nodes under ``root`` counted as a tree, capped just above MAX_TEMPLATE_NODES (kept
        on every node at its construction: O(1))."""
        size = root.tree
        return size if size <= MAX_TEMPLATE_NODES else MAX_TEMPLATE_NODES + 1

    def _template(self, node: Expr) -> tuple[tuple, list, list]:
        """:func:`_template`, memoized."""
        t = self._templates.get(id(node))
        if t is None:
            t = self._templates[id(node)] = _template(node)
        return t

    def _plan(self, node: Expr) -> tuple[list, list | None]:
        plan = self._plans.get(id(node))
        if plan is None:
            plan = self._plans[id(node)] = self._plan_of(node)
        return plan

    def _plan_of(self, node: Expr) -> tuple[list, list | None]:
        if node.op not in _CHAIN_OPS:
            return list(node.args), None
        operands = _flatten_chain(node)
        if node.op in _ORDERED_OPS:
            return self._plan_ordered(operands)
        shapes: dict = {}
        order: list = []
        for operand in operands:
            if operand.op == "const" or self._size(operand) > MAX_TEMPLATE_NODES:
                # Large operands (typically the rest of the scene) are never folded: finding
                # their shape would walk them again at every level, quadratic in the scene.
                order.append(("node", operand))
                continue
            sig, steps, consts = self._template(operand)
            group = shapes.get(sig)
            if group is None:
                group = shapes[sig] = [steps, [], []]
                order.append(("group", sig))
            group[1].append(operand)
            group[2].append(consts)
        items: list[tuple] = []
        deps: list[Expr] = []
        for kind, ref in order:
            if kind == "node":
                items.append(("node", ref))
                deps.append(ref)
                continue
            steps, members, rows = shapes[ref]
            if len(members) >= MIN_LOOP:
                items.append(("loop", steps, _varying_columns(rows), members, rows))
            else:
                for member in members:
                    items.append(("node", member))
                    deps.append(member)
        # Restore the left-to-right order of single operands relative to each other; loops are
        # placed where their first member stood. (Ties go to the operand evaluated first.)
        return deps, items

    def _plan_ordered(self, operands: list) -> tuple[list, list]:
        """:meth:`_plan` of a left fold: runs of consecutive same-shape operands become loops,
        in place (the order of the operands is the written one)."""
        items: list[tuple] = []
        deps: list[Expr] = []
        run: list | None = None

        def flush():
            if run is None:
                return
            if len(run[2]) >= MIN_LOOP:
                items.append(("loop", run[1], _varying_columns(run[3]), run[2], run[3]))
            else:
                items.extend(("node", m) for m in run[2])
                deps.extend(run[2])

        for operand in operands:
            if operand.op == "const" or self._size(operand) > MAX_TEMPLATE_NODES:
                flush()
                run = None
                items.append(("node", operand))
                deps.append(operand)
                continue
            sig, steps, consts = self._template(operand)
            if run is None or run[0] != sig:
                flush()
                run = [sig, steps, [], []]
            run[2].append(operand)
            run[3].append(consts)
        flush()
        return deps, items

    def ordered_chain(self, out: list, op: str, k: float, items: list) -> _Val:
        """Emit the left fold of the blend ``op`` (qmin, cmin) over ``items`` (as
        :meth:`chain`): each step is the binary operation's own code, so the results are those
        of the nested binary operations. A loop carries the running value and gradient in
        variables reassigned per row; a chain that opens with a loop starts from +huge (the
        blend of +huge and ``a`` is ``a``: ``|a - huge| > k``)."""
        node: Any = _OpNode(op, k)  # (what the emitters read of a node)
        n = len(self.COMPONENTS)
        c = self._name("c")
        base = {"m": f"{c}m"}
        base.update((suffix, f"{c}{suffix}") for suffix in self.COMPONENTS)
        cur: _Val | None = None
        for item in items:
            if item[0] == "val":
                cur = item[1] if cur is None else self.op(out, node, [cur, item[1]])
                continue
            _, steps, consts, count, group = item
            if cur is None:
                cur = _Val(_HUGE, (None,) * n if self.grad else None)
            out.append(f"{base['m']} = {cur.v}")
            if self.grad:
                out.extend(
                    f"{base[sfx]} = {_zero(comp)}"
                    for sfx, comp in zip(self.COMPONENTS, cur.grads(n))
                )
            loop = self._name("i")
            body: list[str] = [f"{loop} = _act[{loop}q]"]
            val = self.template(body, steps, [cc.format(row=loop) for cc in consts])
            carried = _Val(
                base["m"], tuple(base[sfx] for sfx in self.COMPONENTS) if self.grad else None
            )
            new = self.op(body, node, [carried, val])
            body.append(f"{base['m']} = {new.v}")
            if self.grad:
                body.extend(
                    f"{base[sfx]} = {_zero(comp)}"
                    for sfx, comp in zip(self.COMPONENTS, new.grads(n))
                )
            out.append(f"for {loop}q in range(_off[{group}], _off[{group + 1}]):")
            out.extend("    " + line for line in body)
            cur = carried
        assert cur is not None  # (a chain has operands)
        return cur

    def _emit_planned(self, node: Expr, plan: tuple, done: dict) -> _Val:
        deps, items = plan
        folded = self.fold_of.get(id(node))
        if folded is not None:  # evaluated in a loop already: read its entries
            g, j, stored = folded
            r = self._name()
            self.lines.append(f"{r} = _F{g}[{j * len(stored)}]")
            comps: list[str | None] = [None] * len(self.COMPONENTS)
            for slot, c in enumerate(stored[1:], 1):
                comps[c] = self.assign(
                    self.lines, f"{r}{self.COMPONENTS[c]}", f"_F{g}[{j * len(stored) + slot}]"
                )
            return _Val(r, tuple(comps) if self.grad else None)
        if node.op == "const":
            return _Val(_lit(node.attr))
        if node.op in ("sym", "param"):
            return self.leaf(node)
        if items is None:
            return self.op(self.lines, node, [done[id(a)] for a in node.args])
        chain_items: list[tuple] = []
        others = [item[1] for item in items if item[0] == "node"]
        before: list = []  # the chain's items so far: ("node", operand) or ("group", index)
        for item in items:
            if item[0] == "node":
                chain_items.append(("val", done[id(item[1])]))
                before.append(item)
            else:
                _, steps, (table, refs), members, rows = item
                name = self.table(table) if table.shape[1] else None
                consts = [
                    _lit(v) if kind == "l" else f"{name}[{{row}}, {j}]"
                    for kind, v in refs
                    for j in [v if kind == "t" else None]
                ]
                self.groups.append(
                    dict(
                        op=node.op,
                        k=node.attr,
                        chain=node,
                        members=members,
                        steps=steps,
                        rows=np.asarray(rows, dtype=np.float64),
                        others=others,
                        before=list(before),
                    )
                )
                chain_items.append(("loop", steps, consts, table.shape[0], len(self.groups) - 1))
                before.append(("group", len(self.groups) - 1))
        if node.op in _ORDERED_OPS:
            return self.ordered_chain(self.lines, node.op, node.attr, chain_items)
        return self.chain(self.lines, node.op, node.attr, chain_items)


_HEADER = '''"""Generated by fastsdf {fastsdf} (numba {numba}, numpy {numpy}, Python {python}).

Expression: {expr}
Do not edit: the file name is the hash of this content.
"""
import math

import numpy as np
from numba import njit, prange

from fastsdf.intrinsics import select as _sel

'''

_POINT_TEMPLATE = '''
@njit(cache=True, nogil=True, error_model="numpy")
def {name}(x, y{pargs}):
    """{doc}"""
    if not (math.isfinite(x) and math.isfinite(y)):
        return {nan_return}
{body}
    return {ret}
'''


def _as_float(expr: str) -> str:
    """Wrap literal results so that numba types every returned value as float64."""
    return f"float({expr})" if expr[0].isdigit() or expr.startswith("(") else expr


def _function_source(
    root: Expr,
    symbol_names: Sequence[str],
    grad: bool,
    tables: dict,
    param_names: Sequence[str] | None = None,
    time: bool = False,
    vmath: bool = True,
    memo: dict | None = None,
) -> tuple[Any, str, list]:
    """``(one, rows, groups)``: the source of the one-point function (with the block kernels
    where the scene has them: a pair), of the one-point function over given row lists
    (``rows_vg``, for scenes with loop groups; else empty), and the loop groups.
    ``param_names`` (None for a scene without parameters): the functions take ``(x, y, t,
    prm)``, ``prm`` the tuple of those parameters' values; ``time``: also return dd/dt (the
    ``vgt`` functions)."""
    if (
        param_names is None
        and not time
        and vmath
        and COMBINE_PROGRAMS
        and dag_size(root, FOLD_MIN_LINES // 2) > FOLD_MIN_LINES // 2
    ):
        # A large static scene: try the combine program first; it needs no straight-line code
        # (which is most of the code generation time of a large scene).
        prog = _program_source(root, symbol_names, grad, tables, memo)
        if prog is not None:
            return prog, "", []
    em = _Emitter(symbol_names, grad or time, tables, param_names or (), time, memo=memo)
    res = em.emit(root)
    if grad or time:
        results = [_as_float(res.v)] + [_as_float(_zero(c)) for c in res.grads(len(em.COMPONENTS))]
    if time:
        single = (
            "point_vgt",
            "Value, gradient and time derivative (d, dd/dx, dd/dy, dd/dt) at one point.",
            "math.nan, math.nan, math.nan, math.nan",
        )
    elif grad:
        single = (
            "point_vg",
            "Value and gradient (d, dd/dx, dd/dy) at one point.",
            "math.nan, math.nan, math.nan",
        )
    else:
        results = [_as_float(res.v)]
        single = ("point_v", "Value at one point.", "math.nan")
    if vmath:
        em.lines = vectorizable(em.lines)
    # numba lowers every reference to a global array as its own constant: bind each table to
    # a local once, so a table is embedded once per function however often the loop reads it.
    used = sorted(set(re.findall(r"\b(_T\d+)\b", "\n".join(em.lines))))
    binds = [f"{name} = {name}G" for name in used]
    # Parameters: read once per call from the tuple (passed by value: no reference counting).
    binds += [f"_p{i} = prm[{i}]" for i in range(len(param_names or ()))]
    em.lines[:0] = binds
    pargs = ", t, prm" if param_names is not None else ""
    # The one-point function iterates every row of every group; rows_vg takes the row lists
    # as arguments (all rows, or a tile's pruned lists).
    all_rows = ["_act = _ACTG", "_off = _OFFG"] if em.groups else []
    body = "\n".join("    " + line for line in all_rows + em.lines) or "    pass"
    point = _POINT_TEMPLATE.format(
        name=single[0],
        doc=single[1],
        body=body,
        pargs=pargs,
        ret=", ".join(results),
        nan_return=single[2],
    )
    one: str | tuple[str, str] = point
    bind, rest = em.lines[: len(binds)], em.lines[len(binds) :]
    many = ""
    if em.groups and grad and param_names is None and not time:
        # The one-point function over given row lists (pointers to int64: a tile's pruned
        # lists), for per-point callers such as the particle step (see fastsdf.backends.prune).
        many += _POINT_TEMPLATE.format(
            name="rows_vg",
            doc="point_vg over the row lists ``_act``, ``_off`` (int64 "
            "pointers, see fastsdf.backends.prune).",
            body="\n".join("    " + line for line in em.lines),
            pargs=", _act, _off",
            ret=", ".join(results),
            nan_return=single[2],
        )
    if param_names is None and not time:
        kind = "vg" if grad else "v"
        fold_sizes: Sequence[int] = ()
        prog = None
        if len(rest) > FOLD_MIN_LINES and vmath and not em.groups and COMBINE_PROGRAMS:
            # A long body that is a tree of blends over small subexpressions: those in loops
            # over tables, the blends as a program for the installation's interpreter.
            prog = _program_source(root, symbol_names, grad, tables, memo)
            if prog is not None:
                one = prog
        if prog is None and len(rest) > FOLD_MIN_LINES:
            # A long body: the block kernels evaluate repeated subexpressions in loops (the
            # per-point functions keep the straight-line code; the tests compare the two).
            fe = _Emitter(symbol_names, grad, tables, fold=True, memo=memo)
            fres = fe.emit(root)
            if fe.fold_sizes:
                assert [len(g["members"]) for g in fe.groups] == [
                    len(g["members"]) for g in em.groups
                ]
                rest = vectorizable(fe.lines) if vmath else fe.lines
                results = [_as_float(fres.v)] + (
                    [_as_float(_zero(c)) for c in fres.grads(len(fe.COMPONENTS))] if grad else []
                )
                fold_sizes = fe.fold_sizes
        if prog is None:
            one = (point, block_source(rest, results, kind, fold_sizes=fold_sizes))
    elif param_names is not None:  # parameters are data: read once per block from prm
        kind = "vgt" if time else "vg" if grad else "v"
        one = (
            point,
            block_source(
                list(rest),
                results,
                kind,
                ("t", "prm"),
                binds=tuple(ln for ln in bind if ln.startswith("_p")),
            ),
        )
    return one, many, em.groups


class PointCode:
    """The per-point statements of one kind of function, for a target other than the CPU's
    (the CUDA target of :mod:`fastsdf.backends.cuda`): the same emitter and op table as the CPU
    kernels, with the C library's functions (``math.exp``, ``math.log``, ``math.hypot``) left
    as they are instead of the CPU's vectorisable ones.

    ``lines``: statements (unindented) reading ``x``, ``y`` (and ``t``, ``_p<i>``), tables bound
    by their names (``_T0`` ...), and for loop groups the row lists ``_act`` and ``_off``;
    ``results``: the returned expressions (value, then dd/dx, dd/dy, then dd/dt for ``'vgt'``);
    ``groups``: the loop groups (as :func:`generate_module` returns them); ``nan_return``: what
    a non-finite point returns. The tables the lines may read are the values of the ``tables``
    dict given to :func:`point_code` (each named ``_T<i>``).
    """

    def __init__(self, lines: list, results: list, groups: list) -> None:
        self.lines, self.results, self.groups = lines, results, groups
        self.nan_return = ", ".join(["math.nan"] * len(results))


def point_code(
    root: Expr,
    symbol_names: Sequence[str],
    kind: str,
    tables: dict,
    param_names: Sequence[str] | None = None,
    memo: dict | None = None,
) -> PointCode:
    """The per-point statements of ``kind`` (``'v'``, ``'vg'``, ``'vgt'``) for ``root``;
    ``tables`` (shared by the functions of one module) receives the constant tables, rendered
    by :func:`table_source`."""
    time = kind == "vgt"
    grad = kind != "v"
    em = _Emitter(symbol_names, grad, tables, param_names or (), time, memo=memo)
    res = em.emit(root)
    results = [_as_float(res.v)]
    if grad:
        results += [_as_float(_zero(c)) for c in res.grads(len(em.COMPONENTS))]
    binds = [f"_p{i} = prm[{i}]" for i in range(len(param_names or ()))]
    return PointCode(binds + em.lines, results, em.groups)


def table_source(tables: dict, groups: list) -> str:
    """Module-level definitions of the constant tables (``_T<i>G``) and, for loop groups, of
    the full row lists ``_ACTG`` and ``_OFFG``."""
    parts = []
    for (shape, data), name in tables.items():
        arr = np.frombuffer(data, dtype=np.float64).reshape(shape)
        rows = ",\n    ".join("[" + ", ".join(repr(float(v)) for v in row) + "]" for row in arr)
        parts.append(f"{name}G = np.array([\n    {rows},\n], dtype=np.float64)\n")
    if groups:
        sizes = [len(g["members"]) for g in groups]
        parts.append(
            "_ACTG = np.concatenate(("
            + "".join(f"np.arange({n}), " for n in sizes)
            + ")).astype(np.int64)\n"
            f"_OFFG = np.array({[0] + list(np.cumsum(sizes).tolist())}, dtype=np.int64)\n"
        )
    return "\n".join(parts)


def _program_source(
    root: Expr, symbol_names: Sequence[str], grad: bool, tables: dict, memo: dict | None
) -> tuple[str, str] | None:
    """``(point function, block kernels)`` of a combine program for ``root``, or None (see
    ``_Emitter.program``). The one-point function runs the program too: numba's time for the
    straight-line one grows faster than the scene (38 s at 200 mixed primitives)."""
    ptables = dict(tables)  # kept only if the program is used
    pe = _Emitter(symbol_names, grad, ptables, fold=True, memo=memo)
    prog = pe.program(root)
    if prog is None:
        return None
    tables.update(ptables)
    return program_source(vectorizable(pe.lines), "vg" if grad else "v", pe.fold_sizes, *prog)


def scene_parameters(root: Expr) -> tuple[str, ...] | None:
    """``None`` for a scene without parameters, else the sorted names of its parameters other
    than time (the order of the ``prm`` tuple the kernels take)."""
    names = parameters(root)
    if not names:
        return None
    return tuple(sorted(n for n in names if n != "t"))


def generate_module_source(
    root: Expr, symbol_names: Sequence[str], vmath: bool = True
) -> tuple[str, dict]:
    """Full source of the kernel module for ``root``; also returns each function's source."""
    source, funcs, _ = generate_module(root, symbol_names, vmath=vmath)
    return source, funcs


def generate_module(
    root: Expr, symbol_names: Sequence[str], vmath: bool = True
) -> tuple[str, dict, list]:
    """``(source, functions, groups)``: :func:`generate_module_source` plus the loop groups
    (one dict per loop over a table, in the order of the kernels' row lists: ``op``, ``k``,
    ``chain`` (the chain's node), ``members`` (the operands' expressions), ``steps`` and
    ``rows`` (their shared template and constants), ``others`` (the chain's other operands))."""
    with gc_paused():  # a bulk pass over the graph (see fastsdf.expr.graph._GCPaused)
        return _generate_module(root, symbol_names, vmath)


def _generate_module(
    root: Expr, symbol_names: Sequence[str], vmath: bool
) -> tuple[str, dict, list]:
    tables: dict = {}
    pn = scene_parameters(root)
    memo: dict = {}
    v_one, v_rows, groups_v = _function_source(
        root, symbol_names, False, tables, pn, vmath=vmath, memo=memo
    )
    vg_one, vg_rows, groups = _function_source(
        root, symbol_names, True, tables, pn, vmath=vmath, memo=memo
    )
    # The batch kernels are the SIMD block kernels of fastsdf.backends.kernel.simd.
    blocks = []
    if isinstance(v_one, tuple):
        (v_one, v_block), (vg_one, vg_block) = v_one, vg_one
        blocks = [v_block, vg_block]
    assert [len(g["members"]) for g in groups_v] == [len(g["members"]) for g in groups]
    funcs = {"v": v_one, "vg": vg_one}
    rows = [v_rows, vg_rows]
    if pn is not None:
        # A scene with parameters: functions (x, y, t, prm) and a third kind with dd/dt.
        # Parameter values never appear in the source: scenes that differ only in them share
        # one module.
        vgt_one, vgt_rows, _ = _function_source(
            root, symbol_names, True, tables, pn, time=True, vmath=vmath, memo=memo
        )
        vgt_one, vgt_block = vgt_one
        blocks.append(vgt_block)
        funcs.update(vgt=vgt_one)
        rows.append(vgt_rows)
    parts = [
        _HEADER.format(
            fastsdf=__version__,
            numba=numba.__version__,
            numpy=np.__version__,
            python=platform.python_version(),
            expr=_short(root).replace('"""', "'''").replace("\\", "\\\\"),
        )
    ]
    if any("_P." in src for src in [*funcs.values(), *rows]):
        parts.append(_prims_import())
    if tables or groups:
        parts.append(table_source(tables, groups))
    parts.extend(funcs[k] for k in ("v", "vg", "vgt") if k in funcs)
    parts.extend(rows)
    if vmath:
        parts.append(vmath_import())
    if blocks:
        parts.append(drive_import())
    parts.extend(blocks)
    return "\n".join(parts), funcs, groups


def _prims_import() -> str:
    """Import of the compiled primitives of :mod:`fastsdf.backends.kernel.prims`."""
    return hashed_import("fastsdf.backends.kernel.prims", alias="_P") + "\n"


def _short(root: Expr) -> str:
    from fastsdf.expr.graph import expr_to_str

    return expr_to_str(root, limit=300)
