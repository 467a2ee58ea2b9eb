"""The lowering: a scene's expression DAG becomes a :class:`Program`, built once per scene.

The Program holds every decision the code generators, pruning and the NumPy reference share,
as data: the order in which nodes are evaluated; chains of one associative operation (``min``,
``max``, ``smin``/``smax`` with one ``k``, and the left folds of the polynomial blends) with
their operands in order; operands of the same *shape* (the same operations, differing only in
constants, e.g. 20 rotated boxes) grouped into loops over a table of their constants; which
gradient components of each value are known to be zero; the parameters; the coordinates (a
list of symbol names: a third coordinate is a third name); and, for long scenes, which small
subexpressions are evaluated in loops first (:meth:`Program.folds`) and the scene's blends as a
combine program (:meth:`Program.combine`). The emitters of every target render it; nothing
else plans.

Why loops over tables: generated code then grows with the number of distinct shapes, not with
the number of primitives, which keeps numba's compile time flat (docs/codegen.md).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from fastsdf.expr.graph import Expr, dag_size, gc_paused, parameters, topological_order
from fastsdf.expr.ops import OPS

__all__ = [
    "CHAIN_OPS",
    "ORDERED_OPS",
    "MIN_LOOP",
    "PROGRAM_STEPS",
    "Chain",
    "Combine",
    "FoldGroup",
    "FoldPlan",
    "Group",
    "Program",
    "lower",
]

#: Same-shape operands of a chain needed before they are folded into a loop over a table.
MIN_LOOP = 4
#: Chain operands with more nodes than this (as a tree) are never folded into loops.
MAX_TEMPLATE_NODES = 128
#: At most this many values per point (scratch rows of a block, per thread) are stored by
#: the loops of :meth:`Program.folds`; shapes beyond it stay straight-line code.
MAX_FOLD_ROWS = 1536
#: The same for the subexpressions under a combine program (all of the scene's primitives;
#: 8192 rows are 32 MiB of scratch space per thread).
MAX_PROGRAM_ROWS = 8192

#: Operations flattened into n-ary chains.
CHAIN_OPS = ("min", "max", "smin", "smax", "qmin", "cmin")
#: Chains of the polynomial blends are left folds (the blends are not associative): flattened
#: along the left operand only, never reordered; consecutive same-shape operands become loops.
ORDERED_OPS = ("qmin", "cmin")
#: The chains a combine program runs.
PROGRAM_OPS = ("min", "max", "smin", "smax", "qmin", "cmin")
#: The steps of a combine program, by opcode (a program row's first column): copy the operand
#: into the accumulator (s = 1); one hard or smooth step of a min or max chain; finish a smooth
#: chain; the last row (the result's rows); a smooth pair (blend and finish in one step); the
#: negated operand; one step of a left fold of polynomial blends.
PROGRAM_STEPS = (
    "init",
    "min",
    "max",
    "smin",
    "smax",
    "fin_smin",
    "fin_smax",
    "out",
    "smin2",
    "smax2",
    "neg",
    "qmin",
    "cmin",
)


@dataclass(eq=False)
class Group:
    """A loop over a table: the same-shape operands (``members``) of one chain (``chain``, of
    operation ``op`` with parameter ``k``). ``steps`` is their shared template (see
    :func:`template`), ``rows`` every member's constants, ``table`` the columns that differ
    between members and ``refs`` for each constant ``('t', column)`` or ``('l', value)``
    (the same in every member); ``live`` which gradient components of a member's value can be
    nonzero; ``others`` the chain's operands outside loops; ``before`` the chain's items
    before this loop (``('node', operand)`` or ``('group', index)``); ``index`` its place in
    the kernels' row lists."""

    op: str
    k: Any
    chain: Expr
    members: list
    steps: list
    rows: np.ndarray
    table: np.ndarray
    refs: list
    live: tuple
    index: int = -1
    others: list = field(default_factory=list)
    before: list = field(default_factory=list)


class Chain:
    """An n-ary chain: ``items`` in order, each ``('node', operand)`` or ``('group', Group)``."""

    __slots__ = ("node", "op", "k", "items")

    def __init__(self, node: Expr, items: list) -> None:
        self.node, self.op, self.k, self.items = node, node.op, node.attr, items

    @property
    def ordered(self) -> bool:
        """A left fold (polynomial blends): operands in the written order, never regrouped."""
        return self.op in ORDERED_OPS


