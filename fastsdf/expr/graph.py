"""Symbolic expression graphs: the cgraph-compatible front end of fastsdf.

An expression is an immutable, hash-consed DAG of :class:`Expr` nodes. Building the same
subexpression twice returns the same node, so identical subexpressions are shared, symbols with
the same name are the same object (``Symbol('x') is Symbol('x')``), and constants are folded at
construction. Every traversal in fastsdf is iterative, so graphs of any depth build, print and
compile without hitting Python's recursion limit.

The node operations are

    const, sym, add, sub, mul, div, neg, powc (constant exponent), pow, sqrt, exp, log, sin,
    cos, abs, min, max, length (hypot of two expressions), smin, smax (exponential smooth
    minimum / maximum with sharpness ``k``), floor, select (``a if cond > 0 else b``), qmin,
    cmin (quadratic / cubic polynomial smooth minimum with blend width ``k``) and prim (a
    primitive evaluated by a fixed compiled function of :mod:`fastsdf.backends.kernel.prims`).

Each operation is defined once, in the table of :mod:`fastsdf.expr.ops` (printing, NumPy reference,
partial derivatives, interval rule, code template); this module holds the constructors, which
fold constants and simplify. :class:`Function` (an expression bound to two coordinate symbols,
evaluated by compiled kernels) lives in :mod:`fastsdf.function` and is importable from here.

Conventions shared by the whole library: distances are in the units of the coordinates, negative
inside a shape, positive outside; gradients are with respect to the two coordinates, in the order
the symbols are given to :class:`Function`.
"""

from __future__ import annotations

import collections
import gc
import math
import numbers
import struct
import threading
import weakref
from _weakref import _remove_dead_weakref  # type: ignore[attr-defined]  # not in typeshed
from collections.abc import Callable, Sequence
from typing import Any, Literal, TypeGuard

import numpy as np

from fastsdf.expr.ops import OPS, chain_rule_numpy, fmt_const
from fastsdf.expr.quote import shown

__all__ = [
    "Expr",
    "Symbol",
    "Constant",
    "as_expr",
    "sym_sqrt",
    "sym_exp",
    "sym_log",
    "sym_sin",
    "sym_cos",
    "sym_abs",
    "sym_min",
    "sym_max",
    "sym_smin",
    "sym_smax",
    "sym_length",
    "sym_floor",
    "sym_select",
    "sym_qmin",
    "sym_cmin",
    "sym_prim",
    "substitute",
    "evaluate_numpy",
    "dag_size",
    "topological_order",
    "Param",
    "t",
    "parameters",
    "substitute_params",
]

# Operations grouped by arity; attributes (symbol name, constant exponent, smoothness k) are part
# of a node's identity.
UNARY_OPS = tuple(name for name, op in OPS.items() if op.arity == 1)
BINARY_OPS = tuple(name for name, op in OPS.items() if op.arity == 2)
LEAF_OPS = ("const", "sym", "param")
#: ``select(cond, a, b)``; ``prim(u, v, *constants)`` with attr ``(kind, data)``.
OTHER_OPS = tuple(name for name, op in OPS.items() if op.arity not in (1, 2))

# The intern table: key -> weak reference to the node. A plain dict of weak references with one
# shared callback instead of a WeakValueDictionary, whose Python-level get/set cost several
# microseconds per node (most of a primitive's construction).
_INTERN: dict = {}


class _Ref(weakref.ref):
    """A weak reference to an interned node that remembers its key (to forget it when the node
    is collected)."""

    __slots__ = ("key",)
    key: tuple


def _forget(ref: _Ref, _remove: Callable = _remove_dead_weakref, _intern: dict = _INTERN) -> None:
    # Atomic: removes the entry only if it still is this (dead) reference.
    _remove(_intern, ref.key)


_pack_double = struct.Struct("<d").pack


def _float_key(value: float) -> bytes:
    """Bit pattern of a float: distinguishes 0.0 from -0.0 and keeps NaN hashable."""
    return _pack_double(value)


_NO_SYMBOLS: frozenset = frozenset()


class _GCPaused:
    """Context manager: Python's cyclic garbage collector is paused while a bulk pass over a
    graph runs (code generation, tapes, pruning plans, building many shapes at once).

    Such a pass allocates hundreds of thousands of small objects that form no cycles; with the
    collector on, every few hundred of them trigger a collection, and a full one (which walks
    every object of the process, numba's included) comes again and again as the heap grows:
    measured, that took a third to two thirds of the pass for scenes of 1000-5000 primitives.
    Paused, the objects are examined once, at the next collection after the pass. Nested and
    concurrent uses are counted; the collector is switched back on only if it was on at the
    outermost entry."""

    _lock = threading.Lock()
    _depth = 0
    _was_enabled = False

    def __enter__(self) -> _GCPaused:
        with _GCPaused._lock:
            if _GCPaused._depth == 0:
                _GCPaused._was_enabled = gc.isenabled()
                gc.disable()
            _GCPaused._depth += 1
        return self

    def __exit__(self, *exc: object) -> Literal[False]:
        with _GCPaused._lock:
            _GCPaused._depth -= 1
            if _GCPaused._depth == 0 and _GCPaused._was_enabled:
                gc.enable()
        return False


