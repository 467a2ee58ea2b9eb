"""The combine programs' interpreter, generated from the emitter's own chain arithmetic.

A long scene that is a tree of blends runs them as a combine program (data: one row per step,
see :meth:`fastsdf.backends.lower.Program.combine`). Its interpreter is the same for every
scene: this module writes it once per installation from the statements the straight-line code
is made of (:func:`fastsdf.backends.emit.chain_step`, :func:`~fastsdf.backends.emit.chain_finish`
and the op table's polynomial blends), so a blend's arithmetic is written once and both paths
give the same bits. What differs is only where operands live: the rows of a block's scratch
space (``step_vg``, ``step_v``: each step a loop over the block's points, vectorised) or single
floats (``combine_point_vg``, ``combine_point_v``, for the per-point functions), with ``k``
and which gradient components are known to be zero read from the program's row.

The kernels of :mod:`fastsdf.backends.kernel.drive` call the step functions by address
(:data:`fastsdf.backends.kernel.drive.STEP_SIG`), so they do not depend on this module's
compiled code; a scene's module imports this one by its name, which is its content's hash.
"""

from __future__ import annotations

from collections.abc import Callable
from types import ModuleType

from fastsdf.backends.code import VMATH, Assign, Code, Style, num, render, render_stmt, var, walk
from fastsdf.backends.emit import Val, Writer, chain_finish, chain_step, flagged
from fastsdf.backends.kernel.cache import hashed_import, load_module
from fastsdf.backends.kernel.layout import BLOCK
from fastsdf.backends.lower import PROGRAM_STEPS
from fastsdf.expr.ops import OPS

__all__ = ["combine_import", "combine_module"]

_AXES = ("x", "y")


class _Node:
    """What the op table's emitters read of a node: its op and attribute (here ``k``, read
    from the program row at run time)."""

    __slots__ = ("op", "attr")

    def __init__(self, op: str, attr: Code) -> None:
        self.op, self.attr = op, attr


class _Step:
    """The statements of one step of a program: ``loads`` (name -> (rows, index): ``'a'`` the
    operand's rows value, x, y; ``'m'`` the accumulator's m, x, y, then s), ``stmts`` and
    ``stores`` ((rows, index, expression))."""

    def __init__(self, op: str, grad: bool) -> None:
        self.loads: dict[str, tuple] = {}
        self.stores: list[tuple] = []
        self.stmts: list = []
        self.comps = _AXES if grad else ()
        grads = tuple(self._load(f"v{c}", "a", j + 1) for j, c in enumerate(self.comps))
        self.operand = Val(self._load("v", "a", 0), grads or None)
        self.cur: dict[str, Code] = {"m": self._load("c", "m", 0)}
        self.cur.update((c, self._load(f"c{c}", "m", j + 1)) for j, c in enumerate(self.comps))
        self.writer = Writer("vg" if grad else "v")
        self.zero = [var(f"z{c}", "b") for c in self.comps]
        if op == "init":
            self._store(self.operand)
            self.stores.append(("m", len(self.comps) + 1, num(1.0)))
        elif op == "neg":
            self.stmts.append(Assign(("m1",), -self.operand.v))
            self._store(Val(var("m1"), self._flag_each(lambda g: -g)))
        elif op in ("qmin", "cmin"):
            self._poly(op)
        else:
            self._chain(op)

    def _load(self, name: str, rows: str, index: int) -> Code:
        self.loads[name] = (rows, index)
        return var(name)

    def _store(self, val: Val) -> None:
        self.stores.append(("m", 0, val.v))
        self.stores += [("m", j + 1, g) for j, g in enumerate(val.grads(len(self.comps)))]

    def _flag_each(self, live: Callable) -> tuple | None:
        """Per component, ``live(component)``, or 0.0 where its flag says it is zero."""
        if not self.comps:
            return None
        pairs = zip(self.zero, self.operand.grads(len(self.comps)))
        return tuple(flagged([z], lambda dead, g=g: None if dead[0] else live(g)) for z, g in pairs)

    def _chain(self, op: str) -> None:
        """A step of a min, max or exponential chain (``smin2``: a smooth pair, blend and
        finish at once; ``fin_smin``: finish), as the straight-line code writes it."""
        nk, ik = var("nk", "b"), var("ik", "b")
        base = op[4:] if op.startswith("fin_") else op.rstrip("2")
        smooth = base in ("smin", "smax")
        if smooth:
            self.cur["s"] = (
                num(1.0) if op.endswith("2") else self._load("s", "m", len(self.comps) + 1)
            )
        if op.startswith("fin_"):
            self._store(chain_finish(self.writer, self.stmts, base, self.cur, ik, "r", self.comps))
            return
        new = {"w": "w", "e": "e", "s": "s1", "m": "m1"} | {c: f"{c}1" for c in self.comps}
        grads = self.operand.grads(len(self.comps))
        v = self.operand.v
        chain_step(
            self.writer, self.stmts, base, v, grads, self.cur, new, nk, self.comps, self.zero
        )
        done = {key: var(name) for key, name in new.items()}
        if op.endswith("2"):
            self._store(chain_finish(self.writer, self.stmts, base, done, ik, "r", self.comps))
            return
        self._store(Val(done["m"], tuple(done[c] for c in self.comps) or None))
        if smooth:
            self.stores.append(("m", len(self.comps) + 1, done["s"]))

    def _poly(self, op: str) -> None:
        """One step of a left fold of polynomial blends: the op table's own code, ``k`` read
        from the program row, the running value first."""
        comps, cur = self.comps, self.cur
        running = Val(cur["m"], tuple(cur[c] for c in comps) or None)
        emit = OPS[op].emit
        assert emit is not None  # (the polynomial blends have their code in the op table)
        node = _Node(op, var("nk", "b"))
        rule = emit(self.writer, self.stmts, node, [running, self.operand], "r")
        if not comps:
            self._store(Val(var("r")))
            return
        zacc = [var(f"za{c}", "b") for c in comps]

        def component(j: int) -> Code:
            g = (cur[comps[j]], self.operand.grads(len(comps))[j])
            return flagged(
                [zacc[j], self.zero[j]],
                lambda dead: rule([None if d else x for d, x in zip(dead, g)]),
            )

        self._store(Val(var("r"), tuple(component(j) for j in range(len(comps)))))

    def render(self, row: Callable[[str, int], str], pad: str) -> list:
        """The step's lines: the loads it reads (``row(rows, index)``), its statements, its
        stores."""
        style = Style(VMATH)
        values = [e for _, _, e in self.stores] + [c for st in self.stmts for c in st.reads()]
        read = {c.args[0] for code in values for c in walk(code) if c.op == "var"}
        out = [f"{pad}{n} = {row(*at)}" for n, at in self.loads.items() if n in read]
        out += [pad + line for st in self.stmts for line in render_stmt(st, style)]
        return out + [f"{pad}{row(rows, k)} = {render(e, style)}" for rows, k, e in self.stores]


