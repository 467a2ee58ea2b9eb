"""A scene-independent tape interpreter: answers a new scene at once, while its kernel compiles.

A scene's expression DAG (:mod:`fastsdf.expr.graph`) is flattened into a *tape*: a deduplicated
instruction list in topological order, each instruction an opcode, operand registers and a
constant (libfive and Fidget evaluate such tapes next to their JITs). One numba function,
:func:`_eval_par` (``@njit(cache=True)``, compiled once per installation and cached beside this
file), evaluates any tape for blocks of ``BLOCK`` points: instruction by instruction, each over
the whole block (the dispatch costs once per block, not per point), with a register file of
``BLOCK`` values (and two gradient rows) per live value. Registers are reused once their value
is dead (linear scan), so the register file follows the scene's width, not its size.

The tape computes the compiled kernel's bits (:mod:`fastsdf.backends.kernel.codegen`; tested bit
for bit, value and gradient): the same formulas for values and partial derivatives (the table
of :mod:`fastsdf.expr.ops`) in the same order; chains of ``min``/``max``/``smin``/``smax``
flattened and streamed operand by operand in the generated code's order with its tie rule (the
earlier operand wins), smooth chains as the same online log-sum-exp, loop members evaluated as
the loop does (nested chains pairwise), left folds of polynomial blends from +huge where they
open with a loop; the same branch-free ``exp``/``log``/``length`` of
:mod:`fastsdf.backends.kernel.vmath` and compiled primitives of
:mod:`fastsdf.backends.kernel.prims`; constant powers as LLVM rewrites them in the kernel.
Gradients are forward mode with the same one-sided conventions at kinks; a gradient component
is left out of a sum exactly where the generated code leaves it out (known zero), and carried
where the generated code carries it (a chain's components, even when zero). Non-finite input
points give NaN for those points only.

Runtime parameters (:func:`fastsdf.expr.graph.Param`, time ``t``) are inputs of the tape (read from
an array per call); the time derivative (``time_derivative=True``) is not offered by the tape.

Per point the tape costs several times the compiled kernel (``python -m bench.bench_tape``), so
it is for the first calls of a new scene: :class:`fastsdf.function.Function` answers through it
by default (``backend='auto'``) while the scene's kernel compiles in a background thread, and
with ``backend='tape'`` always. Since its bits are the kernel's, a call returns the same bits
before and after the kernel takes over.
"""

from __future__ import annotations

import math
import os
import subprocess
import sys
import time
from collections.abc import Sequence
from typing import Any

import numba
import numpy as np
from numba import njit, prange
from numpy.typing import ArrayLike

from fastsdf.backends.kernel import prims as _P
from fastsdf.intrinsics import select as _sel
from fastsdf.backends.kernel.vmath import vexp, vlength, vlength_grad, vlog
from fastsdf.expr.graph import Expr
from fastsdf.notice import compiling

__all__ = ["Tape", "compile_tape", "BLOCK", "interpreter_ready", "warm", "warm_in_background"]

#: Points per block: the register file (``BLOCK`` floats per live value, three rows with the
#: gradient) stays in the L1/L2 cache.
BLOCK = 256

# Opcodes. Columns of ``code``: op, dst, a, b, c, d, mask (see _Builder.emit). A chain is
# streamed as the generated code does: _CINIT (the first operand, or +-huge), one step per
# operand updating the accumulator in place (and, for smooth chains, the sum of weights in a
# register of its own made by _SINIT), and _SEND (smooth chains: m -+ log(s) / k).
(
    _CONST,
    _SYMX,
    _SYMY,
    _PARAM,
    _ADD,
    _SUB,
    _MUL,
    _DIV,
    _NEG,
    _POWC,
    _POW,
    _SQRT,
    _EXP,
    _LOG,
    _SIN,
    _COS,
    _ABS,
    _FLOOR,
    _LENGTH,
    _QMIN,
    _CMIN,
    _SELECT,
    _ELLIPSE,
    _POLYGON,
    _OUTLINE,
    _CINIT,
    _SINIT,
    _SEND,
    _MINSTEP,
    _MAXSTEP,
    _SMINSTEP,
    _SMAXSTEP,
    _ADDK,
    _SUBK,
    _KSUB,
    _MULK,
    _DIVK,
) = range(37)
# The last five take their constant as an immediate (a + k, a - k, k - a, a * k, a / k): most
# constants of a scene (transforms, sizes) then cost no instruction and no register.

_UNARY = {
    "neg": _NEG,
    "powc": _POWC,
    "sqrt": _SQRT,
    "exp": _EXP,
    "log": _LOG,
    "sin": _SIN,
    "cos": _COS,
    "abs": _ABS,
    "floor": _FLOOR,
}
_BINARY = {
    "add": _ADD,
    "sub": _SUB,
    "mul": _MUL,
    "div": _DIV,
    "pow": _POW,
    "length": _LENGTH,
    "qmin": _QMIN,
    "cmin": _CMIN,
}
_CHAINS = {"min": _MINSTEP, "max": _MAXSTEP, "smin": _SMINSTEP, "smax": _SMAXSTEP}
_STEPS = (_MINSTEP, _MAXSTEP, _SMINSTEP, _SMAXSTEP)
_HUGE = 1.7976931348623157e308