gc_paused = _GCPaused


def _param_set(op: str, args: tuple, attr: Any) -> frozenset:
    """``(name, default)`` of the runtime parameters a new node depends on (O(1) per node, as
    :func:`_symbol_set`)."""
    if op == "param":
        return frozenset((attr,))
    out = _NO_SYMBOLS
    for a in args:
        if a.prms is not out and not a.prms <= out:
            out = a.prms if out <= a.prms else out | a.prms
    return out


def _symbol_set(op: str, args: tuple, attr: Any) -> frozenset:
    """Symbols a new node depends on, computed once at construction (O(1) per node: the sets
    of the arguments are reused when they are equal, which they almost always are)."""
    if op == "sym":
        return frozenset((attr,))
    out = _NO_SYMBOLS
    for a in args:
        if a.syms is not out and not a.syms <= out:
            out = a.syms if out <= a.syms else out | a.syms
    return out


class Expr:
    """A node of a symbolic expression DAG. Build nodes with operators and ``sym_*`` functions.

    Nodes are immutable and unique: two structurally identical expressions are the same object,
    so ``==``/``hash`` are identity-based and cheap. ``str(expr)`` gives a readable formula.
    """

    # ``lip``: a Lipschitz constant noted for the node by the modelling layer (see
    # fastsdf.expr.interval.note_lipschitz), or None; the one slot set after construction.
    # ``tree``: the number of nodes under this one counted as a tree (shared subexpressions
    # once per use), capped at TREE_CAP: the code generator's size of a subexpression.
    __slots__ = ("op", "args", "attr", "syms", "prms", "lip", "tree", "__weakref__")
    # Make NumPy scalars and arrays defer to Expr's reflected operators (np.float64(2) * x).
    __array_ufunc__ = None

    op: str
    args: tuple
    attr: Any  # a constant's value, a symbol's name, a parameter's (name, default), ...
    syms: frozenset
    prms: frozenset
    lip: float | None
    tree: int

    def __new__(cls, op: str, args: tuple = (), attr: Any = None) -> Expr:
        return _intern(op, args, attr)

    def __setattr__(self, name: str, value: object) -> None:
        raise AttributeError("Expr nodes are immutable")

    def __reduce__(self) -> tuple:
        # Flat, children-first node list: pickling a deep graph node by node would recurse
        # once per level and hit the recursion limit. Unpickling re-interns the nodes.
        return (_from_flat, (_to_flat(self),))

    # Arithmetic operators build (and fold) new nodes.
    def __add__(self, other: Expr | float) -> Expr:
        return _add(self, as_expr(other, "other"))

    def __radd__(self, other: Expr | float) -> Expr:
        return _add(as_expr(other, "other"), self)

    def __sub__(self, other: Expr | float) -> Expr:
        return _sub(self, as_expr(other, "other"))

    def __rsub__(self, other: Expr | float) -> Expr:
        return _sub(as_expr(other, "other"), self)

    def __mul__(self, other: Expr | float) -> Expr:
        return _mul(self, as_expr(other, "other"))

    def __rmul__(self, other: Expr | float) -> Expr:
        return _mul(as_expr(other, "other"), self)

    def __truediv__(self, other: Expr | float) -> Expr:
        return _div(self, as_expr(other, "other"))

    def __rtruediv__(self, other: Expr | float) -> Expr:
        return _div(as_expr(other, "other"), self)

    def __pow__(self, other: Expr | float) -> Expr:
        return _pow(self, as_expr(other, "exponent"))

    def __rpow__(self, other: Expr | float) -> Expr:
        return _pow(as_expr(other, "base"), self)

    def __neg__(self) -> Expr:
        return _neg(self)

    def __pos__(self) -> Expr:
        return self

    def __bool__(self) -> bool:
        raise TypeError(
            "a symbolic expression has no truth value; use sym_min/sym_max instead of comparisons"
        )

    @property
    def value(self) -> float:
        """The value of a constant node (raises ``TypeError`` for other nodes)."""
        if self.op != "const":
            raise TypeError(f"{self} is not a constant")
        return self.attr

    @property
    def is_const(self) -> bool:
        """True for a constant node (its value is ``self.value``)."""
        return self.op == "const"

    def symbols(self) -> set:
        """Names of the symbols this expression depends on."""
        return set(self.syms)

    def __str__(self) -> str:
        return expr_to_str(self)

    def __repr__(self) -> str:
        return f"Expr({expr_to_str(self, limit=200)})"


_object_new = object.__new__


def _slot_setter(name: str) -> Callable[[Expr, Any], None]:
    """The ``__set__`` of one of Expr's slot descriptors (``Expr.__setattr__`` refuses)."""
    return vars(Expr)[name].__set__


_set_op, _set_args, _set_attr = _slot_setter("op"), _slot_setter("args"), _slot_setter("attr")
_set_syms, _set_prms, _set_lip = _slot_setter("syms"), _slot_setter("prms"), _slot_setter("lip")
_set_tree = _slot_setter("tree")
#: Cap of the ``tree`` size of nodes (far above any size the code generator asks about).
TREE_CAP = 1 << 40


