"""Block kernels: generated per-point code shaped so that LLVM vectorizes it across points.

LLVM's loop vectorizer turns a counted innermost loop into SIMD code (4 float64 lanes with AVX2,
8 with AVX-512) when its body is inlined, free of branches and calls, and its loads and stores
are contiguous. The per-point code of :mod:`fastsdf.backends.kernel.codegen` is branch-free already
(selects for every min, max and blend); this module re-arranges it:

* A non-parallel ``@njit`` block function evaluates ``BLOCK`` points: the per-point statements
  become the body of ``for i in range(n)``. The parallel kernel is a tiny ``prange`` over chunks
  of blocks (long generated code inside a ``parallel=True`` body is what makes numba's compile
  time explode, so it stays out of it).
* A folded loop over a constant table (``for j in range(20)``: 20 boxes of one shape) becomes the
  *outer* loop: for each row j, all points of the block against operand j, then j+1. The row's
  constants are read once per row, outside the point loop. Values that live across such a loop
  (coordinates, chain accumulators) are kept in a per-chunk scratch array, one contiguous row of
  ``BLOCK`` values each (the constant distance between rows lets LLVM prove the stores and loads
  independent without runtime checks).
* ``math.exp``/``math.log``/``math.log1p`` (scalar calls into the C library) are replaced by the
  branch-free :mod:`fastsdf.backends.kernel.vmath` functions, and the overflow-safe ``length`` by
  its branch-free form, unless ``vmath=False`` (kept to compare against the C library).

Non-finite input points are evaluated at the origin and their outputs set to NaN afterwards.
"""

from __future__ import annotations

import re
from collections.abc import Callable, Sequence

__all__ = [
    "BLOCK",
    "block_source",
    "program_source",
    "choose_lanes",
    "drive_import",
    "vectorizable",
    "vmath_import",
]

from fastsdf.backends.kernel.cache import hashed_import
from fastsdf.backends.kernel.layout import BLOCK

#: Bodies longer than this (generated lines) get one lane: copies would multiply compile time.
LONG_BODY_LINES = 400

_VAR = re.compile(r"\b(?:[a-z]\d+[a-z]*|x|y)\b")
_TABLE_READ = re.compile(r"\b(_T\d+)\[(i\d+), (\d+)\]")
_COMPARE = re.compile(r"(?<![<>=!])(?:<=|>=|==|!=|<|>)(?![<>=])")
_LENGTH_IF = re.compile(r"^if not \(1e-150 < (\w+) < 1e150\):$")
_HYPOT = re.compile(r"^(\w+) = math\.hypot\((.*)\)$")
_SQRT = re.compile(r"^\s*(\w+) = math\.sqrt\(")


def _split_args(text: str) -> list:
    """Arguments of a call's argument text, split at top-level commas."""
    out, depth, cur = [], 0, ""
    for ch in text:
        if ch == "," and depth == 0:
            out.append(cur.strip())
            cur = ""
            continue
        depth += ch == "("
        depth -= ch == ")"
        cur += ch
    out.append(cur.strip())
    return out


def vectorizable(lines: list) -> list:
    """The statements with the C library's exp/log/log1p and the branchy overflow-safe length
    (and its partials) replaced by the branch-free versions of
    :mod:`fastsdf.backends.kernel.vmath`."""
    out: list[str] = []
    i = 0
    sqrt_at: dict = {}  # variable -> index in out of its latest "v = math.sqrt(...)" (linear time)

    def push(line):
        m = _SQRT.match(line)
        if m:
            sqrt_at[m.group(1)] = len(out)
        out.append(line)

    while i < len(lines):
        line = lines[i]
        stripped = line.lstrip()
        indent = line[: len(line) - len(stripped)]
        m = _LENGTH_IF.match(stripped)
        if m and i + 1 < len(lines):
            r = m.group(1)
            h = _HYPOT.match(lines[i + 1].strip())
            j = i + 1
            while j < len(lines) and len(lines[j]) - len(lines[j].lstrip()) > len(indent):
                j += 1
            back = sqrt_at.get(r)
            if h and h.group(1) == r and back is not None:
                a, b = _split_args(h.group(2))
                tail = out[back + 1 :]
                del out[back:]
                for name in [k for k, at in sqrt_at.items() if at >= back]:
                    del sqrt_at[name]
                if any(t.strip().startswith(f"{r}i = ") for t in tail):
                    out.append(f"{indent}{r}, {r}p, {r}q = _vlength_grad({a}, {b})")
                else:
                    out.append(f"{indent}{r} = _vlength({a}, {b})")
                for t in tail:
                    if not t.strip().startswith((f"{r}i = ", f"{r}p = ", f"{r}q = ")):
                        push(t)
                i = j
                continue
        line = (
            line.replace("math.exp(", "_vexp(")
            .replace("math.log1p(", "_vlog1p(")
            .replace("math.log(", "_vlog(")
        )
        push(line)
        i += 1
    return out