class Tape:
    """The flattened instruction list of one expression of two coordinates.

    ``tape(x, y)`` evaluates it (signed distance, negative inside, in the coordinates' units);
    ``tape(x, y, compute_gradient=True)`` returns ``(d, grad)`` with ``grad[..., 0] = dd/dx``,
    ``grad[..., 1] = dd/dy``, as :class:`fastsdf.function.Function` does. ``params`` gives values
    of runtime parameters by name (the others take their defaults; ``'t'`` is time).

    Attributes: ``code`` (one row per instruction: opcode, destination register, operand
    registers, gradient mask), ``consts`` (one constant per instruction), ``table`` (polygon
    vertices), ``nreg`` (registers), ``root`` (the result's register), ``param_names`` (the
    order of the parameter array), ``nodes`` (expression nodes evaluated).
    """

    def __init__(
        self,
        code: np.ndarray,
        consts: np.ndarray,
        table: np.ndarray,
        nreg: int,
        root: int,
        param_names: Sequence[str],
        defaults: dict,
        nodes: int,
    ):
        self.code = code
        self.consts = consts
        self.table = table
        self.nreg = nreg
        self.root = root
        self.param_names = tuple(param_names)
        self._defaults = dict(defaults)
        self.nodes = nodes

    def __len__(self) -> int:
        return int(self.code.shape[0])

    def __repr__(self) -> str:
        return f"Tape({len(self)} instructions, {self.nreg} registers)"

    def param_array(self, params: dict | None = None) -> np.ndarray:
        """The parameter values in ``param_names`` order (defaults where not given)."""
        vals = dict(self._defaults)
        vals.update(params or {})
        return np.array([float(vals.get(n, 0.0)) for n in self.param_names], dtype=np.float64)

    def run(
        self,
        xs: np.ndarray,
        ys: np.ndarray,
        out: np.ndarray,
        grad: np.ndarray | None = None,
        prm: np.ndarray | None = None,
    ) -> None:
        """Evaluate at flat float64 points into ``out`` (and ``grad``, shape (n, 2))."""
        n = xs.shape[0]
        if not n:
            return
        prm = self.param_array() if prm is None else prm
        g = grad is not None
        gout = grad if g else np.empty((0, 2))
        blocks = (n + BLOCK - 1) // BLOCK
        chunks = min(blocks, 8 * numba.get_num_threads()) if n >= 4096 else 1
        args = (self.code, self.consts, self.table, self.nreg, self.root, xs, ys, prm)
        if _eval_par.overloads:
            _eval_par(*args, out, gout, g, chunks)
            return
        with compiling("the tape interpreter"):
            _eval_par(*args, out, gout, g, chunks)

    def __call__(
        self, x: ArrayLike, y: ArrayLike, compute_gradient: bool = False, params: dict | None = None
    ) -> Any:
        from fastsdf.expr.points import as_points

        xs, ys, shape = as_points(x, y)
        n = xs.shape[0]
        out = np.empty(n)
        prm = self.param_array(params)
        if compute_gradient:
            grad = np.empty((n, 2))
            self.run(xs, ys, out, grad, prm)
            return out.reshape(shape), grad.reshape(shape + (2,))
        self.run(xs, ys, out, None, prm)
        return out.reshape(shape)


class _Builder:
    """Instructions over virtual registers (one per instruction; register allocation later)."""

    def __init__(self, symbol_names: Sequence[str]) -> None:
        self.names = tuple(symbol_names)
        self.rows: list = []  # [op, dst(virtual), a, b, c, d, mask]
        self.consts: list = []
        self.used: list = []  # per instruction: the virtual registers it reads
        self.table: list = []
        self.params: dict = {}  # name -> index
        self.defaults: dict = {}
        self.deps: list = []  # per instruction: bit 1 = depends on x, bit 2 = on y
        # per instruction: which gradient components the generated code carries (bit 1: x,
        # bit 2: y); a component it knows to be zero is left out of every sum, as there.
        self.live: list = []

    def emit(self, op, args=(), k=0.0, c=0, d=0, used=None, deps=None, live=None, args_live=None):
        """One instruction; returns its virtual register (the instruction's index). ``mask``
        bit ``2 j + comp`` says that argument j's gradient component comp is carried (may be
        nonzero); ``args_live`` overrides that per argument, ``live`` the result's."""
        args = list(args)
        mask = 0
        for j, a in enumerate(args[:3]):
            mask |= (self.live[a] if args_live is None else args_live[j]) << (2 * j)
        used = args if used is None else used
        if deps is None:
            deps = 0
            for a in used:
                deps |= self.deps[a]
        if live is None:
            live = deps if not used else 0
            for a in used:
                live |= self.live[a]
        idx = len(self.rows)
        full = args + [0] * (3 - len(args))
        self.rows.append([op, idx, full[0], full[1], full[2] if len(args) > 2 else c, d, mask])
        self.consts.append(float(k))
        self.deps.append(deps)
        self.live.append(live)
        self.used.append(list(used))
        return idx