def _intern(op: str, args: tuple = (), attr: Any = None) -> Expr:
    """The unique node ``(op, args, attr)``: the existing one, or a new one interned (what
    ``Expr(op, args, attr)`` does; called directly by the constructors below)."""
    key = (op, args, _pack_double(attr) if op == "const" else attr)
    ref = _INTERN.get(key)
    if ref is not None:
        node = ref()
        if node is not None:
            return node
    node = _object_new(Expr)
    # The slots' own descriptors: __setattr__ refuses (nodes are immutable once built).
    _set_op(node, op)
    _set_args(node, args)
    _set_attr(node, attr)
    _set_lip(node, None)
    # The symbol and parameter sets of the arguments, shared when equal (almost always: O(1)
    # per node); the same sets as _symbol_set and _param_set give.
    n = len(args)
    if n == 2:
        a, b = args
        size = 1 + a.tree + b.tree
        _set_tree(node, size if size < TREE_CAP else TREE_CAP)
        sa, sb = a.syms, b.syms
        _set_syms(node, sa if sb <= sa else sb if sa <= sb else sa | sb)
        sa, sb = a.prms, b.prms
        _set_prms(node, sa if sb <= sa else sb if sa <= sb else sa | sb)
    elif n == 1:
        size = 1 + args[0].tree
        _set_tree(node, size if size < TREE_CAP else TREE_CAP)
        _set_syms(node, args[0].syms)
        _set_prms(node, args[0].prms)
    elif n:
        _set_tree(node, min(TREE_CAP, 1 + sum(a.tree for a in args)))
        _set_syms(node, _symbol_set(op, args, attr))
        _set_prms(node, _param_set(op, args, attr))
    else:
        _set_tree(node, 1)
        _set_syms(node, frozenset((attr,)) if op == "sym" else _NO_SYMBOLS)
        _set_prms(node, frozenset((attr,)) if op == "param" else _NO_SYMBOLS)
    ref = _Ref(node, _forget)
    ref.key = key
    _INTERN[key] = ref
    return node


def Symbol(name: str) -> Expr:
    """A named variable. Symbols are identified by name: ``Symbol('x') is Symbol('x')``."""
    if not isinstance(name, str) or not name.isidentifier():
        raise ValueError(f"Symbol name must be a Python identifier, got name={name!r}")
    return _intern("sym", (), name)


def Constant(value: float) -> Expr:
    """A constant node holding a float64 value."""
    return as_expr(value, "value")


def Param(name: str, default: float = 0.0) -> Expr:
    """A named runtime parameter with a default value: an expression usable wherever a number
    is (``transform(angle=Param('angle', 0.0))``, ``Circle(center=[Param('px', 0.0), 0])``).

    Compiled kernels read parameters as data: changing a value (``f(x, y, angle=0.3)``,
    ``f.with_params(angle=0.3)``, ``sim.params['angle'] = 0.3``) never recompiles, and two
    scenes that differ only in parameter values share one kernel. The default is used where no
    value is given; one scene must not give one name two defaults. The parameter named ``'t'``
    is time (:data:`t`): kernels can differentiate in it (``dd/dt``) and a particle simulation
    sets it to its own clock.
    """
    if not isinstance(name, str) or not name.isidentifier() or name.startswith("_"):
        raise ValueError(
            f"Param name must be a Python identifier not starting with '_', got name={name!r}"
        )
    if name in ("x", "y"):
        raise ValueError(f"Param name must not be a coordinate ('x' or 'y'), got name={name!r}")
    if isinstance(default, (bool, np.bool_)) or not isinstance(default, numbers.Real):
        raise TypeError(f"Param default must be a real number, got default={default!r}")
    default = float(default)
    if not math.isfinite(default):
        raise ValueError(f"Param default must be finite, got default={default!r}")
    return _intern("param", (), (name, default))


#: Time in seconds, a parameter (default 0). Scenes built with it move: ``f(x, y, t=1.5)``,
#: ``f(x, y, t=..., time_derivative=True)`` also returns ``dd/dt``, and a particle simulation
#: evaluates it at its own time (its walls push particles).
t = Param("t", 0.0)


def parameters(root: Expr) -> dict:
    """``{name: default}`` of the parameters in ``root`` (``ValueError`` if one name has two
    different defaults)."""
    out: dict = {}
    for name, default in sorted(root.prms, key=lambda p: (p[0], _float_key(p[1]))):
        if name in out and _float_key(out[name]) != _float_key(default):
            raise ValueError(
                f"parameter {name!r} is given two defaults in one scene: "
                f"{out[name]!r} and {default!r}"
            )
        out[name] = default
    return out


def substitute_params(root: Expr, values: dict) -> Expr:
    """``root`` with the parameters named in ``values`` replaced by constants (folded)."""
    new = {}
    for node in topological_order(root):
        if node.op == "param":
            name = node.attr[0]
            new[id(node)] = _intern("const", (), float(values[name])) if name in values else node
        elif not node.args:
            new[id(node)] = node
        else:
            args = tuple(new[id(a)] for a in node.args)
            new[id(node)] = (
                node if all(x is y for x, y in zip(args, node.args)) else _rebuild(node, args)
            )
    return new[id(root)]