def _split(lines: list) -> list:
    """Top-level segments: ``('line', [stmts])`` runs and ``('loop', header, [body])`` loops
    (an ``if`` statement stays with its indented block inside a run)."""
    segs: list[tuple] = []
    i = 0
    while i < len(lines):
        line = lines[i]
        j = i + 1
        while j < len(lines) and lines[j].startswith(" "):
            j += 1
        block = [ln[4:] for ln in lines[i + 1 : j]]
        if line.startswith("for "):
            segs.append(("loop", line, block))
        else:
            if not segs or segs[-1][0] != "line":
                segs.append(("line", []))
            segs[-1][1].extend([line] + [("    " + b) for b in block])
        i = j
    return segs


def _defs_uses(stmts: list) -> tuple[list[str], list[str], set[str]]:
    """Names assigned, and names read before being assigned, in a list of statements (in
    order); also which assigned names hold booleans (a comparison at the top level)."""
    defs: list[str] = []
    uses: list[str] = []
    bools: set[str] = set()
    seen: set[str] = set()  # names in defs or uses (linear time)
    defined: set[str] = set()  # names in defs
    for st in stmts:
        s = st.strip()
        if s.startswith(("if ", "for ")):
            for n in _VAR.findall(s):
                if n not in seen:
                    uses.append(n)
                    seen.add(n)
            continue
        lhs, _, rhs = s.partition(" = ")
        for n in _VAR.findall(rhs):
            if n not in seen:
                uses.append(n)
                seen.add(n)
        for n in (t.strip() for t in lhs.split(",")):
            if n not in defined:
                defs.append(n)
                defined.add(n)
                seen.add(n)
            if _COMPARE.search(_top_level(rhs)):
                bools.add(n)
    return defs, uses, bools


def _top_level(expr: str) -> str:
    """``expr`` with everything inside parentheses removed."""
    out, depth = [], 0
    for ch in expr:
        if ch == "(":
            depth += 1
        elif ch == ")":
            depth -= 1
        elif depth == 0:
            out.append(ch)
    return "".join(out)


def choose_lanes(lines: list) -> int:
    """Independent vectors in flight per loop iteration. A smooth blend is a long dependency
    chain (exp -> sum -> log -> next blend's exp) and one iteration of a loop-free body is too
    long for the CPU to overlap with the next, so two interleaved copies of the body (points i
    and i + BLOCK/2) keep the vector units busy (measured 1.8x on the seed world with AVX2).
    Bodies with a loop over a table are throughput-bound already (no gain measured) and long
    bodies would double numba's compile time: one copy."""
    if len(lines) > LONG_BODY_LINES or any(ln.startswith("for ") for ln in lines):
        return 1
    return 2


def _units(stmts: list) -> list:
    """Statements grouped with their indented continuation (an ``if`` and its block)."""
    out: list[list[str]] = []
    for st in stmts:
        if st.startswith(" ") and out:
            out[-1].append(st)
        else:
            out.append([st])
    return out


def _lane(stmt: str, k: int) -> str:
    """One lane's copy of a statement: every per-point variable gets the suffix ``_k`` (loop
    indices ``iN`` and hoisted table values are shared)."""
    return _VAR.sub(lambda mt: mt.group(0) if mt.group(0)[0] == "i" else f"{mt.group(0)}_{k}", stmt)


_FOLD_LOAD = re.compile(r"\b_F(\d+)\[(\d+)\]")
_FOLD_STORE = re.compile(r"\b_F(\d+)\[(i\d+) \* (\d+)(?: \+ (\d+))?\]")