@dataclass(eq=False)
class FoldGroup:
    """Subexpressions of one shape evaluated in a loop over a table before the rest of a long
    scene (see :meth:`Program.folds`): ``members``, their template ``steps``, ``table`` and
    ``refs`` (as :class:`Group`), ``stored`` the components stored per member (None for the
    value, then gradient component indices) and ``zero`` which gradient components are known
    to be zero; ``index`` its place among the fold groups."""

    index: int
    members: list
    steps: list
    table: np.ndarray
    refs: list
    stored: tuple
    zero: tuple

    @property
    def size(self) -> int:
        """Values stored per member."""
        return len(self.stored)


class FoldPlan:
    """Which subexpressions a long scene evaluates in loops first: ``groups`` (FoldGroup, in
    order), ``at`` (member -> (group, row)) and ``order``, the evaluation order of the rest
    (folded members are read, not evaluated); ``singles``: every subexpression under the
    scene's blends, each storing every gradient component (for a combine program)."""

    def __init__(self, groups: list, at: dict, order: list, singles: bool) -> None:
        self.groups, self.at, self.order, self.singles = groups, at, order, singles

    @property
    def sizes(self) -> list[int]:
        """Values stored per group (members x stored components)."""
        return [len(g.members) * g.size for g in self.groups]


class Combine:
    """A scene's blends as data: ``fold`` (every small subexpression in loops first) and
    ``steps``, each ``(op, operand, acc, k, zeros)``: ``operand`` the first of the operand's
    rows (value, then one per gradient component), ``acc`` the first of the accumulator's rows
    (m, the gradient components, s), ``zeros`` which of the operand's gradient components are
    known to be zero. A row is ``('F', group, entry)`` (a folded subexpression's entry) or
    ``('A', n)`` (accumulator rows). The last step is ``('out', operand)``; ``acc_rows`` the
    accumulator rows used."""

    def __init__(self, fold: FoldPlan, steps: list, acc_rows: int) -> None:
        self.fold, self.steps, self.acc_rows = fold, steps, acc_rows


def template(root: Expr) -> tuple[tuple, list, list]:
    """Linearize the sub-DAG of ``root`` with constants abstracted.

    Returns ``(signature, steps, constants)``: ``steps`` lists ``(node, argrefs)`` in
    evaluation order, where each argref is ``('c', j)`` for the j-th constant (every occurrence
    counted separately, so equal constants do not change the shape) or ``('n', i)`` for the
    value of step i. Two roots with equal signatures evaluate by the same code.
    """
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