def as_expr(value: Expr | float, name: str = "value") -> Expr:
    """Return ``value`` as an expression: nodes pass through, real numbers become constants.

    Raises ``TypeError`` naming ``name`` for anything else (strings, complex numbers, arrays).
    """
    if isinstance(value, Expr):
        return value
    if type(value) is float:
        return _intern("const", (), value)
    if isinstance(value, float):  # np.float64 (a subclass of float)
        return _intern("const", (), float(value))
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, numbers.Real):
        if (
            isinstance(value, np.ndarray)
            and value.shape == ()
            and np.issubdtype(value.dtype, np.number)
            and not np.issubdtype(value.dtype, np.complexfloating)
        ):
            return _intern("const", (), float(value))
        raise TypeError(
            f"{name} must be a real number or an expression, got {shown(value)} "
            f"of type {type(value).__name__}"
        )
    return _intern("const", (), float(value))


# ---------------------------------------------------------------------------------------------
# Constructors with constant folding and light, IEEE-safe simplification (for finite values).


def _both_const(a: Expr, b: Expr) -> bool:
    return a.op == "const" and b.op == "const"


def _fold(fn: Callable, *values: float) -> Expr:
    with np.errstate(all="ignore"):
        return _intern("const", (), float(fn(*[np.float64(v) for v in values])))


def _is(node: Expr, value: float) -> bool:
    return node.op == "const" and node.attr == value


def _offset(a: Expr) -> tuple[Expr, float]:
    """Split ``a`` into ``(base, c)`` with ``a = base + c`` for a constant ``c`` (else c = 0)."""
    if a.op in ("add", "sub") and a.args[1].op == "const":
        c = a.args[1].attr
        return a.args[0], (c if a.op == "add" else -c)
    return a, 0.0


def _add_const(base: Expr, c: float) -> Expr:
    if c == 0.0:
        return base
    # One canonical form (add a signed constant) so that shapes differing only in the sign of an
    # offset share generated code; str() prints a negative offset as a subtraction.
    return _intern("add", (base, _intern("const", (), c)))


def _add(a: Expr, b: Expr) -> Expr:
    if _both_const(a, b):
        return _fold(np.add, a.attr, b.attr)
    if _is(a, 0.0):
        return b
    if _is(b, 0.0):
        return a
    if a.op == "const":
        a, b = b, a
    if b.op == "const":
        # (u + c1) + c2 -> u + (c1 + c2): one operation instead of two, and a canonical form.
        base, c = _offset(a)
        return _add_const(base, c + b.attr)
    if b.op == "neg":
        return _sub(a, b.args[0])
    return _intern("add", (a, b))


def _sub(a: Expr, b: Expr) -> Expr:
    if _both_const(a, b):
        return _fold(np.subtract, a.attr, b.attr)
    if _is(b, 0.0):
        return a
    if _is(a, 0.0):
        return _neg(b)
    if b.op == "const":
        base, c = _offset(a)
        return _add_const(base, c - b.attr)
    if b.op == "neg":
        return _add(a, b.args[0])
    return _intern("sub", (a, b))


def _mul(a: Expr, b: Expr) -> Expr:
    if _both_const(a, b):
        return _fold(np.multiply, a.attr, b.attr)
    # Keep the constant on the right: one canonical form shares more nodes.
    if a.op == "const":
        a, b = b, a
    if b.op == "const":
        if b.attr == 1.0:
            return a
        if b.attr == 0.0:
            return b  # exact for finite a; non-finite inputs are handled by the kernels
        if b.attr == -1.0:
            return _neg(a)
        if a.op == "neg":
            return _mul(a.args[0], _intern("const", (), -b.attr))
        if a.op == "mul" and a.args[1].op == "const":
            return _mul(a.args[0], _fold(np.multiply, a.args[1].attr, b.attr))
    return _intern("mul", (a, b))


def _div(a: Expr, b: Expr) -> Expr:
    if _both_const(a, b):
        return _fold(np.divide, a.attr, b.attr)
    if _is(b, 1.0):
        return a
    if _is(b, -1.0):
        return _neg(a)
    return _intern("div", (a, b))


def _neg(a: Expr) -> Expr:
    if a.op == "const":
        return _intern("const", (), -a.attr)
    if a.op == "neg":
        return a.args[0]
    return _intern("neg", (a,))


def _pow(a: Expr, b: Expr) -> Expr:
    if _both_const(a, b):
        return _fold(np.power, a.attr, b.attr)
    if b.op == "const":
        p = b.attr
        if p == 1.0:
            return a
        if p == 0.0:
            return _intern("const", (), 1.0)
        if p == 0.5:
            return sym_sqrt(a)
        return _intern("powc", (a,), p)
    return _intern("pow", (a, b))


def _unary(op: str, fn: Callable, a: Expr | float, name: str) -> Expr:
    e = as_expr(a, name)
    if e.op == "const":
        return _fold(fn, e.attr)
    return _intern(op, (e,))