class _Staging:
    """The per-point statements of a block, segment by segment, staged through the scratch
    array ``S``: a variable live across segments has one row per lane,
    ``S[slot * BLOCK + lane * half + i]`` (booleans stored as 0.0 / 1.0); every segment is a
    loop over the block's points that loads the rows it uses and stores the ones used later.

    ``slots`` (name -> row) is filled as rows are first used; ``fbase``/``fold_loop`` place the
    rows of folded subexpressions (see :func:`block_source`).
    """

    def __init__(
        self,
        segs: list,
        result_names: list,
        lanes: int,
        slots: dict,
        fbase: Sequence[int] = (),
        fold_loop: dict | None = None,
    ):
        self.lanes, self.half = lanes, BLOCK // lanes
        self.slots, self.fbase = slots, fbase
        self.fold_loop = {} if fold_loop is None else fold_loop
        self.info = [_defs_uses(seg[1] if seg[0] == "line" else seg[2]) for seg in segs]
        self.bools = set()
        for _, _, b in self.info:
            self.bools |= b
        self.later_uses: list[set[str]] = [set() for _ in segs]
        acc = set(result_names)
        for k in range(len(segs) - 1, -1, -1):
            self.later_uses[k] = set(acc)
            acc |= set(self.info[k][1])

    def at(self, name, k):
        if name not in self.slots:
            self.slots[name] = len(self.slots)
        return f"S[{self.slots[name] * BLOCK + k * self.half} + i]"

    def load(self, name, pad):
        return [
            f"{pad}{name}_{k} = {self.at(name, k)} != 0.0"
            if name in self.bools
            else f"{pad}{name}_{k} = {self.at(name, k)}"
            for k in range(self.lanes)
        ]

    def store(self, name, pad):
        return [
            f"{pad}{self.at(name, k)} = _sel({name}_{k}, 1.0, 0.0)"
            if name in self.bools
            else f"{pad}{self.at(name, k)} = {name}_{k}"
            for k in range(self.lanes)
        ]

    def compute(self, stmts, pad):
        out = []
        for unit in _units(stmts):
            for k in range(self.lanes):
                out += [pad + _lane(st, k) for st in unit]
        return out

    def segment(self, k: int, seg: tuple) -> list:
        """The code of segment ``k`` (``('line', stmts)`` or ``('loop', header, stmts)``)."""
        code = []
        defs, uses, _ = self.info[k]
        if seg[0] == "line":
            pad = "        "
            code.append(f"    for i in range({self.half}):")
            for name in uses:
                code += self.load(name, pad)
            code += self.compute(seg[1], pad)
            for name in defs:
                if name in self.later_uses[k]:
                    code += self.store(name, pad)
        else:
            header, stmts = seg[1], seg[2]
            loop_var = header.split()[1]
            hoisted: dict = {}

            def hoist(mt: re.Match, loop_var: str, hoisted: dict = hoisted) -> str:
                if mt.group(2) != loop_var:
                    return mt.group(0)
                key = (mt.group(1), mt.group(3))
                if key not in hoisted:
                    hoisted[key] = f"h{mt.group(1)[2:]}_{mt.group(3)}"
                return hoisted[key]

            row = re.match(r"^(i\d+) = _act\[(i\d+q)\]$", stmts[0]) if stmts else None
            if row and row.group(2) == loop_var:
                # a loop over a row list (pruning): the row index is the same for all points
                loop_var = row.group(1)
                stmts = stmts[1:]
            stmts = [_TABLE_READ.sub(lambda mt: hoist(mt, loop_var), st) for st in stmts]
            defs, uses, _ = _defs_uses(stmts)
            code.append(f"    {header}")
            if row:
                code.append(f"        {row.group(0)}")
            code += [
                f"        {name} = {t}[{loop_var}, {col}]"
                for (t, col), name in sorted(hoisted.items(), key=lambda kv: kv[1])
            ]
            for g in sorted({int(n) for n in re.findall(r"\bfo_(\d+)\b", "\n".join(stmts))}):
                lv, size = self.fold_loop[g]
                code.append(f"        fo_{g} = ({self.fbase[g]} + {lv} * {size}) * {BLOCK}")
            pad = "            "
            code.append(f"        for i in range({self.half}):")
            for name in uses:
                code += self.load(name, pad)
            code += self.compute(stmts, pad)
            for name in defs:
                if name in uses or name in self.later_uses[k]:
                    code += self.store(name, pad)
        return code