def varying_columns(rows: list) -> tuple[np.ndarray, list]:
    """Split a group's constants into a table of the columns that differ between members and
    literals for the columns that are the same in every member (e.g. the 0 of ``max(q, 0)``).

    Returns ``(table, refs)`` where ``refs[j]`` is ``('t', column)`` or ``('l', value)``.
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


def flatten_chain(node: Expr) -> list:
    """Operands of the maximal chain of ``node``'s operation (same op and k), left to right
    (for the left folds of ``ORDERED_OPS``: along the left operands only)."""
    if node.op in ORDERED_OPS:
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


def _tree_size(root: Expr) -> int:
    """Nodes under ``root`` counted as a tree, capped just above MAX_TEMPLATE_NODES (kept
    on every node at its construction: O(1))."""
    size = root.tree
    return size if size <= MAX_TEMPLATE_NODES else MAX_TEMPLATE_NODES + 1


class Program:
    """The lowered scene (see the module docstring); build it with :func:`lower`.

    ``coords``: the coordinate symbols' names (the gradient's components, in order);
    ``params``: the sorted names of the parameters other than time (None: a static scene);
    ``time``: whether the scene depends on the time ``t``; ``order``: the nodes evaluated by
    straight-line code, arguments first (a chain's operands are its arguments);
    ``chains``: node -> :class:`Chain`; ``groups``: the loops over tables, in order;
    ``live``: node -> per component (the coordinates, then time) whether it can be nonzero.
    """

    def __init__(self, root: Expr, coords: Sequence[str]) -> None:
        self.root = root
        self.coords = tuple(coords)
        names = parameters(root)
        self.time = "t" in names
        self.params = tuple(sorted(n for n in names if n != "t")) if names else None
        self.chains: dict[Expr, Chain] = {}
        self.groups: list[Group] = []
        self.live: dict[Expr, tuple] = {}
        self._deps: dict[Expr, list] = {}
        self._templates: dict[Expr, tuple] = {}
        self._foldable: dict[Expr, bool] = {}
        self._shapes: dict[bool, dict] = {}
        self._folds: dict[tuple, FoldPlan | None] = {}
        self._combine: dict[bool, Combine | None] = {}
        self._nodes: list | None = None
        self.order = self._walk(root, {})
        self._number_groups()

    # -- what the evaluators read ----------------------------------------------------------
    @property
    def parametric(self) -> bool:
        """Whether kernels take the time and parameters (the scene has either)."""
        return self.params is not None or self.time

    @property
    def ncomp(self) -> int:
        """Gradient components besides time: one per coordinate."""
        return len(self.coords)

    @property
    def nodes(self) -> list:
        """Every node of the scene, arguments first (the NumPy reference's order)."""
        if self._nodes is None:
            self._nodes = topological_order(self.root)
        return self._nodes

    @property
    def ops(self) -> set[str]:
        """The operations the scene uses (a module imports what they call): those of the
        planned nodes and of every loop's template."""
        steps = [g.steps for g in self.groups]
        steps += [shape[0] for shapes in self._shapes.values() for shape in shapes.values()]
        return {n.op for n in self._deps} | {s[0].op for ss in steps for s in ss}

    def deps(self, node: Expr) -> list:
        """The values ``node`` is computed from in straight-line code: a chain's operands
        outside loops, else its arguments."""
        return self._deps[node]

    def template(self, node: Expr) -> tuple:
        """:func:`template` of ``node``, memoized."""
        t = self._templates.get(node)
        if t is None:
            t = self._templates[node] = template(node)
        return t

    # -- the walk ----------------------------------------------------------------------------
    def _walk(self, root: Expr, leaves: dict) -> list:
        """Nodes in straight-line evaluation order from ``root`` (depth first, arguments in
        order); ``leaves``: nodes read rather than evaluated."""
        order: list[Expr] = []
        done: set[Expr] = set()
        stack = [root]
        while stack:
            node = stack[-1]
            if node in done:
                stack.pop()
                continue
            deps = [] if node in leaves else self._plan(node)
            missing = [d for d in deps if d not in done]
            if missing:
                stack.extend(reversed(missing))
                continue
            stack.pop()
            done.add(node)
            order.append(node)
        return order

    def _plan(self, node: Expr) -> list:
        deps = self._deps.get(node)
        if deps is None:
            if node.op in CHAIN_OPS:
                items = self._plan_chain(node)
                self.chains[node] = Chain(node, items)
                deps = [item[1] for item in items if item[0] == "node"]
            else:
                deps = list(node.args)
            self._deps[node] = deps
        return deps

    def _plan_chain(self, node: Expr) -> list:
        operands = flatten_chain(node)
        if node.op in ORDERED_OPS:
            return self._plan_ordered(node, operands)
        shapes: dict = {}
        order: list = []
        for operand in operands:
            if operand.op == "const" or _tree_size(operand) > MAX_TEMPLATE_NODES:
                # Large operands (typically the rest of the scene) are never folded: finding
                # their shape would walk them again at every level, quadratic in the scene.
                order.append(("node", operand))
                continue
            sig, steps, consts = self.template(operand)
            group = shapes.get(sig)
            if group is None:
                group = shapes[sig] = [steps, [], []]
                order.append(("shape", sig))
            group[1].append(operand)
            group[2].append(consts)
        items: list[tuple] = []
        for kind, ref in order:
            if kind == "node":
                items.append(("node", ref))
                continue
            steps, members, rows = shapes[ref]
            if len(members) >= MIN_LOOP:
                items.append(("group", self._group(node, steps, members, rows)))
            else:
                items.extend(("node", member) for member in members)
        # Loops stand where their first member stood; single operands keep their order.
        return items

    def _plan_ordered(self, node: Expr, operands: list) -> list:
        """A left fold: runs of consecutive same-shape operands become loops, in place."""
        items: list[tuple] = []
        run: list | None = None

        def flush() -> None:
            if run is None:
                return
            if len(run[2]) >= MIN_LOOP:
                items.append(("group", self._group(node, run[1], run[2], run[3])))
            else:
                items.extend(("node", m) for m in run[2])

        for operand in operands:
            if operand.op == "const" or _tree_size(operand) > MAX_TEMPLATE_NODES:
                flush()
                run = None
                items.append(("node", operand))
                continue
            sig, steps, consts = self.template(operand)
            if run is None or run[0] != sig:
                flush()
                run = [sig, steps, [], []]
            run[2].append(operand)
            run[3].append(consts)
        flush()
        return items

    def _group(self, chain: Expr, steps: list, members: list, rows: list) -> Group:
        table, refs = varying_columns(rows)
        return Group(
            op=chain.op,
            k=chain.attr,
            chain=chain,
            members=members,
            steps=steps,
            rows=np.asarray(rows, dtype=np.float64),
            table=table,
            refs=refs,
            live=self._template_live(steps),
        )

    def _number_groups(self) -> None:
        """Loops in the order straight-line code meets them (their row lists' order), each
        chain's other operands and the items before each loop; gradient liveness of every
        node of ``order``."""
        for node in self.order:
            chain = self.chains.get(node)
            if chain is not None:
                others = [item[1] for item in chain.items if item[0] == "node"]
                before: list = []
                for item in chain.items:
                    if item[0] == "group":
                        g = item[1]
                        g.index, g.others, g.before = len(self.groups), others, list(before)
                        self.groups.append(g)
                        before.append(("group", g.index))
                    else:
                        before.append(item)
            self.live[node] = self._node_live(node)

    # -- gradient liveness --------------------------------------------------------------------
    def _leaf_live(self, node: Expr) -> tuple:
        n = self.ncomp
        if node.op == "sym":
            return tuple(node.attr == name for name in self.coords) + (False,)
        if node.op == "param":
            return (False,) * n + (node.attr[0] == "t",)
        return (False,) * (n + 1)

    def _op_live(self, node: Expr, args: list) -> tuple:
        rule = OPS[node.op].live
        if rule is None:
            return tuple(any(a[c] for a in args) for c in range(self.ncomp + 1))
        return tuple(bool(rule(node, [a[c] for a in args])) for c in range(self.ncomp + 1))

    def _node_live(self, node: Expr) -> tuple:
        """Whether each gradient component of ``node`` (planned, in ``order``) can be
        nonzero. A chain carries every component (an accumulator), except a left fold of
        polynomial blends, whose step drops a component both sides know to be zero."""
        if node.op in ("const", "sym", "param"):
            return self._leaf_live(node)
        chain = self.chains.get(node)
        if chain is None:
            return self._op_live(node, [self.live[a] for a in node.args])
        if not chain.ordered:
            return (True,) * (self.ncomp + 1)
        cur: tuple | None = None
        for kind, ref in chain.items:
            if kind == "group":
                cur = (True,) * (self.ncomp + 1)  # carried through the loop
            else:
                live = self.live[ref]
                cur = live if cur is None else tuple(a or b for a, b in zip(cur, live))
        assert cur is not None  # (a chain has operands)
        return cur

    def _template_live(self, steps: list) -> tuple:
        """Liveness of a template's result (its constants are constants)."""
        vals: list[tuple] = []
        const = (False,) * (self.ncomp + 1)
        for node, refs in steps:
            if node.op in ("sym", "param"):
                vals.append(self._leaf_live(node))
            elif node.op in CHAIN_OPS and OPS[node.op].chain:
                vals.append((True,) * (self.ncomp + 1))  # emitted pairwise: an accumulator
            else:
                args = [const if kind == "c" else vals[j] for kind, j in refs]
                vals.append(self._op_live(node, args))
        return vals[-1]

    # -- long scenes: subexpressions in loops first --------------------------------------------
    def _is_foldable(self, root: Expr) -> bool:
        """Whether every chain in the small subexpression ``root`` is emitted as it stands (no
        operand of the same operation to flatten, too few operands to fold into a loop), so
        that its template's code is exactly its straight-line code."""
        memo = self._foldable
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
            if ok and node.op in CHAIN_OPS:
                ok = not (
                    len(node.args) >= MIN_LOOP
                    or any(a.op == node.op and a.attr == node.attr for a in node.args)
                )
            memo[node] = ok
        return memo[root]

    def _too_big(self, node: Expr, singles: bool) -> bool:
        if _tree_size(node) <= MAX_TEMPLATE_NODES:
            return False
        # For a program: a primitive larger as a tree than as a DAG (a transformed capsule
        # shares its subexpressions) is still one subexpression; blends never are.
        return (
            not singles
            or node.op in CHAIN_OPS
            or node.op == "neg"
            or dag_size(node, MAX_TEMPLATE_NODES) > MAX_TEMPLATE_NODES
        )

    def _fold_shapes(self, singles: bool) -> dict:
        """Candidates of :meth:`folds`: ``{signature: (steps, members, rows)}`` in the order of
        their first member. Candidates are the maximal small subexpressions (at most
        MAX_TEMPLATE_NODES nodes as a tree, under a larger one) that straight-line code would
        evaluate, typically each primitive of a scene without repeated structure; one whose
        straight-line code would differ from its template's (a chain that would be flattened
        or folded) is left alone."""
        shapes = self._shapes.get(singles)
        if shapes is not None:
            return shapes
        root = self.root
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
            deps = self._plan(node)
            # For a program: the operands of the root, and of every expression that is not
            # a candidate, are candidates (also in a small scene).
            big = self._too_big(node, singles) or (
                singles and (node is root or node.op in CHAIN_OPS and not self._is_foldable(node))
            )
            if big:
                under_big.update(deps)
            stack.extend(deps)
        shapes = {}
        for node in order:
            if (
                node not in under_big
                or node.op in ("const", "sym", "param")
                or self._too_big(node, singles)
                or not self._is_foldable(node)
            ):
                continue
            sig, steps, consts = self.template(node)
            shapes.setdefault(sig, (steps, [], []))
            shapes[sig][1].append(node)
            shapes[sig][2].append(consts)
        self._shapes[singles] = shapes
        return shapes

    def folds(self, singles: bool, grad: bool) -> FoldPlan:
        """The subexpressions a long scene evaluates in loops over tables first (the block
        kernels store their values and gradients per point), within a budget of stored rows;
        ``singles``: also shapes of one member (for a combine program, which reads every
        subexpression from the stored rows), storing every gradient component."""
        key = (singles, grad)
        plan = self._folds.get(key)
        if plan is not None:
            return plan
        ncomp = self.ncomp
        rows_left = MAX_PROGRAM_ROWS if singles else MAX_FOLD_ROWS
        groups: list[FoldGroup] = []
        at: dict[Expr, tuple] = {}
        for steps, members, rows in self._fold_shapes(singles).values():
            per = 1 + ncomp * grad
            if len(members) < (1 if singles else 2) or len(members) * per > rows_left:
                continue
            rows_left -= len(members) * per
            live = self._template_live(steps)[:ncomp] if grad else (False,) * ncomp
            if singles and grad:  # combine programs read value, x, y in consecutive rows
                stored: tuple = (None, *range(ncomp))
            else:
                stored = (None,) + tuple(c for c in range(ncomp) if live[c])
            table, refs = varying_columns(rows)
            g = FoldGroup(
                index=len(groups),
                members=members,
                steps=steps,
                table=table,
                refs=refs,
                stored=stored,
                zero=tuple(not c for c in live),
            )
            groups.append(g)
            for j, member in enumerate(members):
                at[member] = (g.index, j)
        plan = FoldPlan(groups, at, self._walk(self.root, at), singles)
        self._folds[key] = plan
        return plan

    def combine(self, grad: bool) -> Combine | None:
        """The combine program of the scene, or None.

        Every maximal small subexpression is evaluated in a loop over a table first
        (:meth:`folds` with one-member shapes); if what remains is a tree of chains (min, max,
        smin, smax, polynomial blends, negation; no loops over tables) over those results, it
        becomes a list of steps for the installation's interpreter
        (:mod:`fastsdf.backends.kernel.drive`) instead of straight-line code."""
        if grad in self._combine:
            return self._combine[grad]
        self._combine[grad] = out = self._plan_combine(grad)
        return out

    def _combine_order(self, fold: FoldPlan) -> tuple[list, dict] | None:
        """Post-order of the chains above the folded subexpressions, and the uses of each
        chain's value; None where anything else stands above them."""
        order: list[Expr] = []
        uses: dict[Expr, int] = {}
        seen: set[Expr] = set()
        stack: list[tuple] = [(self.root, False)]
        while stack:
            node, expanded = stack.pop()
            if expanded:
                order.append(node)
                continue
            if node in seen:
                continue
            seen.add(node)
            chain = self.chains.get(node)
            deps = self._plan(node)
            if node.op == "neg":  # e.g. a - b = max(a, -b) with b a large subexpression
                if deps[0].op == "const":
                    return None
            elif (
                node.op not in PROGRAM_OPS
                or chain is None
                or len(chain.items) < 2
                or any(item[0] != "node" or item[1].op == "const" for item in chain.items)
            ):
                return None
            stack.append((node, True))
            for dep in reversed(list(dict.fromkeys(deps))):
                if dep in fold.at:
                    continue
                uses[dep] = uses.get(dep, 0) + 1
                stack.append((dep, False))
        return order, uses

    def _plan_combine(self, grad: bool) -> Combine | None:
        fold = self.folds(True, grad)
        if not fold.groups or self.root in fold.at:
            return None
        found = self._combine_order(fold)
        if found is None:
            return None
        order, uses = found
        ncomp = self.ncomp
        width = 2 + ncomp * grad  # rows of an accumulator: m, gradient components, s
        free: list = []
        count = [0]
        result: dict[Expr, tuple] = {}
        zeros: dict[Expr, tuple] = {}

        def alloc() -> tuple:
            if free:
                return free.pop()
            count[0] += 1
            return ("A", (count[0] - 1) * width)

        def operand(node: Expr) -> tuple:
            folded = fold.at.get(node)
            if folded is None:
                return result[node], zeros.get(node, (False,) * ncomp)
            g, j = folded
            group = fold.groups[g]
            return ("F", g, j * group.size), group.zero

        def release(dep: Expr, acc: tuple) -> None:
            if dep in result:
                uses[dep] -= 1
                if uses[dep] == 0 and result[dep] is not acc:
                    free.append(result[dep])

        steps: list[tuple] = []
        for node in order:
            if node.op == "neg":
                arg = node.args[0]
                row, zero = operand(arg)
                acc = row if arg not in fold.at and uses[arg] == 1 else alloc()  # in place
                steps.append(("neg", row, acc, None, zero))
                result[node], zeros[node] = acc, zero
                release(arg, acc)
                continue
            acc = self._combine_chain(node, operand, uses, alloc, steps, zeros, fold)
            result[node] = acc
            for dep in dict.fromkeys(item[1] for item in self.chains[node].items):
                if dep is not node:
                    release(dep, acc)
        steps.append(("out", operand(self.root)[0], None, None, None))
        return Combine(fold, steps, count[0] * width)

    def _combine_chain(
        self,
        node: Expr,
        operand: Callable,
        uses: dict,
        alloc: Callable,
        steps: list,
        zeros: dict,
        fold: FoldPlan,
    ) -> tuple:
        """The steps of one chain; returns its accumulator."""
        chain = self.chains[node]
        operands = [item[1] for item in chain.items]
        first = operands[0]
        acc = None
        if first not in fold.at and uses[first] == 1 and sum(o is first for o in operands) == 1:
            acc = operand(first)[0]  # its last use: accumulate in place
        smooth = node.op in ("smin", "smax")
        pair = smooth and len(operands) == 2  # one fused step: blend and finish
        if acc is None:
            acc = alloc()
            steps.append(("init", operand(first)[0], acc, None, None))
        elif smooth and not pair:  # in place: only s = 1
            steps.append(("init", acc, acc, None, None))
        if chain.ordered:
            # a left fold of polynomial blends: the running value's gradient components
            # known to be zero are tracked too (the straight-line code drops their terms)
            za = operand(first)[1]
            for other in operands[1:]:
                row, zb = operand(other)
                steps.append((node.op, row, acc, node.attr, zb + za))
                za = tuple(a and b for a, b in zip(za, zb))
            zeros[node] = za
        elif pair:
            row, zero = operand(operands[1])
            steps.append((node.op + "2", row, acc, node.attr, zero))
        else:
            for other in operands[1:]:
                row, zero = operand(other)
                steps.append((node.op, row, acc, node.attr, zero))
            if smooth:
                steps.append(("fin_" + node.op, None, acc, node.attr, None))
        return acc


def lower(root: Expr, coords: Sequence[str]) -> Program:
    """The :class:`Program` of ``root`` over the coordinate symbols named ``coords``."""
    with gc_paused():  # a bulk pass over the graph (see fastsdf.expr.graph._GCPaused)
        return Program(root, coords)