def _square_base(node: Expr) -> Expr | None:
    """``u`` if ``node`` is ``u**2`` or ``u*u``, else None."""
    if node.op == "powc" and node.attr == 2.0:
        return node.args[0]
    if node.op == "mul" and node.args[0] is node.args[1]:
        return node.args[0]
    return None


def sym_sqrt(a: Expr | float) -> Expr:
    """Square root. ``sqrt(u**2 + v**2)`` is recognised and becomes ``length(u, v)``, which does
    not overflow for huge ``u, v`` and has a defined gradient at ``u = v = 0``."""
    a = as_expr(a, "a")
    if a.op == "add":
        u, v = (_square_base(arg) for arg in a.args)
        if u is not None and v is not None:
            return sym_length(u, v)
    return _unary("sqrt", np.sqrt, a, "a")


def sym_exp(a: Expr | float) -> Expr:
    """Exponential ``e**a``."""
    return _unary("exp", np.exp, a, "a")


def sym_log(a: Expr | float) -> Expr:
    """Natural logarithm."""
    return _unary("log", np.log, a, "a")


def sym_sin(a: Expr | float) -> Expr:
    """Sine (radians)."""
    return _unary("sin", np.sin, a, "a")


def sym_cos(a: Expr | float) -> Expr:
    """Cosine (radians)."""
    return _unary("cos", np.cos, a, "a")


def sym_abs(a: Expr | float) -> Expr:
    """Absolute value. At ``a = 0`` the gradient is that of ``+a`` (the right-sided one)."""
    a = as_expr(a, "a")
    if a.op == "const":
        return _intern("const", (), abs(a.attr))
    if a.op in ("abs", "length", "sqrt", "exp"):
        return a
    if a.op == "neg":
        return sym_abs(a.args[0])
    return _intern("abs", (a,))


def sym_min(a: Expr | float, b: Expr | float) -> Expr:
    """Minimum. At a tie the gradient of ``a`` (the left operand) is returned."""
    a, b = as_expr(a, "a"), as_expr(b, "b")
    if _both_const(a, b):
        return _intern("const", (), a.attr if a.attr <= b.attr else b.attr)
    if a is b:
        return a
    return _intern("min", (a, b))


def sym_max(a: Expr | float, b: Expr | float) -> Expr:
    """Maximum. At a tie the gradient of ``a`` (the left operand) is returned."""
    a, b = as_expr(a, "a"), as_expr(b, "b")
    if _both_const(a, b):
        return _intern("const", (), a.attr if a.attr >= b.attr else b.attr)
    if a is b:
        return a
    return _intern("max", (a, b))


def sym_length(a: Expr | float, b: Expr | float) -> Expr:
    """Euclidean length ``sqrt(a**2 + b**2)`` computed without overflow.

    Where ``a = b = 0`` the gradient is that of ``a`` (for a circle's centre: the local x axis),
    so it stays finite and, for an SDF, of unit length.
    """
    a, b = as_expr(a, "a"), as_expr(b, "b")
    if _both_const(a, b):
        return _intern("const", (), float(math.hypot(a.attr, b.attr)))
    if _is(b, 0.0):
        return sym_abs(a)
    if _is(a, 0.0):
        return sym_abs(b)
    return _intern("length", (a, b))


def _param_blend(a: Expr | float, b: Expr | float, k: Expr, kind: str, sign: float) -> Expr:
    """A smooth minimum (``sign = 1``) or maximum (``-1``) whose ``k`` is an expression of
    runtime parameters, from generic operations (the blend nodes take a constant ``k``): the
    same formulas, so the same values, with gradients in x, y and t from the graph. ``k`` is
    checked > 0 at the parameters' defaults."""
    number = float(evaluate_numpy(k, {"_": np.zeros(1)})[0]) if not k.syms else math.nan
    if not number > 0 or not math.isfinite(1.0 / number):
        raise ValueError(
            f"k given by parameters must be finite and > 0 (at their defaults, "
            f"and not depend on x or y), got k={k} = {number!r}"
        )
    ea, eb = as_expr(a, "a") * sign, as_expr(b, "b") * sign
    m, gap = sym_min(ea, eb), sym_abs(ea - eb)
    if kind == "exponential":
        r = m - sym_log(1.0 + sym_exp(-k * gap)) / k
    else:
        h = sym_max(k - gap, 0.0) / k
        r = m - (k * h * h * h / 6.0 if kind == "cubic" else k * h * h / 4.0)
    return r * sign


def _is_param_k(k: object) -> TypeGuard[Expr]:
    return isinstance(k, Expr) and k.op != "const"


def _check_k(k: object, name: str = "k") -> float:
    if isinstance(k, (bool, np.bool_)) or not isinstance(k, numbers.Real):
        raise TypeError(f"{name} must be a real number, got {k!r} of type {type(k).__name__}")
    k = float(k)
    if not math.isfinite(k) or k <= 0.0:
        raise ValueError(f"{name} must be finite and > 0 for a smooth blend, got {name}={k!r}")
    if not math.isfinite(1.0 / k):  # the blend divides by k: a subnormal k gives inf and NaN
        raise ValueError(
            f"{name} is too small for a smooth blend (1/k overflows), got {name}={k!r}"
        )
    return k