def _fold_layout(fold_sizes: Sequence[int]) -> tuple[dict, list, dict, Callable]:
    """Scratch rows of a block: ``x``, ``y``, then each loop group's stored values.

    Returns ``(slots, fbase, fold_loop, fold_store)``: the row of every name, each group's first
    row, a dict the substitution fills with each group's loop variable and row count, and the
    ``re.sub`` callback that turns a group's store into a store into its scratch row.
    """
    slots: dict = {"x": 0, "y": 1}
    fbase: list[int] = []
    fold_loop: dict[int, tuple] = {}
    for g, count in enumerate(fold_sizes):
        fbase.append(len(slots))
        slots.update((f"#F{g}.{q}", len(slots)) for q in range(count))

    def fold_store(mt: re.Match) -> str:
        g, loop_var, size, slot = int(mt.group(1)), mt.group(2), int(mt.group(3)), mt.group(4)
        fold_loop[g] = (loop_var, size)
        return f"S[fo_{g} + {int(slot or 0) * BLOCK} + i]"

    return slots, fbase, fold_loop, fold_store


def block_source(
    lines: list,
    results: list,
    kind: str,
    extra_args: tuple = (),
    lanes: int | None = None,
    binds: tuple = (),
    fold_sizes: Sequence[int] = (),
) -> str:
    """Source of ``_block_<kind>`` (a block of points) and of the kernels
    ``batch_<kind>_par(xs, ys, out[, grad], chunks)`` and ``batch_<kind>_ser(xs, ys, out[, grad])``.

    ``lines`` are the per-point statements of :class:`fastsdf.backends.kernel.codegen._Emitter`
    (reading ``x``, ``y``; top-level ``for`` loops over tables), ``results`` the expressions of the
    value (and of the two gradient components for ``kind='vg'``). The kernels are plain Python
    functions that hand the block function to the scene-independent kernels of
    :mod:`fastsdf.backends.kernel.drive`.

    The block's points are staged in the scratch array: coordinates copied in (non-finite ones
    replaced by 0, the block padded to ``BLOCK`` points), every compute loop reading and
    writing only rows of the scratch array at constant offsets with a constant trip count (no
    runtime alias checks, no scalar remainder loops), results copied out.

    ``fold_sizes``: entries of the arrays ``_F<g>`` of subexpressions evaluated in loops (see
    ``codegen._Emitter.fold``); each entry becomes a row of the scratch array.

    Scenes with parameters (``extra_args`` passed from the kernels to the block function,
    ``binds`` run at its top, ``kind='vgt'`` also writing dd/dt) use
    :func:`_param_block_source`.
    """
    if extra_args or binds or kind == "vgt":
        assert not fold_sizes
        return _param_block_source(lines, results, kind, extra_args, lanes, binds)
    grad = kind == "vg"
    lanes = lanes or choose_lanes(lines)
    assert lanes == 1 or not fold_sizes
    lines = list(lines) + [f"r{k} = {expr}" for k, expr in enumerate(results)]
    result_names = [f"r{k}" for k in range(len(results))]
    segs = _split(lines)
    tables = sorted(set(re.findall(r"\b(_T\d+)\b", "\n".join(lines))))
    outs = ["out"] + (["grad"] if grad else [])
    sig = ", ".join(["xs", "ys"] + outs)
    gflat = "grad.reshape(-1), 2, " if grad else "out, 1, "
    body: list[str] = []

    slots, fbase, fold_loop, fold_store = _fold_layout(fold_sizes)

    if fold_sizes:

        def fold_load(mt):
            return f"S[{(fbase[int(mt.group(1))] + int(mt.group(2))) * BLOCK} + i]"

        segs = [
            ("line", [_FOLD_LOAD.sub(fold_load, st) for st in seg[1]])
            if seg[0] == "line"
            else ("loop", seg[1], [_FOLD_STORE.sub(fold_store, st) for st in seg[2]])
            for seg in segs
        ]

    st = _Staging(segs, result_names, lanes, slots, fbase, fold_loop)
    at = st.at

    prelude = [
        "    for i in range(n):",
        "        x = xs[i]",
        "        y = ys[i]",
        "        ok = (abs(x) < math.inf) & (abs(y) < math.inf)",
        "        S[i] = _sel(ok, x, 0.0)",
        f"        S[{BLOCK} + i] = _sel(ok, y, 0.0)",
        f"    for i in range(n, {BLOCK}):",
        "        S[i] = 0.0",
        f"        S[{BLOCK} + i] = 0.0",
    ]
    # The loops that fill the _F arrays open the body; they go to a function of their own
    # (_fold_<kind>), called before the block function: in one function with the rest, LLVM
    # stops inlining the exp/log calls of the long straight-line loop, which then stays scalar.
    fold_segs = 0
    while (
        fold_sizes
        and fold_segs < len(segs)
        and segs[fold_segs][0] == "loop"
        and "S[fo_" in "\n".join(segs[fold_segs][2])
    ):
        fold_segs += 1
    fold_body = None
    for k, seg in enumerate(segs):
        if k == fold_segs and fold_sizes:
            fold_body, body = body, []
        body += st.segment(k, seg)
    res = [f"        out[i] = _sel(ok, {at(result_names[0], 0)}, math.nan)"]
    if grad:
        res += [
            f"        grad[2 * i] = _sel(ok, {at(result_names[1], 0)}, math.nan)",
            f"        grad[2 * i + 1] = _sel(ok, {at(result_names[2], 0)}, math.nan)",
        ]
    body += [
        "    for i in range(n):",
        "        x = xs[i]",
        "        y = ys[i]",
        "        ok = (abs(x) < math.inf) & (abs(y) < math.inf)",
    ] + res
    nslots = len(slots)
    size = max(nslots, 1) * BLOCK
    views = ["    xs = carray(xp, (n,))", "    ys = carray(yp, (n,))", "    out = carray(op, (n,))"]
    if grad:
        views.append("    grad = carray(gp, (2 * n,))")
    views.append(f"    S = carray(sp, ({size},))")

    def head(part):
        text = "\n".join(part)
        used = [f"    {t} = {t}G" for t in tables if re.search(rf"\b{t}\b", text)]
        if "_act[" in text:  # the row lists: all rows, or a tile's (pruning)
            used += ["    _act = ap", "    _off = fp"]
        return "\n".join(views + used + prelude)

    fold = "_drive_nofold"
    fold_src = ""
    # every block gets the rows of the loops over tables as pointers (all rows here)
    rows = "_ACTG, _OFFG" if "_act[" in "\n".join(body + (fold_body or [])) else "_NOROWS, _NOROWS"
    if fold_body is not None:
        fold = f"_fold_{kind}_fn"
        fold_src = f'''

@njit(cache=True, nogil=True, error_model="numpy")
def _fold_{kind}(xp, yp, op, gp, n, sp, ap, fp):
    """The loops over same-shape subexpressions of the block function: their values and
    gradients into the scratch rows (called before ``_block_{kind}``, same arguments)."""
{head(fold_body)}
{chr(10).join(fold_body)}


_fold_{kind}_fn = _BlockFn(_fold_{kind})
'''
    src = (
        fold_src
        + f'''

@njit(cache=True, nogil=True, error_model="numpy")
def _block_{kind}(xp, yp, op, gp, n, sp, ap, fp):
    """{"Value and gradient" if grad else "Value"} at ``n`` (at most {BLOCK}) points from pointers
    (:data:`fastsdf.backends.kernel.drive.BLOCK_SIG`){", ``grad`` flat (x, y pairs)" if grad else " (``gp`` unused)"};
    scratch ``sp[:{size}]``."""
{head(body)}
{chr(10).join(body)}


_block_{kind}_fn = _BlockFn(_block_{kind})


#: Scratch floats per thread of the ``{kind}`` kernels (see :func:`fastsdf.backends.kernel.drive.scratch`).
scratch_{kind} = {size}


def batch_{kind}_par({sig}, chunks, S=None):
    """All points, in parallel: the installation's kernel calls ``_block_{kind}`` per block
    (``S``: scratch space of ``_max_threads() * scratch_{kind}`` floats, else allocated here)."""
    S = _drive_scratch(_max_threads() * {size}) if S is None else S
    _run_par({fold}.address, _block_{kind}_fn.address, xs, ys, out, {gflat}S, {size}, chunks, _max_threads(), {rows})


def batch_{kind}_ser({sig}, S=None):
    """All points, in this thread (``S``: at least ``scratch_{kind}`` floats)."""
    S = _drive_scratch({size}) if S is None else S
    _run_ser({fold}.address, _block_{kind}_fn.address, xs, ys, out, {gflat}S, {size}, {rows})
'''
    )
    if rows != "_NOROWS, _NOROWS":
        src += f'''

def tiles_{kind}_par({sig}, order, starts, act, offs, chunks, S=None):
    """Points sorted by tile (tile ``t``: ``order[starts[t]:starts[t + 1]]``) in parallel
    blocks, each with its tile's row lists (``act``, ``offs[t]``: see :mod:`fastsdf.backends.prune`)."""
    S = _drive_scratch(_max_threads() * {size}) if S is None else S
    _tiles_par({fold}.address, _block_{kind}_fn.address, xs, ys, out, {"grad" if grad else "_NOGRAD"}, S, {size}, chunks, _max_threads(), order, starts, act, offs, _ACTG.shape[0])
'''
    return src