_FLAGS = ["nk = R[3]", "ik = R[4]"]
_ZERO_FLAGS = ["zx = R[5] != 0.0", "zy = R[6] != 0.0", "zax = R[7] != 0.0", "zay = R[8] != 0.0"]


def _branches(grad: bool, row: Callable, pad: str, loop: bool) -> list:
    """One branch per opcode (the last row, ``out``, is the caller's)."""
    lines = []
    for code, op in enumerate(PROGRAM_STEPS):
        if op == "out":
            continue
        lines.append(f"{pad}{'if' if code == 0 else 'elif'} op == {code}:  # {op}")
        inner = pad + "    "
        if loop:
            lines.append(f"{inner}for i in range(nv):")
            inner += "    "
        lines += _Step(op, grad).render(row, inner)
    return lines


def _interpreter_source(grad: bool, point: bool) -> str:
    """``step_<kind>`` (one step on a block's rows, a loop over its points per opcode) or,
    with ``point``, ``combine_point_<kind>`` (the whole program at one point)."""
    kind = "vg" if grad else "v"
    what = "value and gradient" if grad else "value"
    if point:
        head = [
            f"def combine_point_{kind}(F, prog):",
            f'    """The program ``prog`` ({what}) at one point: rows are single floats '
            f'``F[row]`` (offsets divided by {BLOCK}); the statements of ``step_{kind}``."""',
            "    for p in range(prog.shape[0] - 1):",
            "        op = int(prog[p, 0])",
            f"        a = int(prog[p, 1]) // {BLOCK}",
            f"        m = int(prog[p, 2]) // {BLOCK}",
            "        R = prog[p]",
        ]
        pad = "        "
        row = lambda rows, k: f"F[{'a' if rows == 'a' else 'm'} + {k}]"
        ret = "F[a], F[a + 1], F[a + 2]" if grad else "F[a]"
        tail = [f"    a = int(prog[prog.shape[0] - 1, 1]) // {BLOCK}", f"    return {ret}"]
    else:
        head = [
            f"def step_{kind}(op, ap, mp, rp, nv):",
            f'    """One step of a combine program ({what}) on the first ``nv`` points of a '
            'block\'s rows."""',
            f"    A = carray(ap, ({(3 if grad else 1) * BLOCK},))",
            f"    M = carray(mp, ({(4 if grad else 2) * BLOCK},))",
            "    R = carray(rp, (9,))",
        ]
        pad = "    "
        row = lambda rows, k: f"{'A' if rows == 'a' else 'M'}[{k * BLOCK} + i]"
        tail = []
    flags = [pad + f for f in _FLAGS + (_ZERO_FLAGS if grad else [])]
    decorator = '@njit(cache=True, nogil=True, error_model="numpy")'
    return "\n".join([decorator, *head, *flags, *_branches(grad, row, pad, not point), *tail])


_HEAD = '''"""Generated by fastsdf: the combine programs' interpreter (see
fastsdf.backends.kernel.combine). Do not edit: the file name is the hash of this content."""
import math

from numba import carray, njit

from fastsdf.intrinsics import select as _sel
'''

_TAIL = """
#: The step functions, called by address by the kernels of fastsdf.backends.kernel.drive.
step_vg_fn = _BlockFn(step_vg, _STEP_SIG)
step_v_fn = _BlockFn(step_v, _STEP_SIG)
"""


def module_source() -> str:
    """Source of the interpreter module (the same for every scene of an installation)."""
    imports = [
        hashed_import("fastsdf.backends.kernel.vmath", ["vexp as _vexp", "vlog as _vlog"]),
        hashed_import(
            "fastsdf.backends.kernel.drive", ["BlockFn as _BlockFn", "STEP_SIG as _STEP_SIG"]
        ),
    ]
    bodies = [_interpreter_source(g, p) for p in (False, True) for g in (True, False)]
    return "\n\n\n".join([_HEAD + "\n".join(imports), *bodies, _TAIL])


_MODULE: list[ModuleType] = []


def combine_module() -> ModuleType:
    """The interpreter's module (generated and imported once per process; its functions are
    compiled once per installation, on first use)."""
    if not _MODULE:
        _MODULE.append(load_module(module_source(), prefix="fastsdf_combine"))
    return _MODULE[0]


def combine_import() -> str:
    """The line a scene's module imports the interpreter with."""
    names = ["step_vg_fn", "step_v_fn", "combine_point_vg", "combine_point_v"]
    return f"from {combine_module().__name__} import " + ", ".join(f"{n} as _{n}" for n in names)