def _smin_value(a: float, b: float, k: float) -> float:
    m = min(a, b)
    return m - math.log1p(math.exp(-k * abs(a - b))) / k


def sym_smin(a: Expr | float, b: Expr | float, k: Expr | float) -> Expr:
    """Exponential smooth minimum ``-log(exp(-k a) + exp(-k b)) / k`` (the notebook's smooth
    union), evaluated as ``min(a, b) - log1p(exp(-k |a - b|)) / k`` so that it never overflows.

    ``k > 0`` is the sharpness in 1/distance units; the blend deepens the result by at most
    ``log(2) / k``.
    """
    if _is_param_k(k):
        return _param_blend(a, b, k, "exponential", 1.0)
    a, b, k = as_expr(a, "a"), as_expr(b, "b"), _check_k(k)
    if _both_const(a, b):
        return _intern("const", (), _smin_value(a.attr, b.attr, k))
    return _intern("smin", (a, b), k)


def sym_smax(a: Expr | float, b: Expr | float, k: Expr | float) -> Expr:
    """Exponential smooth maximum ``log(exp(k a) + exp(k b)) / k`` (the notebook's smooth
    intersection), evaluated as ``max(a, b) + log1p(exp(-k |a - b|)) / k``."""
    if _is_param_k(k):
        return _param_blend(a, b, k, "exponential", -1.0)
    a, b, k = as_expr(a, "a"), as_expr(b, "b"), _check_k(k)
    if _both_const(a, b):
        return _intern("const", (), -_smin_value(-a.attr, -b.attr, k))
    return _intern("smax", (a, b), k)


# ---------------------------------------------------------------------------------------------
# Floor, select, the polynomial smooth minima and the generic "prim" node
# (primitives evaluated by fixed numba functions in fastsdf.backends.kernel.prims), and graph
# substitution.

#: Kinds of "prim" nodes: the numba functions ``_prims.<kind>_v``/``<kind>_vg`` evaluate them
#: and ``_prims_ref.evaluate`` is their independent NumPy reference.
PRIM_KINDS = ("ellipse", "polygon", "outline")


def sym_floor(a: Expr | float) -> Expr:
    """Largest integer ``<= a`` (as a float). Piecewise constant: its gradient is 0."""
    return _unary("floor", np.floor, a, "a")


def sym_select(cond: Expr | float, a: Expr | float, b: Expr | float) -> Expr:
    """``a`` where ``cond > 0``, else ``b`` (value and gradient of the branch taken).

    Both branches are always evaluated (branch-free), so both must be safe to compute."""
    cond, a, b = as_expr(cond, "cond"), as_expr(a, "a"), as_expr(b, "b")
    if cond.op == "const":
        return a if cond.attr > 0 else b
    if a is b:
        return a
    return _intern("select", (cond, a, b))


def _check_width(k: object, name: str = "k") -> float:
    if isinstance(k, (bool, np.bool_)) or not isinstance(k, numbers.Real):
        raise TypeError(f"{name} must be a real number, got {k!r} of type {type(k).__name__}")
    k = float(k)
    if not math.isfinite(k) or k <= 0.0:
        raise ValueError(f"{name} (the blend width) must be finite and > 0, got {name}={k!r}")
    if not math.isfinite(1.0 / k):  # the blend divides by k: a subnormal k gives inf and NaN
        raise ValueError(f"{name} (the blend width) is too small (1/k overflows), got {name}={k!r}")
    return k


def _poly_smin_value(a: float, b: float, k: float, cubic: bool) -> float:
    h = max(k - abs(a - b), 0.0) / k
    return min(a, b) - (h * h * h * k / 6.0 if cubic else h * h * k / 4.0)


def sym_qmin(a: Expr | float, b: Expr | float, k: Expr | float) -> Expr:
    """Quadratic polynomial smooth minimum with blend width ``k`` (distance units):
    ``min(a, b) - k h**2 / 4`` with ``h = max(k - |a - b|, 0) / k``.

    Exactly ``min(a, b)`` where ``|a - b| >= k``; C1 everywhere; at ``a = b`` it is ``k / 4``
    below the minimum. Its gradient is the convex combination ``(1 - h/2) grad(min operand) +
    (h/2) grad(other)``. Not associative: chains of it are nested binary operations.
    """
    if _is_param_k(k):
        return _param_blend(a, b, k, "quadratic", 1.0)
    a, b, k = as_expr(a, "a"), as_expr(b, "b"), _check_width(k)
    if _both_const(a, b):
        return _intern("const", (), _poly_smin_value(a.attr, b.attr, k, False))
    return _intern("qmin", (a, b), k)