def compile_tape(expr: Expr, symbol_names: Sequence[str]) -> Tape:
    """The :class:`Tape` of ``expr`` over the two named coordinate symbols (x, y order).

    Raises ``ValueError`` for what the tape does not evaluate (a symbol other than the two
    coordinates, a primitive whose constants depend on the coordinates)."""
    from fastsdf.backends.kernel.codegen import _Emitter

    names = tuple(symbol_names)
    planner = _Emitter(names, False, {})
    b = _Builder(names)
    reg: dict = {}
    chains: dict = {}  # id(chain node) -> _Chain
    # Depth first: each operand is emitted right before it is used (a chain's step follows its
    # operand), so values die young and few registers are live at once.
    stack = [expr]
    nodes = 0
    while stack:
        node = stack[-1]
        if id(node) in reg:
            stack.pop()
            continue
        ch = chains.get(id(node))
        if ch is None and (node.op in _CHAINS or node.op in _ORDERED):
            ch = chains[id(node)] = _Chain(planner, node)
            if ch.operands is None:  # a left fold without loops: its binary nodes
                ch = chains[id(node)] = False
        if ch:
            nxt = ch.next_operand()
            if nxt is not None and id(nxt) not in reg:
                stack.append(nxt)
                continue
            if ch.step(b, reg):
                stack.pop()
                nodes += 1
            continue
        missing = [a for a in node.args if id(a) not in reg and a.op != "const"]
        if missing:
            stack.extend(reversed(missing))
            continue
        stack.pop()
        nodes += 1
        reg[id(node)] = _emit_node(b, node, reg)
    root = reg[id(expr)]
    code, nreg = _allocate(b, root)
    return Tape(
        code,
        np.asarray(b.consts, dtype=np.float64),
        np.asarray(b.table, dtype=np.float64).reshape(-1, 2),
        nreg,
        int(code[root, 1]),
        sorted(b.params, key=lambda name: b.params[name]),
        b.defaults,
        nodes,
    )


_ORDERED = {"qmin": _QMIN, "cmin": _CMIN}
#: The generated code carries both gradient components (as variables, possibly zero).
_LIVE = 3


class _Chain:
    """One n-ary chain in the generated code's form (see ``codegen._Emitter._plan``): its
    operands in that order, whether it starts from +-huge (a chain that opens with a loop over
    a table), which operands are members of such loops, and the emission state.

    A loop member whose subexpression holds chains that the straight-line code would flatten
    (``codegen._foldable`` false) is evaluated as the loop does, by its template: node by node,
    each chain binary. Min/max/smin/smax chains: the generated code's streamed accumulator;
    left folds of polynomial blends (qmin, cmin) with loops: their binary steps, with the
    accumulator's gradient carried from the first loop on. ``operands`` is None for a left fold
    without loops (it is evaluated as its binary nodes)."""

    def __init__(self, planner: Any, node: Expr) -> None:
        from fastsdf.backends.kernel.codegen import _flatten_chain, _foldable

        self.node, self.planner = node, planner
        self.ordered = node.op in _ORDERED
        operands = _flatten_chain(node)
        self.looped: list = [False] * len(operands)
        self.huge = False
        if len(operands) > 2 or self.ordered:
            _, items = planner._plan(node)
            if self.ordered and all(item[0] == "node" for item in items):
                self.operands: Any = None  # a left fold without loops: its binary nodes
                return
            operands, self.looped = [], []
            for item in items:
                members = [item[1]] if item[0] == "node" else item[3]
                operands.extend(members)
                self.looped.extend([item[0] != "node"] * len(members))
            self.huge = items[0][0] != "node"
        self.operands = operands
        memo = planner.memo.setdefault("foldable", {})
        self.templated = [
            lp and not _foldable(m, memo) for lp, m in zip(self.looped, operands, strict=True)
        ]
        self.j = 0
        self.acc: int | None = None
        self.s: int | None = None

    def next_operand(self):
        """The operand to evaluate (through the graph) before the next step, or None."""
        j = self.j if self.acc is not None or self.huge else 0
        if j >= len(self.operands) or self.templated[j] or self.operands[j].op == "const":
            return None
        return self.operands[j]

    def _value(self, b: _Builder, j: int, reg: dict) -> int:
        if self.templated[j]:
            return _emit_template(b, self.planner, self.operands[j], reg)
        return _arg(b, self.operands[j], reg)

    def step(self, b: _Builder, reg: dict) -> bool:
        """Emit the chain's next instruction (its next operand is ready); True when done."""
        if self.ordered:
            return self._ordered_step(b, reg)
        node, op = self.node, self.node.op
        smooth = op in ("smin", "smax")
        less = op in ("min", "smin")
        if self.acc is None:  # start: the first operand, or +-huge before a loop's members
            if self.huge:
                self.acc = b.emit(_CINIT, (), _HUGE if less else -_HUGE, d=1, deps=0)
            else:
                first = self._value(b, 0, reg)
                self.acc = b.emit(_CINIT, (first,), d=0)
                self.j = 1
            if smooth:
                self.s = b.emit(_SINIT, (), 0.0 if self.huge else 1.0, deps=0)
            return False
        acc, s = self.acc, self.s
        if self.j < len(self.operands):
            v = self._value(b, self.j, reg)
            used = [acc, v] + ([s] if smooth else [])
            self.acc = b.emit(_CHAINS[op], (), node.attr if smooth else 0.0, used=used)
            b.rows[-1][2:5] = [acc, v, s if smooth else 0]
            self.j += 1
            return False
        if smooth:
            acc = b.emit(_SEND, (), node.attr, d=int(less), used=[acc, s])
            b.rows[-1][2], b.rows[-1][4] = self.acc, s
        b.live[acc] = _LIVE
        reg[id(node)] = acc
        return True

    def _ordered_step(self, b: _Builder, reg: dict) -> bool:
        node = self.node
        if self.acc is None:
            if self.huge:  # the blend of +huge and a is a
                self.acc = b.emit(_CONST, (), float(_HUGE), deps=0)
            else:
                self.acc = self._value(b, 0, reg)
                self.j = 1
            return False
        if self.j < len(self.operands):
            v = self._value(b, self.j, reg)
            looped = self.looped[self.j]
            acc_live = _LIVE if looped else b.live[self.acc]
            self.acc = b.emit(
                _ORDERED[node.op],
                (self.acc, v),
                node.attr,
                args_live=(acc_live, b.live[v]),
                live=_LIVE if looped else None,
            )
            self.j += 1
            return False
        reg[id(node)] = self.acc
        return True


