"""Block kernels: per-point statements laid out so that LLVM vectorizes them across points.

LLVM's loop vectorizer turns a counted innermost loop into SIMD code (4 float64 lanes with AVX2,
8 with AVX-512) when its body is inlined, free of branches and calls, and its loads and stores
are contiguous. The per-point statements of :mod:`fastsdf.backends.emit` are branch-free already
(selects for every min, max and blend); this module stages them:

* A non-parallel ``@njit`` block function evaluates ``BLOCK`` points: each run of statements
  becomes the body of ``for i in range(n)``. The parallel kernel is a tiny ``prange`` over chunks
  of blocks (long generated code inside a ``parallel=True`` body is what makes numba's compile
  time explode, so it stays out of it).
* A loop over a constant table (``for j in range(20)``: 20 boxes of one shape) becomes the
  *outer* loop: for each row j, all points of the block against operand j, then j+1. The row's
  constants are read once per row, outside the point loop. Values that live across such a loop
  (coordinates, chain accumulators) are kept in a per-chunk scratch array, one contiguous row of
  ``BLOCK`` values each (the constant distance between rows lets LLVM prove the stores and loads
  independent without runtime checks).
* The statements are rendered with the vectorisable ``exp``/``log`` and overflow-safe length of
  :mod:`fastsdf.backends.kernel.vmath` (the C library's with ``vmath=False``, for comparison).

Everything is read from the statement objects (what each defines and reads, which values are
booleans, which loops they sit in); no generated text is parsed. Non-finite input points are
evaluated at the origin and their outputs set to NaN afterwards.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np

from fastsdf.backends.code import (
    MATH,
    VMATH,
    Assign,
    Code,
    Loop,
    Store,
    Style,
    line_count,
    render_stmt,
    tables_read,
)
from fastsdf.backends.emit import Body
from fastsdf.backends.kernel.cache import hashed_import
from fastsdf.backends.kernel.layout import BLOCK
from fastsdf.backends.lower import PROGRAM_STEPS, Combine

__all__ = [
    "BLOCK",
    "block_source",
    "program_source",
    "choose_lanes",
    "drive_import",
    "vmath_import",
]

#: Bodies longer than this (generated lines) get one lane: copies would multiply compile time.
LONG_BODY_LINES = 400


def choose_lanes(stmts: list, vmath: bool = True) -> int:
    """Independent vectors in flight per loop iteration. A smooth blend is a long dependency
    chain (exp -> sum -> log -> next blend's exp) and one iteration of a loop-free body is too
    long for the CPU to overlap with the next, so two interleaved copies of the body (points i
    and i + BLOCK/2) keep the vector units busy (measured 1.8x on the seed world with AVX2).
    Bodies with a loop over a table are throughput-bound already (no gain measured) and long
    bodies would double numba's compile time: one copy."""
    if line_count(stmts, vmath) > LONG_BODY_LINES or any(isinstance(s, Loop) for s in stmts):
        return 1
    return 2


def _segments(stmts: list) -> list:
    """Top-level runs of statements (``('line', [stmts])``) and loops (``('loop', Loop)``)."""
    segs: list[tuple] = []
    for st in stmts:
        if isinstance(st, Loop):
            segs.append(("loop", st))
        elif segs and segs[-1][0] == "line":
            segs[-1][1].append(st)
        else:
            segs.append(("line", [st]))
    return segs


def _defs_uses(stmts: list, vmath: bool) -> tuple[list, list, set]:
    """Per-point names assigned, and read before being assigned, in order; also which assigned
    names hold booleans."""
    defs: dict[str, None] = {}
    uses: dict[str, None] = {}
    bools: set[str] = set()
    for st in stmts:
        for c in st.reads():
            if c.op == "var" and c.args[1] == "p":
                name = c.args[0]
                if name not in defs:
                    uses.setdefault(name)
        for name in st.defs(vmath):
            defs.setdefault(name)
            if st.boolean:
                bools.add(name)
    return list(defs), list(uses), bools


class Data:
    """What a kind's block kernels read from the call's data ``D`` after its first ``first``
    values (the time and the parameters, or a combine program): the scene's tables (``tables``:
    name -> array) and numbers (constants of its graph, its blends' ``k``), each placed where it
    is first used. The kernels' source then depends only on the scene's structure, so scenes
    that differ in these numbers share it, compiled once; the values travel with each call
    (:meth:`values`)."""

    def __init__(self, first: int, tables: dict) -> None:
        self.first, self.size, self.tables = first, first, tables
        self.parts: list = [np.zeros(first)]
        self.at: dict = {}  # a constant (by identity) or a table name -> its offset
        self.used: dict[str, str] = {}  # the current function's bindings: name -> line

    def const(self, c: Code) -> str:
        """The local name of constant ``c`` (bound in the function that uses it)."""
        if id(c) not in self.at:
            self.at[id(c)] = self.size
            self.parts.append(np.array([c.args[0]]))
            self.size += 1
        name = f"K{self.at[id(c)]}"
        self.used[name] = f"{name} = D[{self.at[id(c)]}]"
        return name

    def table(self, name: str) -> None:
        """Bind table ``name`` (a view of the data) in the current function."""
        arr = self.tables[name]
        if name not in self.at:
            self.at[name] = self.size
            self.parts.append(arr.reshape(-1))
            self.size += arr.size
        rows, cols = arr.shape
        self.used[name] = f"{name} = carray(_at(D, {self.at[name]}), ({rows}, {cols}))"

    def binds(self) -> list:
        """The current function's bindings, then a fresh start for the next one."""
        out, self.used = [f"    {line}" for _, line in sorted(self.used.items())], {}
        return out

    def values(self) -> np.ndarray:
        """The data, its first ``first`` values zero (the caller's)."""
        return np.concatenate(self.parts + [np.zeros(1)])  # (never empty)


class _Staging:
    """The per-point statements of a block, segment by segment, staged through the scratch
    array ``S``: a variable live across segments has one row per lane,
    ``S[slot * BLOCK + lane * half + i]`` (booleans stored as 0.0 / 1.0); every segment is a
    loop over the block's points (``count`` of them) that loads the rows it uses and stores
    the ones used later. ``slots`` (name -> row) is filled as rows are first used; ``fbase``
    places the rows of each fold group's stored values."""

    def __init__(
        self,
        segs: list,
        result_names: list,
        lanes: int,
        slots: dict,
        vmath: bool,
        data: Data,
        fbase: Sequence[int] = (),
        count: str | None = None,
    ):
        self.data = data
        self.lanes, self.half = lanes, BLOCK // lanes
        self.count = count or str(self.half)
        self.slots, self.fbase, self.vmath = slots, fbase, vmath
        self.info = [_defs_uses(seg[1] if seg[0] == "line" else seg[1].body, vmath) for seg in segs]
        self.bools: set[str] = set()
        for _, _, b in self.info:
            self.bools |= b
        self.later_uses: list[set[str]] = [set() for _ in segs]
        acc = set(result_names)
        for k in range(len(segs) - 1, -1, -1):
            self.later_uses[k] = set(acc)
            acc |= set(self.info[k][1])

    def at(self, name: str, k: int) -> str:
        if name not in self.slots:
            self.slots[name] = len(self.slots)
        return f"S[{self.slots[name] * BLOCK + k * self.half} + i]"

    def load(self, name: str, pad: str) -> list:
        if name in self.bools:
            return [f"{pad}{name}_{k} = {self.at(name, k)} != 0.0" for k in range(self.lanes)]
        return [f"{pad}{name}_{k} = {self.at(name, k)}" for k in range(self.lanes)]

    def store(self, name: str, pad: str) -> list:
        if name in self.bools:
            return [
                f"{pad}{self.at(name, k)} = _sel({name}_{k}, 1.0, 0.0)" for k in range(self.lanes)
            ]
        return [f"{pad}{self.at(name, k)} = {name}_{k}" for k in range(self.lanes)]

    def style(self, k: int, hoisted: dict | None = None) -> Style:
        """Lane ``k``'s names; table reads at the loop's row from hoisted names; stored
        subexpressions from their scratch rows."""
        hoisted = hoisted or {}

        def read(t: str, row: str, col: int) -> str:
            return hoisted.get((t, row, col)) or f"{t}[{row}, {col}]"

        return Style(
            VMATH if self.vmath else MATH,
            name=lambda n, scope: f"{n}_{k}" if scope == "p" else n,
            read=read,
            fold=lambda g, e: f"S[{(self.fbase[g] + e) * BLOCK} + i]",
            const=self.data.const,
        )

    def compute(self, stmts: list, pad: str, hoisted: dict | None = None) -> list:
        out = []
        styles = [self.style(k, hoisted) for k in range(self.lanes)]
        for st in stmts:
            for style in styles:
                out += [pad + ln for ln in render_stmt(st, style, _fold_store)]
        return out

    def segment(self, k: int, seg: tuple) -> list:
        """The code of segment ``k`` (``('line', stmts)`` or ``('loop', Loop)``)."""
        defs, uses, _ = self.info[k]
        if seg[0] == "line":
            pad = "        "
            code = [f"    for i in range({self.count}):"]
            for name in uses:
                code += self.load(name, pad)
            code += self.compute(seg[1], pad)
            code += [
                ln for name in defs if name in self.later_uses[k] for ln in self.store(name, pad)
            ]
            return code
        loop: Loop = seg[1]
        iv = loop.index.name
        hoisted = _hoisted(loop)
        if loop.group is not None:  # a loop over a row list: the same row for all points
            g = loop.group
            code = [
                f"    for {iv}q in range(_off[{g}], _off[{g + 1}]):",
                f"        {iv} = _act[{iv}q]",
            ]
        else:
            code = [f"    for {iv} in range({loop.count}):"]
        code += [
            f"        {name} = {t}[{iv}, {col}]"
            for (t, _, col), name in sorted(hoisted.items(), key=lambda kv: kv[1])
        ]
        for st in sorted({(s.group, s.size) for s in loop.body if isinstance(s, Store)}):
            g, size = st
            code.append(f"        fo_{g} = ({self.fbase[g]} + {iv} * {size}) * {BLOCK}")
        pad = "            "
        code.append(f"        for i in range({self.count}):")
        for name in uses:
            code += self.load(name, pad)
        code += self.compute(loop.body, pad, hoisted)
        code += [
            ln
            for name in defs
            if name in uses or name in self.later_uses[k]
            for ln in self.store(name, pad)
        ]
        return code


def _fold_store(st: Store) -> str:
    return f"S[fo_{st.group} + {st.slot * BLOCK} + i]"


def _hoisted(loop: Loop) -> dict:
    """Table elements the loop reads at its own row, by the names they are read once per row
    under (``h<table>_<column>``)."""
    iv = loop.index.name
    out: dict[tuple, str] = {}
    for st in loop.body:
        for c in st.reads():
            if c.op == "read" and c.args[1].op == "var" and c.args[1].name == iv:
                key = (c.args[0], iv, c.args[2])
                out.setdefault(key, f"h{c.args[0][2:]}_{c.args[2]}")
    return out


def _fold_layout(fold_sizes: Sequence[int]) -> tuple[dict, list]:
    """Scratch rows of a block: ``x``, ``y``, then each fold group's stored values. Returns
    ``(slots, fbase)``: the row of every name, each group's first row."""
    slots: dict = {"x": 0, "y": 1}
    fbase: list[int] = []
    for g, count in enumerate(fold_sizes):
        fbase.append(len(slots))
        slots.update((f"#F{g}.{q}", len(slots)) for q in range(count))
    return slots, fbase


_PRELUDE = [
    "    for i in range(n):",
    "        x = xs[i]",
    "        y = ys[i]",
    "        ok = (abs(x) < math.inf) & (abs(y) < math.inf)",
    "        S[i] = _sel(ok, x, 0.0)",
    f"        S[{BLOCK} + i] = _sel(ok, y, 0.0)",
]


def _prelude(pad_to: str) -> list:
    return _PRELUDE + [
        f"    for i in range(n, {pad_to}):",
        "        S[i] = 0.0",
        f"        S[{BLOCK} + i] = 0.0",
    ]


def _outputs(at: Callable, kind: str) -> list:
    """The last loop of a block: results out of the scratch rows, NaN where the point is not
    finite (the gradient as x, y pairs, or x, y, t triples with the time derivative)."""
    res = [f"        out[i] = _sel(ok, {at('r0', 0)}, math.nan)"]
    gs = _stride(kind)
    for c in range(gs if kind != "v" else 0):
        res.append(f"        grad[{gs} * i + {c}] = _sel(ok, {at(f'r{c + 1}', 0)}, math.nan)")
    return [
        "    for i in range(n):",
        "        x = xs[i]",
        "        y = ys[i]",
        "        ok = (abs(x) < math.inf) & (abs(y) < math.inf)",
    ] + res


def _with_results(body: Body) -> tuple[list, list]:
    stmts = list(body.stmts) + [Assign((f"r{k}",), e) for k, e in enumerate(body.results)]
    return stmts, [f"r{k}" for k in range(len(body.results))]


def _rows_of(segs: list) -> bool:
    """Whether the segments loop over row lists (a chain's loop groups)."""
    return any(seg[0] == "loop" and seg[1].group is not None for seg in segs)


def _tables_of(segs: list) -> list:
    return tables_read([s for seg in segs for s in (seg[1] if seg[0] == "line" else [seg[1]])])


def _stride(kind: str) -> int:
    """Floats per point of a kind's gradient array: x, y (and t with the time derivative)."""
    return 3 if kind == "vgt" else 2


def block_source(
    body: Body, kind: str, tables: dict, vmath: bool = True, parametric: bool = False
) -> tuple[str, np.ndarray]:
    """Source of ``_block_<kind>`` (a block of points; for long scenes also ``_fold_<kind>``,
    the loops over same-shape subexpressions it runs first) and of the kernels
    ``batch_<kind>_par(xs, ys, out[, grad], chunks, D)`` and ``batch_<kind>_ser(xs, ys, out[,
    grad], D)``, plain functions that hand the block function to the scene-independent kernels of
    :mod:`fastsdf.backends.kernel.drive` (and, for scenes with loops over tables, the pruned
    ``tiles_<kind>_par``), with the values they read from the call's data (see :class:`Data`;
    ``tables``: the module's tables by name). A scene with parameters or time (``parametric``)
    reads them from the data's first values too (``t``, then ``prm``, written by the caller);
    its ``'vgt'`` kernels write the gradient and dd/dt as (x, y, t) triples.

    The block's points are staged in the scratch array: coordinates copied in (non-finite ones
    replaced by 0, the block padded to ``BLOCK`` points), every compute loop reading and
    writing only rows of the scratch array at constant offsets with a constant trip count (no
    runtime alias checks, no scalar remainder loops), results copied out."""
    grad = kind != "v"
    fold_sizes = body.fold.sizes if body.fold is not None else []
    lanes = choose_lanes(body.stmts, vmath)
    assert lanes == 1 or not fold_sizes
    stmts, result_names = _with_results(body)
    segs = _segments(stmts)
    slots, fbase = _fold_layout(fold_sizes)
    data = Data(1 + body.nparams if parametric else 0, tables)
    st = _Staging(segs, result_names, lanes, slots, vmath, data, fbase)
    # The loops that store the fold groups open the body; they go to a function of their own
    # (_fold_<kind>), called before the block function: in one function with the rest, LLVM
    # stops inlining the exp/log calls of the long straight-line loop, which then stays scalar.
    nfold = 0
    while (
        fold_sizes
        and nfold < len(segs)
        and segs[nfold][0] == "loop"
        and any(isinstance(s, Store) for s in segs[nfold][1].body)
    ):
        nfold += 1
    parts = [segs[:nfold], segs[nfold:]]
    codes: list = [[], []]
    binds: list = [[], []]
    for j, part in enumerate(parts):
        for t in _tables_of(part):
            data.table(t)
        for k, seg in enumerate(part, 0 if j == 0 else nfold):
            codes[j] += st.segment(k, seg)
        if j:
            codes[j] += _outputs(st.at, kind)
        binds[j] = data.binds()
    size = max(len(slots), 1) * BLOCK
    views = ["    xs = carray(xp, (n,))", "    ys = carray(yp, (n,))", "    out = carray(op, (n,))"]
    if grad:
        views.append(f"    grad = carray(gp, ({_stride(kind)} * n,))")
    views += [f"    S = carray(sp, ({size},))", f"    D = carray(dp, ({max(data.size, 1)},))"]
    if parametric:  # the call's time and parameters
        views += ["    t = D[0]"] + [f"    _p{i} = D[{i + 1}]" for i in range(body.nparams)]

    def head(j: int) -> str:
        used = binds[j]
        if _rows_of(parts[j]):  # the row lists: all rows, or a tile's (pruning)
            used += ["    _act = ap", "    _off = fp"]
        return "\n".join(views + used + _prelude(str(BLOCK)))

    names = _KernelNames(kind, grad, size)
    rows = "_ACTG, _OFFG" if _rows_of(segs) else "_NOROWS, _NOROWS"
    fold = "_drive_nofold"
    src = ""
    if nfold:
        fold = f"_fold_{kind}_fn"
        src += _BLOCK_FN.format(
            name=f"_fold_{kind}",
            doc="The loops over same-shape subexpressions of the block function: their values "
            f"and gradients into the scratch rows (called before ``_block_{kind}``, same "
            "arguments).",
            head=head(0),
            body="\n".join(codes[0]),
        )
    src += _BLOCK_FN.format(
        name=f"_block_{kind}",
        doc=f"{'Value and gradient' if grad else 'Value'} at ``n`` (at most {BLOCK}) points from "
        f"pointers (:data:`fastsdf.backends.kernel.drive.BLOCK_SIG`); scratch ``sp[:{size}]``.",
        head=head(1),
        body="\n".join(codes[1]),
    )
    src += _BATCH.format(fold=fold, rows=rows, **names.fmt)
    if rows != "_NOROWS, _NOROWS":
        src += _TILES.format(fold=fold, grads="grad" if grad else "_NOGRAD", **names.fmt)
    return src, data.values()


class _KernelNames:
    def __init__(self, kind: str, grad: bool, size: int) -> None:
        outs = ["out"] + (["grad"] if grad else [])
        self.fmt = dict(
            kind=kind,
            size=size,
            sig=", ".join(["xs", "ys"] + outs),
            gflat=f"grad.reshape(-1), {_stride(kind)}, " if grad else "out, 1, ",
        )


_BLOCK_FN = '''

@njit(cache=True, nogil=True, error_model="numpy")
def {name}(xp, yp, op, gp, n, sp, ap, fp, dp):
    """{doc}"""
{head}
{body}


{name}_fn = _BlockFn({name})
'''

_BATCH = '''

#: Scratch floats per thread of the ``{kind}`` kernels (see :func:`fastsdf.backends.kernel.drive.scratch`).
scratch_{kind} = {size}


def batch_{kind}_par({sig}, chunks, D, S=None):
    """All points, in parallel: the installation's kernel calls ``_block_{kind}`` per block
    (``D``: the call's data, see fastsdf.backends.kernel.simd.Data; ``S``: scratch space of
    ``_max_threads() * scratch_{kind}`` floats, else allocated here)."""
    S = _drive_scratch(_max_threads() * {size}) if S is None else S
    _run_par({fold}.address, _block_{kind}_fn.address, 0, xs, ys, out, {gflat}S, {size}, chunks, _max_threads(), {rows}, D)


def batch_{kind}_ser({sig}, D, S=None):
    """All points, in this thread (``S``: at least ``scratch_{kind}`` floats)."""
    S = _drive_scratch({size}) if S is None else S
    _run_ser({fold}.address, _block_{kind}_fn.address, 0, xs, ys, out, {gflat}S, {size}, {rows}, D)
'''

_TILES = '''

def tiles_{kind}_par({sig}, order, starts, act, offs, chunks, D, S=None):
    """Points sorted by tile (tile ``t``: ``order[starts[t]:starts[t + 1]]``) in parallel
    blocks, each with its tile's row lists (``act``, ``offs[t]``: see :mod:`fastsdf.backends.prune`)."""
    S = _drive_scratch(_max_threads() * {size}) if S is None else S
    _tiles_par({fold}.address, _block_{kind}_fn.address, xs, ys, out, {grads}, S, {size}, chunks, _max_threads(), order, starts, act, offs, _ACTG.shape[0], D)
'''


def program_source(
    loops: list, kind: str, combine: Combine, tables: dict
) -> tuple[str, str, np.ndarray]:
    """``(point, blocks, data)``: the one-point function ``point_<kind>`` (with the combine
    program ``_PROG_<KIND>`` it runs, see :meth:`fastsdf.backends.lower.Program.combine`); the
    block kernels: ``_fold_<kind>`` (the loops over same-shape subexpressions, as in
    :func:`block_source`, storing into scratch rows) and ``batch_<kind>_par`` /
    ``batch_<kind>_ser``, which run it and the program through the installation's kernels
    (:func:`fastsdf.backends.kernel.drive.run_par`); and the data those read (the program's
    rows first, then the numbers of :class:`Data`; ``tables``: the module's tables by name).
    The scene's compiled code is the fold function alone: it grows with the number of distinct
    shapes, not with the primitives."""
    grad = kind == "vg"
    segs = _segments(loops)
    assert segs and all(seg[0] == "loop" for seg in segs)
    slots, fbase = _fold_layout(combine.fold.sizes)
    first = len(slots)
    rows = _program_rows(combine.steps, fbase, first, grad)
    data = Data(rows.size, tables)
    # With gradients, only the block's first nv points (its n rounded up to whole vectors, as
    # the program in fastsdf.backends.kernel.drive._lanes): a call on a few points does not pay
    # for a whole block. Not for the value alone: there LLVM vectorizes the loops worse without
    # their constant trip count (a whole block measured 1.6x slower), so they keep it.
    st = _Staging(segs, [], 1, slots, True, data, fbase, count="nv" if grad else None)
    for t in _tables_of(segs):
        data.table(t)
    code = [ln for k, seg in enumerate(segs) for ln in st.segment(k, seg)]
    binds = data.binds()
    values = data.values()
    values[: rows.size] = rows.reshape(-1)
    size = (first + combine.acc_rows) * BLOCK
    views = [
        "    xs = carray(xp, (n,))",
        "    ys = carray(yp, (n,))",
        f"    S = carray(sp, ({size},))",
        f"    D = carray(dp, ({data.size},))",
    ]
    prelude = ([f"    nv = min({BLOCK}, (n + 7) // 8 * 8)"] if grad else []) + _prelude(
        "nv" if grad else str(BLOCK)
    )
    nl = "\n"
    names = _KernelNames(kind, grad, size).fmt
    blocks = _BLOCK_FN.format(
        name=f"_fold_{kind}",
        doc="The scene's subexpressions, each in a loop over a table of its shape: "
        f"{'values and gradients' if grad else 'values'} into the scratch rows that the combine "
        "program reads.",
        head=nl.join(views + binds + prelude),
        body=nl.join(code),
    ) + _PROGRAM.format(KIND=kind.upper(), **names)
    return _program_point(loops, kind, rows, fbase, first + combine.acc_rows), blocks, values


def _program_point(loops: list, kind: str, rows: np.ndarray, fbase: list, floats: int) -> str:
    """The one-point function of a combine program: the same loops storing into a small
    array (one float per row, the program's offsets divided by BLOCK), then the program at
    one point (``rows``: the program, written into the module as ``_PROG_<KIND>``)."""
    grad = kind == "vg"
    style = Style(VMATH)

    def store(s: Store) -> str:
        idx = f"{s.index.name} * {s.size}" + (f" + {s.slot}" if s.slot else "")
        return f"F[{fbase[s.group]} + {idx}]"

    tables = [f"    {t} = {t}G" for t in sorted(tables_read(loops))]
    lines = ["    " + ln for s in loops for ln in render_stmt(s, style, store)]
    table = ",\n    ".join("[" + ", ".join(repr(float(v)) for v in r) + "]" for r in rows)
    nl = "\n"
    what = "Value and gradient (d, dd/dx, dd/dy)" if grad else "Value"
    return f'''
#: The combine program (see fastsdf.backends.kernel.drive.PROG_COLS).
_PROG_{kind.upper()} = np.array([
    {table},
], dtype=np.float64)


@njit(cache=True, nogil=True, error_model="numpy")
def point_{kind}(x, y):
    """{what} at one point: the scene's subexpressions in loops over tables, then its combine
    program (fastsdf.backends.kernel.combine)."""
    if not (math.isfinite(x) and math.isfinite(y)):
        return {"math.nan, math.nan, math.nan" if grad else "math.nan"}
{nl.join(tables)}
    F = np.empty({floats})
{nl.join(lines)}
    return _combine_point_{kind}(F, _PROG_{kind.upper()})
'''


def _program_rows(steps: list, fbase: list, first: int, grad: bool) -> np.ndarray:
    """The combine program, a row of :data:`fastsdf.backends.kernel.drive.PROG_COLS` floats
    per step (opcodes: :data:`fastsdf.backends.lower.PROGRAM_STEPS`)."""

    def row(ref: tuple) -> int:
        if ref[0] == "F":
            return (fbase[ref[1]] + ref[2]) * BLOCK
        return (first + ref[1]) * BLOCK

    table = np.zeros((len(steps), 9))
    for r, (op, operand, acc, k, zeros) in zip(table, steps):
        r[0] = PROGRAM_STEPS.index(op)
        if operand is not None:
            r[1] = row(operand)
        if acc is not None:
            r[2] = row(acc)
        if op in ("smin", "smax", "fin_smin", "fin_smax", "smin2", "smax2"):
            r[3], r[4] = -float(k), 1.0 / float(k)
        elif op in ("qmin", "cmin"):
            r[3], r[4] = float(k), 1.0 / float(k)
        if zeros and grad:
            r[5 : 5 + len(zeros)] = [float(z) for z in zeros]
    return table


_PROGRAM = '''

#: Scratch floats per thread of the ``{kind}`` kernels (see :func:`fastsdf.backends.kernel.drive.scratch`).
scratch_{kind} = {size}


def batch_{kind}_par({sig}, chunks, D, S=None):
    """All points, in parallel: the installation's kernel runs ``_fold_{kind}`` and the
    program (``D``: the program, then the scene's numbers; ``S``: scratch space of
    ``_max_threads() * scratch_{kind}`` floats, else allocated here)."""
    S = _drive_scratch(_max_threads() * {size}) if S is None else S
    _run_par(_fold_{kind}_fn.address, 0, _step_{kind}_fn.address, xs, ys, out, {gflat}S, {size}, chunks, _max_threads(), _NOROWS, _NOROWS, D)


def batch_{kind}_ser({sig}, D, S=None):
    """All points, in this thread (``S``: at least ``scratch_{kind}`` floats)."""
    S = _drive_scratch({size}) if S is None else S
    _run_ser(_fold_{kind}_fn.address, 0, _step_{kind}_fn.address, xs, ys, out, {gflat}S, {size}, _NOROWS, _NOROWS, D)
'''


def drive_import() -> str:
    """Import of the scene-independent kernels of :mod:`fastsdf.backends.kernel.drive`."""
    names = [
        "BlockFn as _BlockFn",
        "run_par as _run_par",
        "run_ser as _run_ser",
        "max_threads as _max_threads",
        "NOFOLD as _drive_nofold",
        "tiles_par as _tiles_par",
        "NOROWS as _NOROWS",
        "NOGRAD as _NOGRAD",
        "scratch as _drive_scratch",
        "element_ptr as _at",
    ]
    drive = hashed_import("fastsdf.backends.kernel.drive", names)
    return "from numba import carray\n" + drive + "\n"


def vmath_import() -> str:
    """Import of the vectorizable functions of :mod:`fastsdf.backends.kernel.vmath`."""
    names = [
        "vexp as _vexp",
        "vlog as _vlog",
        "vlog1p as _vlog1p",
        "vlength as _vlength",
        "vlength_grad as _vlength_grad",
    ]
    return hashed_import("fastsdf.backends.kernel.vmath", names) + "\n"