_PROG_OPS = {
    "init": 0,
    "min": 1,
    "max": 2,
    "smin": 3,
    "smax": 4,
    "fin_smin": 5,
    "fin_smax": 6,
    "out": 7,
    "smin2": 8,
    "smax2": 9,
    "neg": 10,
    "qmin": 11,
    "cmin": 12,
}


def program_source(
    lines: list, kind: str, fold_sizes: Sequence[int], steps: list, acc_rows: int
) -> tuple[str, str]:
    """Source of ``_fold_<kind>`` (the loops over same-shape subexpressions, as in
    :func:`block_source`, storing into scratch rows), of the combine program ``_PROG_<KIND>``
    (see ``codegen._Emitter.program``) and of the kernels ``batch_<kind>_par`` /
    ``batch_<kind>_ser``, which run both through the installation's kernels
    (:func:`fastsdf.backends.kernel.drive.run_prog_par`). The scene's compiled code is the fold
    function alone: it grows with the number of distinct shapes, not with the primitives."""
    grad = kind == "vg"
    segs = _split(lines)
    assert segs and all(seg[0] == "loop" for seg in segs)
    slots, fbase, fold_loop, fold_store = _fold_layout(fold_sizes)

    segs = [("loop", seg[1], [_FOLD_STORE.sub(fold_store, st) for st in seg[2]]) for seg in segs]
    st = _Staging(segs, [], 1, slots, fbase, fold_loop)
    body = []
    for k, seg in enumerate(segs):
        body += st.segment(k, seg)
    # With gradients, only the block's first nv points (its n rounded up to whole vectors, as
    # the program in fastsdf.backends.kernel.drive._lanes): a call on a few points does not pay for
    # a whole block. Not for the value alone: there LLVM vectorizes the loops worse without their
    # constant trip count (a whole block measured 1.6x slower), so they keep it.
    whole = f"        for i in range({BLOCK}):"
    assert whole in body
    if grad:
        body = ["        for i in range(nv):" if ln == whole else ln for ln in body]
    first = len(slots)
    size = (first + acc_rows) * BLOCK

    def row(ref):
        if ref[0] == "F":
            return (fbase[ref[1]] + ref[2]) * BLOCK
        return (first + ref[1]) * BLOCK

    table = []
    for op, operand, acc, k, zeros in steps:
        r = [0.0] * 9
        r[0] = _PROG_OPS[op]
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
        table.append(r)
    prog = ",\n    ".join("[" + ", ".join(repr(float(v)) for v in r) + "]" for r in table)
    tables = sorted(set(re.findall(r"\b(_T\d+)\b", "\n".join(lines))))
    views = [
        "    xs = carray(xp, (n,))",
        "    ys = carray(yp, (n,))",
        f"    S = carray(sp, ({size},))",
    ]
    used = [f"    {t} = {t}G" for t in tables]
    prelude = ([f"    nv = min({BLOCK}, (n + 7) // 8 * 8)"] if grad else []) + [
        "    for i in range(n):",
        "        x = xs[i]",
        "        y = ys[i]",
        "        ok = (abs(x) < math.inf) & (abs(y) < math.inf)",
        "        S[i] = _sel(ok, x, 0.0)",
        f"        S[{BLOCK} + i] = _sel(ok, y, 0.0)",
        f"    for i in range(n, {'nv' if grad else BLOCK}):",
        "        S[i] = 0.0",
        f"        S[{BLOCK} + i] = 0.0",
    ]
    outs = ["out"] + (["grad"] if grad else [])
    sig = ", ".join(["xs", "ys"] + outs)
    gflat = "grad.reshape(-1), 2, " if grad else "out, 1, "
    nl = "\n"
    # The one-point function: the same loops storing into a small array (one float per row,
    # the program's offsets divided by BLOCK), then the program at one point.
    rows_at = {g: base for g, base in enumerate(fbase)}
    plines = [
        "    " + re.sub(r"\b_F(\d+)\[", lambda mt: f"F[{rows_at[int(mt.group(1))]} + ", ln)
        for ln in lines
    ]
    point = f'''
@njit(cache=True, nogil=True, error_model="numpy")
def point_{kind}(x, y):
    """{"Value and gradient (d, dd/dx, dd/dy)" if grad else "Value"} at one point: the scene's subexpressions in loops over
    tables, then its combine program (fastsdf.backends.kernel.drive.combine_point_{kind})."""
    if not (math.isfinite(x) and math.isfinite(y)):
        return {"math.nan, math.nan, math.nan" if grad else "math.nan"}
{nl.join(used)}
    F = np.empty({first + acc_rows})
{nl.join(plines)}
    return _combine_point_{kind}(F, _PROG_{kind.upper()})
'''
    return (
        point,
        f'''

@njit(cache=True, nogil=True, error_model="numpy")
def _fold_{kind}(xp, yp, op, gp, n, sp, ap, fp):
    """The scene's subexpressions, each in a loop over a table of its shape: {"values and gradients" if grad else "values"}
    into the scratch rows that the combine program reads."""
{nl.join(views + used + prelude)}
{nl.join(body)}


_fold_{kind}_fn = _BlockFn(_fold_{kind})

#: The combine program (see fastsdf.backends.kernel.drive.PROG_COLS).
_PROG_{kind.upper()} = np.array([
    {prog},
], dtype=np.float64)


#: Scratch floats per thread of the ``{kind}`` kernels (see :func:`fastsdf.backends.kernel.drive.scratch`).
scratch_{kind} = {size}


def batch_{kind}_par({sig}, chunks, S=None):
    """All points, in parallel: the installation's kernel runs ``_fold_{kind}`` and the program
    (``S``: scratch space of ``_max_threads() * scratch_{kind}`` floats, else allocated here)."""
    S = _drive_scratch(_max_threads() * {size}) if S is None else S
    _run_prog_par(_fold_{kind}_fn.address, _PROG_{kind.upper()}, xs, ys, out, {gflat}S, {size}, chunks, _max_threads())


def batch_{kind}_ser({sig}, S=None):
    """All points, in this thread (``S``: at least ``scratch_{kind}`` floats)."""
    S = _drive_scratch({size}) if S is None else S
    _run_prog_ser(_fold_{kind}_fn.address, _PROG_{kind.upper()}, xs, ys, out, {gflat}S, {size})
''',
    )


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
        "run_prog_par as _run_prog_par",
        "run_prog_ser as _run_prog_ser",
        "combine_point_v as _combine_point_v",
        "combine_point_vg as _combine_point_vg",
        "scratch as _drive_scratch",
    ]
    drive = hashed_import("fastsdf.backends.kernel.drive", names)
    return "from numba import carray\n" + drive + "\n"