def sym_cmin(a: Expr | float, b: Expr | float, k: Expr | float) -> Expr:
    """Cubic polynomial smooth minimum with blend width ``k``: ``min(a, b) - k h**3 / 6`` with
    ``h = max(k - |a - b|, 0) / k``; exactly ``min(a, b)`` where ``|a - b| >= k``; C2; at
    ``a = b`` it is ``k / 6`` below the minimum; gradient ``(1 - h**2/2) grad(min operand) +
    (h**2/2) grad(other)``."""
    if _is_param_k(k):
        return _param_blend(a, b, k, "cubic", 1.0)
    a, b, k = as_expr(a, "a"), as_expr(b, "b"), _check_width(k)
    if _both_const(a, b):
        return _intern("const", (), _poly_smin_value(a.attr, b.attr, k, True))
    return _intern("cmin", (a, b), k)


def sym_prim(
    kind: str, u: Expr | float, v: Expr | float, *constants: Any, data: Any = None
) -> Expr:
    """A primitive evaluated by a fixed compiled function: ``kind`` (one of ``PRIM_KINDS``) at
    local coordinates ``(u, v)`` (expressions), with numeric ``constants`` (become table columns
    when same-kind primitives are folded into a loop) and hashable structural ``data`` (e.g. a
    polygon's vertices, part of the node's shape). The code generator applies the chain rule
    from ``(d, dd/du, dd/dv)`` to the coordinates."""
    if kind not in PRIM_KINDS:
        raise ValueError(f"kind must be one of {PRIM_KINDS}, got kind={kind!r}")
    # A constant may also be an expression of runtime parameters (an ellipse's axes).
    consts = tuple(
        c
        if isinstance(c, Expr) and c.op != "const" and not c.syms
        else as_expr(float(c), "constant")
        for c in constants
    )
    return _intern("prim", (as_expr(u, "u"), as_expr(v, "v")) + consts, (kind, data))


def _rebuild(node: Expr, args: tuple) -> Expr:
    """``node``'s operation applied to new arguments, through the folding constructors."""
    op = node.op
    if op in ("neg", "sqrt", "exp", "log", "sin", "cos", "abs", "floor"):
        return {
            "neg": _neg,
            "sqrt": sym_sqrt,
            "exp": sym_exp,
            "log": sym_log,
            "sin": sym_sin,
            "cos": sym_cos,
            "abs": sym_abs,
            "floor": sym_floor,
        }[op](args[0])
    if op == "powc":
        return _pow(args[0], _intern("const", (), node.attr))
    if op in ("add", "sub", "mul", "div", "pow", "min", "max", "length"):
        return {
            "add": _add,
            "sub": _sub,
            "mul": _mul,
            "div": _div,
            "pow": _pow,
            "min": sym_min,
            "max": sym_max,
            "length": sym_length,
        }[op](*args)
    if op in ("smin", "smax", "qmin", "cmin"):
        return {"smin": sym_smin, "smax": sym_smax, "qmin": sym_qmin, "cmin": sym_cmin}[op](
            args[0], args[1], node.attr
        )
    if op == "select":
        return sym_select(*args)
    return Expr(op, args, node.attr)  # prim (constant arguments stay constants)


def substitute(root: Expr, mapping: dict) -> Expr:
    """``root`` with each symbol named in ``mapping`` replaced by an expression (or number).

    Iterative (no recursion limit); rebuilt nodes go through the folding constructors, and
    nodes that do not depend on a replaced symbol are shared, not copied.
    """
    mapping = {name: as_expr(e, f"mapping[{name!r}]") for name, e in mapping.items()}
    names = frozenset(mapping)
    new = {}
    for node in topological_order(root):
        if node.op == "sym":
            new[id(node)] = mapping.get(node.attr, node)
        elif not (node.syms & names):
            new[id(node)] = node
        else:
            args = tuple(new[id(a)] for a in node.args)
            new[id(node)] = (
                node if all(x is y for x, y in zip(args, node.args)) else _rebuild(node, args)
            )
    return new[id(root)]


# ---------------------------------------------------------------------------------------------
# Traversal and printing (iterative: no recursion-depth limit).


def topological_order(root: Expr) -> list:
    """All nodes reachable from ``root``, each once, children before parents."""
    # Nodes hash by identity: sets of nodes, not of id()s (no call per lookup).
    order: list[Expr] = []
    seen: set[Expr] = set()
    append, add = order.append, seen.add
    stack = [(root, False)]
    pop, push = stack.pop, stack.append
    while stack:
        node, expanded = pop()
        if expanded:
            append(node)
            continue
        if node in seen:
            continue
        add(node)
        push((node, True))
        args = node.args
        if args:
            for arg in reversed(args):
                if arg not in seen:
                    push((arg, False))
    return order


def _to_flat(root: Expr) -> tuple:
    """``root``'s DAG as a tuple of ``(op, arg_indices, attr)``, children first, root last."""
    index: dict[int, int] = {}
    flat: list[tuple] = []
    for node in topological_order(root):
        index[id(node)] = len(flat)
        flat.append((node.op, tuple(index[id(a)] for a in node.args), node.attr))
    return tuple(flat)


def _from_flat(flat: tuple) -> Expr:
    """Inverse of :func:`_to_flat` (the nodes are interned: same graph, same node objects)."""
    nodes: list[Expr] = []
    for op, args, attr in flat:
        nodes.append(Expr(op, tuple(nodes[i] for i in args), attr))
    return nodes[-1]