def _emit_template(b: _Builder, planner: Any, member: Expr, reg: dict) -> int:
    """A loop member as the generated loop evaluates it: its template's nodes in order, each
    chain binary (the straight-line code would flatten nested chains)."""
    _, steps, _ = planner._template(member)
    local: dict = {}
    for node, _refs in steps:
        if node.op in ("sym", "param"):
            if id(node) not in reg:
                reg[id(node)] = _emit_node(b, node, reg)
            local[id(node)] = reg[id(node)]
        elif node.op in _CHAINS:
            ch = _Chain.__new__(_Chain)
            ch.node, ch.planner, ch.ordered, ch.huge = node, planner, False, False
            ch.operands = list(node.args)
            ch.looped = ch.templated = [False] * len(ch.operands)
            ch.j, ch.acc, ch.s = 0, None, None
            while not ch.step(b, local):
                pass
        else:
            local[id(node)] = _emit_node(b, node, local)
    return local[id(member)]


def _arg(b: _Builder, node: Expr, reg: dict) -> int:
    """The register of an evaluated node; a constant is loaded where it is used (no register
    lives from one use to the next)."""
    if node.op == "const":
        return b.emit(_CONST, (), node.attr, deps=0)
    return reg[id(node)]


_IMMEDIATE = {
    ("add", 1): _ADDK,
    ("add", 0): _ADDK,
    ("sub", 1): _SUBK,
    ("sub", 0): _KSUB,
    ("mul", 1): _MULK,
    ("mul", 0): _MULK,
    ("div", 1): _DIVK,
}


