"""Expression graphs as plain data (lists, strings, numbers) and back, without pickle.

:class:`GraphWriter` collects the nodes of one or more expressions into one children-first
node list (shared subexpressions once); :func:`graph_from_data` rebuilds the nodes from such a
list. A node is ``[op, [argument indices], attr, lip]``: ``attr`` is a constant's value (a
number, or for a non-finite one the hex of its 8 bytes), a symbol's name, a parameter's
``[name, default]``, a constant exponent or blend ``k`` (a number), a primitive's ``[kind,
data]`` (``data``: None or nested lists of numbers), else None; ``lip`` is the Lipschitz
constant noted for the node (see :func:`fastsdf.expr.interval.note_lipschitz`) or None.

Reading checks every node before building it (a known operation, its number of arguments,
arguments that come earlier in the list, an attribute of the operation's type: symbol and
parameter names are identifiers, primitive kinds are known ones), because the compiled kernels
are generated from the graph: a list read from a file never puts text of its own into
generated code. Nodes are rebuilt by the interning constructors (:func:`~fastsdf.expr.graph.Symbol`,
:func:`~fastsdf.expr.graph.Param`, :func:`~fastsdf.expr.graph.Constant`,
:class:`~fastsdf.expr.graph.Expr`), so a graph read back is the same node objects as the one
written when both live in one process, and the same graph (same generated code) in another.
"""

from __future__ import annotations

import math
import numbers
import struct
from typing import Any

from fastsdf.expr.graph import PRIM_KINDS, Constant, Expr, Param, Symbol, topological_order
from fastsdf.expr.interval import note_lipschitz
from fastsdf.expr.ops import OPS

__all__ = ["GraphWriter", "graph_to_data", "graph_from_data"]

# Operations whose attribute is a number (a constant exponent, a blend's k).
_NUMBER_ATTR = ("powc", "smin", "smax", "qmin", "cmin")


def _float_out(value: float) -> float | str:
    """A float as JSON can hold it exactly: itself when finite, else its bytes in hex."""
    return value if math.isfinite(value) else struct.pack("<d", value).hex()


def _float_in(value: Any, what: str) -> float:
    if isinstance(value, str):
        try:
            raw = bytes.fromhex(value)
        except ValueError:
            raw = b""
        if len(raw) != 8:
            raise ValueError(f"{what}: {value!r} is not a number")
        return float(struct.unpack("<d", raw)[0])
    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        raise ValueError(f"{what}: {value!r} is not a number")
    return float(value)


def _structure_out(data: Any) -> Any:
    if isinstance(data, tuple):
        return [_structure_out(d) for d in data]
    if isinstance(data, float):
        return _float_out(data)
    return data


def _structure_in(data: Any, what: str) -> Any:
    """A primitive's structural data: None, or nested tuples of numbers."""
    if data is None:
        return None
    if isinstance(data, list):
        return tuple(_structure_in(d, what) for d in data)
    if isinstance(data, str):
        return _float_in(data, what)
    if isinstance(data, bool) or not isinstance(data, (int, float)):
        raise ValueError(f"{what}: {data!r} is not a number")
    return data


class GraphWriter:
    """Nodes of expressions as one children-first list of plain data (:attr:`nodes`);
    :meth:`add` gives the index of an expression's root in it."""

    def __init__(self) -> None:
        self.nodes: list[list] = []
        self._index: dict[int, int] = {}
        self._keep: list[Expr] = []  # the nodes indexed by id() stay alive while written

    def add(self, root: Expr) -> int:
        """Append the nodes of ``root`` not written yet; the index of ``root``."""
        if not isinstance(root, Expr):
            raise TypeError(f"root must be an Expr, got {root!r}")
        index = self._index
        if id(root) in index:
            return index[id(root)]
        for node in topological_order(root):
            if id(node) in index:
                continue
            op, attr = node.op, node.attr
            if op == "const" or op in _NUMBER_ATTR:
                out: Any = _float_out(attr)
            elif op == "param":
                out = [attr[0], _float_out(attr[1])]
            elif op == "prim":
                out = [attr[0], _structure_out(attr[1])]
            else:
                out = attr
            args = [index[id(a)] for a in node.args]
            index[id(node)] = len(self.nodes)
            self._keep.append(node)
            lip = None if node.lip is None else _float_out(node.lip)
            self.nodes.append([op, args, out, lip])
        return index[id(root)]


def graph_to_data(root: Expr) -> list:
    """The nodes of ``root`` as plain data, children first, ``root`` last (see the module)."""
    writer = GraphWriter()
    writer.add(root)
    return writer.nodes


def _node(op: Any, args: tuple, attr: Any, what: str) -> Expr:
    if op == "const":
        if args:
            raise ValueError(f"{what}: a constant takes no arguments")
        return Constant(_float_in(attr, what))
    if op == "sym":
        if args or not isinstance(attr, str):
            raise ValueError(f"{what}: a symbol is a name without arguments, got {attr!r}")
        return Symbol(attr)
    if op == "param":
        if args or not (isinstance(attr, list) and len(attr) == 2 and isinstance(attr[0], str)):
            raise ValueError(f"{what}: a parameter is [name, default], got {attr!r}")
        return Param(attr[0], _float_in(attr[1], what))
    spec = OPS.get(op) if isinstance(op, str) else None
    if spec is None:
        raise ValueError(f"{what}: unknown operation {op!r}")
    if op == "prim":
        if len(args) < 2 or not (isinstance(attr, list) and len(attr) == 2):
            raise ValueError(f"{what}: a primitive is [kind, data] of (u, v, *constants)")
        if attr[0] not in PRIM_KINDS:
            raise ValueError(f"{what}: unknown primitive kind {attr[0]!r}")
        return Expr(op, args, (attr[0], _structure_in(attr[1], what)))
    if len(args) != spec.arity:
        raise ValueError(f"{what}: {op} takes {spec.arity} argument(s), got {len(args)}")
    if op in _NUMBER_ATTR:
        return Expr(op, args, _float_in(attr, what))
    if attr is not None:
        raise ValueError(f"{what}: {op} takes no attribute, got {attr!r}")
    return Expr(op, args, None)


def graph_from_data(nodes: Any) -> list:
    """The nodes written by :class:`GraphWriter` (or :func:`graph_to_data`), rebuilt in
    their order (the root of a single graph is the last). A ``ValueError`` names the first
    node that is not a valid node of a graph."""
    if not isinstance(nodes, list):
        raise ValueError(f"an expression graph is a list of nodes, got {type(nodes).__name__}")
    out: list[Expr] = []
    for k, entry in enumerate(nodes):
        what = f"graph node {k}"
        if not (isinstance(entry, list) and len(entry) == 4 and isinstance(entry[1], list)):
            raise ValueError(f"{what}: expected [op, [arguments], attr, lip], got {entry!r}")
        op, arg_idx, attr, lip = entry
        for i in arg_idx:
            if isinstance(i, bool) or not isinstance(i, int) or not 0 <= i < k:
                raise ValueError(f"{what}: argument {i!r} is not an earlier node")
        node = _node(op, tuple(out[i] for i in arg_idx), attr, what)
        if lip is not None:
            bound = _float_in(lip, what)
            if not bound >= 0:
                raise ValueError(f"{what}: Lipschitz constant {lip!r} is not >= 0")
            note_lipschitz(node, bound)
        out.append(node)
    return out