def expr_to_str(root: Expr, limit: int | None = None) -> str:
    if limit is None:
        nodes = topological_order(root)
    else:
        nodes = _near_root(root, limit + 1)
    text: dict[Expr, str] = {}
    for node in nodes:
        op = node.op
        if op == "const":
            s = fmt_const(node.attr)
        elif op == "sym":
            s = node.attr
        elif op == "param":
            s = node.attr[0]
        else:
            s = OPS[op].fmt(node, [text.get(a, "") for a in node.args])
        # With a limit only the first `limit` characters are kept: cutting every part keeps that
        # prefix exact and makes printing a deep chain linear, not quadratic, in its depth.
        text[node] = s if limit is None else s[: limit + 1]
    out = text[root]
    if limit is not None and len(out) > limit:
        out = out[: limit - 3] + "..."
    return out


def _near_root(root: Expr, depth: int) -> list:
    """The nodes whose printed text can reach into the first ``depth`` characters of ``root``'s,
    children first. Every operation prints at least one character before each argument
    (``min(``, ``(``), except ``powc`` (``u**2``): a node at ``d`` such levels below the root
    starts at character ``d`` or later, and deeper nodes (printed as empty strings by
    :func:`expr_to_str`) cannot change the first ``depth`` characters. A 0-1 breadth-first search
    finds each node's smallest such depth; printing a long scene then costs O(depth), not
    O(nodes)."""
    dist = {root: 0}
    queue = collections.deque([root])
    while queue:
        node = queue.popleft()
        d = dist[node]
        w = 0 if node.op == "powc" else 1
        if d + w > depth:
            continue
        for a in node.args:
            old = dist.get(a)
            if old is None or d + w < old:
                dist[a] = d + w
                if w:
                    queue.append(a)
                else:
                    queue.appendleft(a)
    # children first, among the kept nodes
    order, seen = [], set()
    stack = [(root, False)]
    while stack:
        node, expanded = stack.pop()
        if expanded:
            order.append(node)
            continue
        if node in seen:
            continue
        seen.add(node)
        stack.append((node, True))
        for a in reversed(node.args):
            if a not in seen and a in dist and dist[a] <= depth:
                stack.append((a, False))
    return order


# ---------------------------------------------------------------------------------------------
# Reference evaluation with NumPy (the seed's approach: one array operation per node).


def dag_size(root: Expr, limit: int) -> int:
    """Distinct nodes under ``root``, counted up to ``limit + 1``."""
    seen: set[int] = set()
    stack = [root]
    while stack and len(seen) <= limit:
        node = stack.pop()
        if id(node) not in seen:
            seen.add(id(node))
            stack.extend(node.args)
    return len(seen)


def evaluate_numpy(
    root: Expr,
    symbols: dict,
    compute_gradient: bool = False,
    params: dict | None = None,
    order: Sequence[Expr] | None = None,
) -> Any:
    """Evaluate ``root`` with NumPy, one whole-array operation per node.

    ``symbols`` maps symbol names to arrays of equal shape. With ``compute_gradient`` the result
    is ``(value, [d/d s for s in symbol order])`` by forward-mode differentiation. A parameter
    (:func:`Param`) named in ``symbols`` is treated as a symbol (so ``{'x': .., 'y': .., 't': ..}``
    also differentiates in time); the others take their value from ``params`` or their default.
    ``order``: every node under ``root``, arguments first (a lowered scene's
    :attr:`fastsdf.backends.lower.Program.nodes`; found here if not given). This is the
    independent reference the compiled kernels are tested against, and the baseline the
    benchmarks time them against; it follows the same tie rules as the kernels.
    """
    names = list(symbols)
    shape = np.broadcast(*[np.asarray(v) for v in symbols.values()]).shape
    zero = np.zeros(shape)
    val: dict[int, np.ndarray] = {}
    grad: dict[int, list | None] = {}
    with np.errstate(all="ignore"):
        for node in topological_order(root) if order is None else order:
            i, op, a = id(node), node.op, node.args
            av = [val[id(c)] for c in a]
            ag: list | None = [grad[id(c)] for c in a] if compute_gradient else None
            g: list | None
            if op == "const":
                v = np.full(shape, node.attr)
                g = [zero] * len(names)
            elif op == "sym":
                if node.attr not in symbols:
                    raise ValueError(f"no value given for symbol {node.attr!r}")
                v = np.broadcast_to(np.asarray(symbols[node.attr], dtype=np.float64), shape)
                g = [np.ones(shape) if n == node.attr else zero for n in names]
            elif op == "param":
                name = node.attr[0]
                if name in symbols:
                    v = np.broadcast_to(np.asarray(symbols[name], dtype=np.float64), shape)
                else:
                    v = np.full(shape, float((params or {}).get(name, node.attr[1])))
                g = [np.ones(shape) if n == name else zero for n in names]
            else:
                v, rule = OPS[op].np(node, av, compute_gradient)
                g = chain_rule_numpy(rule, ag, v) if ag is not None else None
            val[i] = v
            if compute_gradient:
                grad[i] = g
    if compute_gradient:
        return val[id(root)], grad[id(root)]
    return val[id(root)]