def _emit_node(b: _Builder, node: Expr, reg: dict) -> int:
    op = node.op
    if op in ("add", "sub", "mul", "div"):
        for j in (1, 0):  # one constant argument (two are folded when the graph is built)
            kop = _IMMEDIATE.get((op, j))
            if kop is not None and node.args[j].op == "const":
                return b.emit(kop, [reg[id(node.args[1 - j])]], node.args[j].attr)
    if op == "const":
        return b.emit(_CONST, (), node.attr, deps=0)
    if op == "sym":
        if node.attr not in b.names:
            raise ValueError(
                f"the tape evaluates expressions of {list(b.names)}, got symbol {node.attr!r}"
            )
        x = node.attr == b.names[0]
        return b.emit(_SYMX if x else _SYMY, (), deps=1 if x else 2)
    if op == "param":
        name = node.attr[0]
        if name not in b.params:
            b.params[name] = len(b.params)
            b.defaults[name] = node.attr[1]
        return b.emit(_PARAM, (), float(b.params[name]), deps=0)
    args = [_arg(b, a, reg) for a in node.args]
    if op in _UNARY:
        return b.emit(
            _UNARY[op],
            args,
            node.attr if op == "powc" else 0.0,
            deps=0 if op == "floor" else None,
            live=0 if op == "floor" else None,
        )
    if op in _BINARY:
        return b.emit(_BINARY[op], args, node.attr if op in ("qmin", "cmin") else 0.0)
    if op == "select":
        return b.emit(
            _SELECT,
            args,
            used=args,
            deps=b.deps[args[1]] | b.deps[args[2]],
            live=b.live[args[1]] | b.live[args[2]],
        )
    if op == "prim":
        kind, data = node.attr
        if any(b.deps[a] for a in args[2:]):
            raise ValueError(
                "the tape evaluates primitives whose constants do not depend on the coordinates"
            )
        if kind == "ellipse":
            return b.emit(_ELLIPSE, args[:3], d=args[3], used=args[:4])
        if kind == "polygon":
            verts = np.asarray(data, dtype=np.float64).reshape(-1, 2)
            off = len(b.table)
            b.table.extend(map(tuple, verts))
            return b.emit(_POLYGON, args[:2], c=off, d=len(verts))
        if kind == "outline":  # rows of 11 numbers, padded to 12: 6 table rows each
            rows = np.asarray(data, dtype=np.float64)
            rows = np.concatenate([rows, np.zeros((len(rows), 1))], axis=1).reshape(-1, 2)
            off = len(b.table)
            b.table.extend(map(tuple, rows))
            return b.emit(_OUTLINE, args[:2], c=off, d=len(rows) // 6)
    raise ValueError(
        f"the tape has no instruction for operation {op!r}"
        + (f" (primitive {node.attr[0]!r})" if op == "prim" else "")
    )


# Columns of code that hold registers, per opcode (the others hold data).
def _reg_columns(op):
    if op in (_CONST, _SYMX, _SYMY, _PARAM, _SINIT):
        return ()
    if op == _CINIT:
        return ()  # column a, if used, is handled with the operand list
    if op in _STEPS:
        return (2, 3, 4) if op in (_SMINSTEP, _SMAXSTEP) else (2, 3)
    if op == _SEND:
        return (2, 4)
    if op == _SELECT:
        return (2, 3, 4)
    if op == _ELLIPSE:
        return (2, 3, 4, 5)
    if op in (_POLYGON, _OUTLINE):
        return (2, 3)
    if op in _UNARY.values() or op >= _ADDK:
        return (2,)
    return (2, 3)


def _allocate(b: _Builder, root: int) -> tuple[np.ndarray, int]:
    """Physical registers by linear scan: a register is free after its value's last use. A
    chain's steps and end update the accumulator in place (and a smooth chain's sum of weights);
    other destinations never share a register with their own operands."""
    rows = b.rows
    n = len(rows)
    last = [-1] * n
    for i in range(n):
        for a in b.used[i]:
            last[a] = i
    last[root] = n
    phys = [0] * n
    free: list = []
    nreg = 0
    code = np.zeros((n, 7), dtype=np.int64)
    for i, row in enumerate(rows):
        op = row[0]
        out = list(row)
        if op in _STEPS or op == _SEND:
            r = phys[row[2]]  # in place: the previous accumulator dies here
        else:
            if free:
                r = free.pop()
            else:
                r = nreg
                nreg += 1
        phys[i] = r
        out[1] = r
        cols = _reg_columns(op)
        for col in cols:
            out[col] = phys[row[col]]
        if op == _CINIT and b.used[i]:
            out[2] = phys[row[2]]
        code[i] = out
        for a in set(b.used[i]):
            if last[a] == i and phys[a] != r:
                free.append(phys[a])
    return code, max(nreg, 1)


# ---------------------------------------------------------------------------------------------
# The interpreter (compiled once per installation).


@njit(cache=True, nogil=True, error_model="numpy")
def _block(code, consts, table, V, GX, GY, PA, PB, bx, by, prm, n, grad):
    """Run every instruction over the ``n`` points of one block (coordinates ``bx, by``)."""
    for ins in range(code.shape[0]):
        op = code[ins, 0]
        d = code[ins, 1]
        a = code[ins, 2]
        b = code[ins, 3]
        c = code[ins, 4]
        mask = code[ins, 6]
        k = consts[ins]
        lin = 0  # 1: unary rule (PA), 2: binary rule (PA, PB); 0: gradients written already
        if op == _CONST:
            for i in range(n):
                V[d, i] = k
        elif op == _SYMX:
            for i in range(n):
                V[d, i] = bx[i]
        elif op == _SYMY:
            for i in range(n):
                V[d, i] = by[i]
        elif op == _PARAM:
            pv = prm[int(k)]
            for i in range(n):
                V[d, i] = pv
        elif op == _ADD:
            for i in range(n):
                V[d, i] = V[a, i] + V[b, i]
                PA[i] = 1.0
                PB[i] = 1.0
            lin = 2
        elif op == _SUB:
            for i in range(n):
                V[d, i] = V[a, i] - V[b, i]
                PA[i] = 1.0
                PB[i] = -1.0
            lin = 2
        elif op == _MUL:
            for i in range(n):
                V[d, i] = V[a, i] * V[b, i]
                PA[i] = V[b, i]
                PB[i] = V[a, i]
            lin = 2
        elif op == _DIV:
            for i in range(n):
                r = V[a, i] / V[b, i]
                V[d, i] = r
                ib = 1.0 / V[b, i]
                PA[i] = ib
                PB[i] = -r * ib
            lin = 2
        elif op == _ADDK:
            for i in range(n):
                V[d, i] = V[a, i] + k
                PA[i] = 1.0
            lin = 1
        elif op == _SUBK:
            for i in range(n):
                V[d, i] = V[a, i] - k
                PA[i] = 1.0
            lin = 1
        elif op == _KSUB:
            for i in range(n):
                V[d, i] = k - V[a, i]
                PA[i] = -1.0
            lin = 1
        elif op == _MULK:
            for i in range(n):
                V[d, i] = V[a, i] * k
                PA[i] = k
            lin = 1
        elif op == _DIVK:
            ik = 1.0 / k
            for i in range(n):
                V[d, i] = V[a, i] / k
                PA[i] = ik
            lin = 1
        elif op == _NEG:
            for i in range(n):
                V[d, i] = -V[a, i]
                PA[i] = -1.0
            lin = 1
        elif op == _POWC:
            if k == 2.0:
                for i in range(n):
                    V[d, i] = V[a, i] * V[a, i]
                    PA[i] = 2.0 * V[a, i]
            elif k == -1.0:
                for i in range(n):
                    r = 1.0 / V[a, i]
                    V[d, i] = r
                    PA[i] = -r * r
            else:
                for i in range(n):
                    V[d, i] = _powc(V[a, i], k)
                if grad:
                    k1 = k - 1.0
                    for i in range(n):
                        PA[i] = k * _powc(V[a, i], k1)
            lin = 1
        elif op == _POW:
            for i in range(n):
                r = V[a, i] ** V[b, i]
                V[d, i] = r
                if grad:
                    PA[i] = V[b, i] * V[a, i] ** (V[b, i] - 1.0)
                    PB[i] = r * vlog(V[a, i])
            lin = 2
        elif op == _SQRT:
            for i in range(n):
                r = math.sqrt(V[a, i])
                V[d, i] = r
                PA[i] = _sel(r > 0.0, 0.5 / r, 0.0)
            lin = 1
        elif op == _EXP:
            for i in range(n):
                r = vexp(V[a, i])
                V[d, i] = r
                PA[i] = r
            lin = 1
        elif op == _LOG:
            for i in range(n):
                V[d, i] = vlog(V[a, i])
                PA[i] = 1.0 / V[a, i]
            lin = 1
        elif op == _SIN:
            for i in range(n):
                V[d, i] = math.sin(V[a, i])
                if grad:
                    PA[i] = math.cos(V[a, i])
            lin = 1
        elif op == _COS:
            for i in range(n):
                V[d, i] = math.cos(V[a, i])
                if grad:
                    PA[i] = -math.sin(V[a, i])
            lin = 1
        elif op == _ABS:
            for i in range(n):
                V[d, i] = abs(V[a, i])
                PA[i] = _sel(V[a, i] >= 0.0, 1.0, -1.0)
            lin = 1
        elif op == _FLOOR:
            for i in range(n):
                V[d, i] = np.floor(V[a, i])
        elif op == _LENGTH:
            if grad:
                for i in range(n):
                    r, p, q = vlength_grad(V[a, i], V[b, i])
                    V[d, i] = r
                    PA[i] = p
                    PB[i] = q
                lin = 2
            else:
                for i in range(n):
                    V[d, i] = vlength(V[a, i], V[b, i])
        elif op == _QMIN or op == _CMIN:
            ik = 1.0 / k
            kq = k / 4.0 if op == _QMIN else k / 6.0
            for i in range(n):
                va = V[a, i]
                vb = V[b, i]
                w = va <= vb
                t = k - abs(va - vb)
                h = _sel(t > 0.0, t, 0.0) * ik
                m = _sel(w, va, vb)
                if op == _QMIN:
                    V[d, i] = m - h * h * kq
                    o = h * 0.5
                else:
                    V[d, i] = m - h * h * h * kq
                    o = h * h * 0.5
                PA[i] = _sel(w, 1.0 - o, o)
                PB[i] = h
            if grad:  # inside the blend the weighted sum, outside the smaller one's gradient
                _blend_grad(GX, V, d, a, b, PA, PB, mask & 1, mask & 4, n)
                _blend_grad(GY, V, d, a, b, PA, PB, mask & 2, mask & 8, n)
        elif op == _SELECT:
            for i in range(n):
                V[d, i] = _sel(V[a, i] > 0.0, V[b, i], V[c, i])
            if grad:
                for i in range(n):
                    pick = V[a, i] > 0.0
                    GX[d, i] = _sel(
                        pick, GX[b, i] if mask & 4 else 0.0, GX[c, i] if mask & 16 else 0.0
                    )
                    GY[d, i] = _sel(
                        pick, GY[b, i] if mask & 8 else 0.0, GY[c, i] if mask & 32 else 0.0
                    )
        elif op == _ELLIPSE:
            e = code[ins, 5]
            for i in range(n):
                r, p, q = _P.ellipse_vg(V[a, i], V[b, i], V[c, i], V[e, i])
                V[d, i] = r
                PA[i] = p
                PB[i] = q
            lin = 2
        elif op == _POLYGON:
            verts = table[c : c + code[ins, 5]]
            for i in range(n):
                r, p, q = _P.polygon_vg(V[a, i], V[b, i], verts)
                V[d, i] = r
                PA[i] = p
                PB[i] = q
            lin = 2
        elif op == _OUTLINE:
            rows = table[c : c + 6 * code[ins, 5]].reshape(code[ins, 5], 12)
            for i in range(n):
                r, p, q = _P.outline_vg(V[a, i], V[b, i], rows)
                V[d, i] = r
                PA[i] = p
                PB[i] = q
            lin = 2
        elif op == _CINIT:  # a chain's accumulator: code[ins, 5] = 1: from +-huge
            if code[ins, 5]:
                for i in range(n):
                    V[d, i] = k
                if grad:
                    for i in range(n):
                        GX[d, i] = 0.0
                        GY[d, i] = 0.0
            else:
                for i in range(n):
                    V[d, i] = V[a, i]
                if grad:
                    for i in range(n):
                        GX[d, i] = GX[a, i]
                        GY[d, i] = GY[a, i]
        elif op == _SINIT:
            for i in range(n):
                V[d, i] = k
        elif op == _SEND:  # smooth chain's end: m -+ log(s) / k, gradient / s (c: s)
            ik = 1.0 / k
            if code[ins, 5]:
                for i in range(n):
                    V[d, i] = V[a, i] - vlog(V[c, i]) * ik
            else:
                for i in range(n):
                    V[d, i] = V[a, i] + vlog(V[c, i]) * ik
            if grad:
                for i in range(n):
                    si = 1.0 / V[c, i]
                    GX[d, i] = GX[a, i] * si
                    GY[d, i] = GY[a, i] * si
        elif op == _SMINSTEP or op == _SMAXSTEP:  # a: accumulator (= d), b: operand, c: s
            nk = -k
            less = op == _SMINSTEP
            for i in range(n):
                v = V[b, i]
                m = V[a, i]
                w = (v < m) if less else (v > m)
                e = vexp(nk * abs(v - m))
                s = V[c, i]
                V[c, i] = _sel(w, s * e + 1.0, s + e)
                if grad:
                    gx = GX[a, i]
                    gy = GY[a, i]
                    GX[d, i] = _sel(w, gx * e + GX[b, i], gx + GX[b, i] * e)
                    GY[d, i] = _sel(w, gy * e + GY[b, i], gy + GY[b, i] * e)
                V[d, i] = _sel(w, v, m)
        else:  # _MINSTEP, _MAXSTEP: the earlier operand wins ties (strict comparison)
            less = op == _MINSTEP
            for i in range(n):
                v = V[b, i]
                m = V[a, i]
                w = (v < m) if less else (v > m)
                if grad:
                    GX[d, i] = _sel(w, GX[b, i], GX[a, i])
                    GY[d, i] = _sel(w, GY[b, i], GY[a, i])
                V[d, i] = _sel(w, v, m)
        if not grad:
            continue
        if op == _CONST or op == _PARAM or op == _FLOOR:
            for i in range(n):
                GX[d, i] = 0.0
                GY[d, i] = 0.0
        elif op == _SYMX:
            for i in range(n):
                GX[d, i] = 1.0
                GY[d, i] = 0.0
        elif op == _SYMY:
            for i in range(n):
                GX[d, i] = 0.0
                GY[d, i] = 1.0
        elif lin == 1:
            _lin1(GX, d, a, PA, mask & 1, n)
            _lin1(GY, d, a, PA, mask & 2, n)
        elif lin == 2:
            # the generated code's sum: terms of known-zero components are left out
            _lin2(GX, d, a, PA, mask & 1, b, PB, mask & 4, n)
            _lin2(GY, d, a, PA, mask & 2, b, PB, mask & 8, n)


@njit(nogil=True, error_model="numpy", inline="always")
def _powc(x, e):
    """``x ** e`` as the generated code's ``x ** <literal e>`` computes it: LLVM rewrites a
    power with the constant exponent 2 into ``x * x`` and 0.5 into a square root (with the
    power's results at -0 and -inf)."""
    if e == 2.0:
        return x * x
    if e == 0.5:
        return _sel(x == -math.inf, math.inf, abs(math.sqrt(x)))
    return x**e


@njit(nogil=True, error_model="numpy", inline="always")
def _blend_grad(G, V, d, a, b, wa, h, ua, ub, n):
    """A polynomial blend's gradient component (weights ``wa``, ``1 - wa`` where ``h > 0``;
    else the smaller operand's), leaving out the terms of components known to be zero."""
    if ua and ub:
        for i in range(n):
            w = V[a, i] <= V[b, i]
            G[d, i] = _sel(
                h[i] > 0.0, G[a, i] * wa[i] + G[b, i] * (1.0 - wa[i]), _sel(w, G[a, i], G[b, i])
            )
    elif ua:
        for i in range(n):
            w = V[a, i] <= V[b, i]
            G[d, i] = _sel(h[i] > 0.0, G[a, i] * wa[i], _sel(w, G[a, i], 0.0))
    elif ub:
        for i in range(n):
            w = V[a, i] <= V[b, i]
            G[d, i] = _sel(h[i] > 0.0, G[b, i] * (1.0 - wa[i]), _sel(w, 0.0, G[b, i]))
    else:
        for i in range(n):
            G[d, i] = 0.0


@njit(nogil=True, error_model="numpy", inline="always")
def _lin1(G, d, a, pa, ua, n):
    """``G[d] = G[a] * pa`` (zero where the argument's component is known to be zero); the
    tests are outside the loops so that they vectorize."""
    if ua:
        for i in range(n):
            G[d, i] = G[a, i] * pa[i]
    else:
        for i in range(n):
            G[d, i] = 0.0


@njit(nogil=True, error_model="numpy", inline="always")
def _lin2(G, d, a, pa, ua, b, pb, ub, n):
    """``G[d] = G[a] * pa + G[b] * pb``, leaving out the terms of known-zero components."""
    if ua and ub:
        for i in range(n):
            G[d, i] = G[a, i] * pa[i] + G[b, i] * pb[i]
    elif ua:
        for i in range(n):
            G[d, i] = G[a, i] * pa[i]
    elif ub:
        for i in range(n):
            G[d, i] = G[b, i] * pb[i]
    else:
        for i in range(n):
            G[d, i] = 0.0


@njit(cache=True, parallel=True, nogil=True, error_model="numpy")
def _eval_par(code, consts, table, nreg, root, xs, ys, prm, out, gout, grad, chunks):
    """Evaluate a tape at the points ``xs, ys`` into ``out`` (and ``gout`` if ``grad``), in
    ``chunks`` chunks of blocks run in parallel."""
    npts = xs.shape[0]
    blocks = (npts + BLOCK - 1) // BLOCK
    for ch in prange(chunks):
        V = np.empty((nreg, BLOCK))
        gr = nreg if grad else 1
        GX = np.zeros((gr, BLOCK))
        GY = np.zeros((gr, BLOCK))
        PA = np.empty(BLOCK)
        PB = np.empty(BLOCK)
        bx = np.empty(BLOCK)
        by = np.empty(BLOCK)
        for blk in range(ch * blocks // chunks, (ch + 1) * blocks // chunks):
            start = blk * BLOCK
            n = min(BLOCK, npts - start)
            for i in range(n):
                x = xs[start + i]
                y = ys[start + i]
                ok = math.isfinite(x) and math.isfinite(y)
                bx[i] = x if ok else 0.0
                by[i] = y if ok else 0.0
            _block(code, consts, table, V, GX, GY, PA, PB, bx, by, prm, n, grad)
            for i in range(n):
                ok = math.isfinite(xs[start + i]) and math.isfinite(ys[start + i])
                out[start + i] = V[root, i] if ok else math.nan
                if grad:
                    gout[start + i, 0] = GX[root, i] if ok else math.nan
                    gout[start + i, 1] = GY[root, i] if ok else math.nan


def _guard():
    from fastsdf.backends.kernel.cache import guard_module

    guard_module(sys.modules[__name__])


_guard()


def interpreter_ready() -> bool:
    """Whether the interpreter runs without compiling first: compiled in this process, or found
    in numba's disk cache for this source and this machine (one small index file is read)."""
    if _eval_par.overloads:
        return True
    try:
        import llvmlite.binding as ll

        index = _eval_par._cache._cache_file._load_index()
        host = (ll.get_process_triple(), numba.config.CPU_NAME or ll.get_host_cpu_name())
        return any(tuple(key[1][:2]) == host for key in index)
    except Exception:  # an unreadable or foreign cache: not ready
        return False


def warm() -> None:
    """Compile the interpreter (or load it from numba's disk cache): one small tape, run."""
    from fastsdf.expr.graph import Symbol, sym_length

    tape = compile_tape(sym_length(Symbol("x"), Symbol("y")) - 1.0, ["x", "y"])
    tape(np.zeros(1), np.zeros(1), compute_gradient=True)


#: Seconds after which another process's claim to compile the interpreter is taken as stale.
_WARM_CLAIM_S = 900.0
_warm_started = [False]


def warm_in_background() -> bool:
    """Compile the interpreter into numba's disk cache in a separate low-priority process, so
    that later processes answer a new scene's first calls through it; this process is not
    slowed (no compiler lock, no GIL shared). Once per process, and not while another process
    claims the job (a file in the kernel cache directory). ``FASTSDF_BACKGROUND_COMPILE=0``
    turns it off. Returns whether a process was started."""
    if _warm_started[0] or os.environ.get("FASTSDF_BACKGROUND_COMPILE", "1").strip() == "0":
        return False
    _warm_started[0] = True
    if interpreter_ready():
        return False
    from fastsdf.backends.kernel.cache import cache_dir

    claim = cache_dir() / "interpreter-compiling.claim"
    try:
        claim.parent.mkdir(parents=True, exist_ok=True)
        if claim.exists() and time.time() - claim.stat().st_mtime < _WARM_CLAIM_S:
            return False
        claim.write_text(str(os.getpid()))
        package_root = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
        env = dict(os.environ, FASTSDF_QUIET="1", FASTSDF_BACKGROUND_COMPILE="0")
        env["PYTHONPATH"] = os.pathsep.join(filter(None, [package_root, env.get("PYTHONPATH")]))
        script = (
            "import os, sys\n"
            "try:\n    os.nice(19)\nexcept (AttributeError, OSError):\n    pass\n"
            "try:\n    from fastsdf.backends.vm import warm\n    warm()\n"
            "finally:\n    try:\n        os.unlink(sys.argv[1])\n    except OSError:\n"
            "        pass\n"
        )
        subprocess.Popen(
            [sys.executable, "-c", script, str(claim)],
            env=env,
            stdin=subprocess.DEVNULL,
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
            start_new_session=True,
        )
    except OSError:  # no cache directory, no process: the interpreter compiles when first used
        return False
    return True