def _param_block_source(
    lines: list,
    results: list,
    kind: str,
    extra_args: tuple = (),
    lanes: int | None = None,
    binds: tuple = (),
) -> str:
    """:func:`block_source` for scenes with parameters: the block function takes arrays and the
    parameters, and the kernels that call it are compiled with the scene.

    ``lines`` are the per-point statements of :class:`fastsdf.backends.kernel.codegen._Emitter`
    (reading ``x``, ``y``; top-level ``for`` loops over tables), ``results`` the expressions of the
    value (and of the two gradient components for ``kind='vg'``). ``extra_args`` are names of
    further arguments passed unchanged from the kernels to the block function (e.g. parameter
    arrays), ``binds`` statements run once at the top of the block function (e.g. ``_p0 = prm[0]``,
    the runtime parameters read from their tuple). ``kind='vgt'`` also writes ``dt`` (a fourth
    result, the time derivative).

    The block's points are staged in the scratch array: coordinates copied in (non-finite ones
    replaced by 0, the block padded to ``BLOCK`` points), every compute loop reading and
    writing only rows of the scratch array at constant offsets with a constant trip count (no
    runtime alias checks, no scalar remainder loops), results copied out.
    """
    grad = kind in ("vg", "vgt")
    timed = kind == "vgt"
    lanes = lanes or choose_lanes(lines)
    lines = list(lines) + [f"r{k} = {expr}" for k, expr in enumerate(results)]
    result_names = [f"r{k}" for k in range(len(results))]
    segs = _split(lines)
    tables = sorted(set(re.findall(r"\b(_T\d+)\b", "\n".join(lines))))
    outs = ["out"] + (["grad"] if grad else []) + (["dt"] if timed else [])
    args = ["xs", "ys"] + outs + list(extra_args)
    body = [f"    {t} = {t}G" for t in tables] + [f"    {b}" for b in binds]
    if "_act[" in "\n".join(lines):
        body += ["    _act = _ACTG", "    _off = _OFFG"]
    body.append("    n = xs.shape[0]")

    slots: dict = {"x": 0, "y": 1}
    st = _Staging(segs, result_names, lanes, slots)
    at = st.at

    body += [
        "    for i in range(n):",
        "        x = xs[i]",
        "        y = ys[i]",
        "        ok = (abs(x) < math.inf) & (abs(y) < math.inf)",
        "        S[i] = _sel(ok, x, 0.0)",
        f"        S[{BLOCK} + i] = _sel(ok, y, 0.0)",
        f"    for i in range(n, {BLOCK}):",
        "        S[i] = 0.0",
        f"        S[{BLOCK} + i] = 0.0",
    ]
    for k, seg in enumerate(segs):
        body += st.segment(k, seg)
    res = [f"        out[i] = _sel(ok, {at(result_names[0], 0)}, math.nan)"]
    if grad:
        res += [
            f"        grad[2 * i] = _sel(ok, {at(result_names[1], 0)}, math.nan)",
            f"        grad[2 * i + 1] = _sel(ok, {at(result_names[2], 0)}, math.nan)",
        ]
    if timed:
        res.append(f"        dt[i] = _sel(ok, {at(result_names[3], 0)}, math.nan)")
    body += [
        "    for i in range(n):",
        "        x = xs[i]",
        "        y = ys[i]",
        "        ok = (abs(x) < math.inf) & (abs(y) < math.inf)",
    ] + res
    nslots = len(slots)
    sig = ", ".join(args)
    size = max(nslots, 1) * BLOCK
    views = ["    xs = xs[start:stop]", "    ys = ys[start:stop]", "    out = out[start:stop]"]
    if grad:
        views.append("    grad = grad[2 * start:2 * stop]")
    if timed:
        views.append("    dt = dt[start:stop]")
    views.append(f"    S = S[at:at + {size}]")
    flat = "\n    grad = grad.reshape(-1)" if grad else ""
    src = f'''

@njit(cache=True, nogil=True, error_model="numpy")
def _block_{kind}({sig}, start, stop, S, at):
    """{"Value, gradient and dd/dt" if timed else "Value and gradient" if grad else "Value"} at points start..stop-1 (at most {BLOCK}){", ``grad`` flat (x, y pairs)" if grad else ""};
    scratch ``S[at:at + {size}]``."""
{chr(10).join(views)}
{chr(10).join(body)}


@njit(cache=True, parallel=True, error_model="numpy")
def batch_{kind}_par({sig}, chunks):
    n = xs.shape[0]{flat}
    blocks = (n + {BLOCK - 1}) // {BLOCK}
    chunks = max(1, min(blocks, chunks))
    S = np.empty(chunks * {size})
    for c in prange(chunks):
        for b in range(c * blocks // chunks, (c + 1) * blocks // chunks):
            _block_{kind}({sig}, b * {BLOCK}, min((b + 1) * {BLOCK}, n), S, c * {size})


@njit(cache=True, error_model="numpy")
def batch_{kind}_ser({sig}):
    n = xs.shape[0]{flat}
    S = np.empty({size})
    for s in range(0, n, {BLOCK}):
        _block_{kind}({sig}, s, min(s + {BLOCK}, n), S, 0)
'''
    return src


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
