"""Block kernels: generated per-point code shaped so that LLVM vectorizes it across points.

LLVM's loop vectorizer turns a counted innermost loop into SIMD code (4 float64 lanes with AVX2,
8 with AVX-512) when its body is inlined, free of branches and calls, and its loads and stores
are contiguous. The per-point code of :mod:`fastsdf.codegen` is branch-free already (selects for
every min, max and blend); this module re-arranges it:

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
  branch-free :mod:`fastsdf._vmath` functions, and the overflow-safe ``length`` by its branch-free
  form, unless ``vmath=False`` (kept to compare against the C library).

Non-finite input points are evaluated at the origin and their outputs set to NaN afterwards.
"""

from __future__ import annotations

import hashlib
import re

__all__ = ["BLOCK", "block_source", "vectorizable", "vmath_import"]

#: Points per block: a multiple of every vector width, small enough that a block's scratch rows
#: stay in the L1/L2 cache.
BLOCK = 512

_VAR = re.compile(r"\b(?:[a-z]\d+[a-z]*|x|y)\b")
_TABLE_READ = re.compile(r"\b(_T\d+)\[(i\d+), (\d+)\]")
_COMPARE = re.compile(r"(?<![<>=!])(?:<=|>=|==|!=|<|>)(?![<>=])")
_LENGTH_IF = re.compile(r"^if not \(1e-150 < (\w+) < 1e150\):$")
_HYPOT = re.compile(r"^(\w+) = math\.hypot\((.*)\)$")


def vectorizable(lines: list) -> list:
    """The statements with the C library's exp/log/log1p and the branchy overflow-safe length
    replaced by the branch-free versions of :mod:`fastsdf._vmath`."""
    out, i = [], 0
    while i < len(lines):
        line = lines[i]
        stripped = line.lstrip()
        indent = line[:len(line) - len(stripped)]
        m = _LENGTH_IF.match(stripped)
        if m and i + 1 < len(lines):
            h = _HYPOT.match(lines[i + 1].strip())
            if h and h.group(1) == m.group(1) and out:
                # the line before computed the plain sqrt(a*a + b*b): replace it
                prev = out.pop()
                assert prev.strip().startswith(f"{m.group(1)} = math.sqrt("), prev
                out.append(f"{indent}{m.group(1)} = _vlength({h.group(2)})")
                i += 2
                continue
        line = (line.replace("math.exp(", "_vexp(").replace("math.log1p(", "_vlog1p(")
                .replace("math.log(", "_vlog("))
        out.append(line)
        i += 1
    return out


def _split(lines: list) -> list:
    """Top-level segments: ``('line', [stmts])`` runs and ``('loop', header, [body])`` loops
    (an ``if`` statement stays with its indented block inside a run)."""
    segs, i = [], 0
    while i < len(lines):
        line = lines[i]
        j = i + 1
        while j < len(lines) and lines[j].startswith(" "):
            j += 1
        block = [ln[4:] for ln in lines[i + 1:j]]
        if line.startswith("for "):
            segs.append(("loop", line, block))
        else:
            if not segs or segs[-1][0] != "line":
                segs.append(("line", []))
            segs[-1][1].extend([line] + [("    " + b) for b in block])
        i = j
    return segs


def _defs_uses(stmts: list):
    """Names assigned, and names read before being assigned, in a list of statements (in
    order); also which assigned names hold booleans (a comparison at the top level)."""
    defs, uses, bools = [], [], set()
    for st in stmts:
        s = st.strip()
        if s.startswith(("if ", "for ")):
            for n in _VAR.findall(s):
                if n not in defs and n not in uses:
                    uses.append(n)
            continue
        lhs, _, rhs = s.partition(" = ")
        for n in _VAR.findall(rhs):
            if n not in defs and n not in uses:
                uses.append(n)
        for n in (t.strip() for t in lhs.split(",")):
            if n not in defs:
                defs.append(n)
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


def block_source(lines: list, results: list, kind: str, extra_args: tuple = ()) -> str:
    """Source of ``_block_<kind>`` (a block of points) and of the kernels
    ``batch_<kind>_par(xs, ys, out[, grad], chunks)`` and ``batch_<kind>_ser(xs, ys, out[, grad])``.

    ``lines`` are the per-point statements of :class:`fastsdf.codegen._Emitter` (reading ``x``,
    ``y``; top-level ``for`` loops over tables), ``results`` the expressions of the value (and
    of the two gradient components for ``kind='vg'``). ``extra_args`` are names of further
    arguments passed unchanged from the kernels to the block function (e.g. parameter arrays).
    """
    grad = kind == "vg"
    lines = list(lines) + [f"r{k}_ = {expr}" for k, expr in enumerate(results)]
    result_names = [f"r{k}_" for k in range(len(results))]
    segs = _split(lines)
    tables = sorted(set(re.findall(r"\b(_T\d+)\b", "\n".join(lines))))
    outs = ["out"] + (["grad"] if grad else [])
    args = ["xs", "ys"] + outs + list(extra_args)
    body = [f"    {t} = {t}G" for t in tables]
    body.append("    n = xs.shape[0]")

    def store_results(indent, names):
        pad = " " * indent
        res = [f"{pad}out[i] = _sel(ok, {names[0]}, math.nan)"]
        if grad:
            res += [f"{pad}grad[2 * i] = _sel(ok, {names[1]}, math.nan)",
                    f"{pad}grad[2 * i + 1] = _sel(ok, {names[2]}, math.nan)"]
        return res

    load_point = ["        x = xs[i]", "        y = ys[i]",
                  "        ok = (abs(x) < math.inf) & (abs(y) < math.inf)"]
    if len(segs) == 1:
        # One run of statements: a single fused loop, no scratch.
        body.append("    for i in range(n):")
        body += load_point
        body += ["        x = _sel(ok, x, 0.0)", "        y = _sel(ok, y, 0.0)"]
        body += ["        " + st for st in segs[0][1]]
        body += store_results(8, result_names)
        nslots = 0
    else:
        # Liveness across segments: what each segment needs from before and leaves for after.
        info = []
        for seg in segs:
            stmts = seg[1] if seg[0] == "line" else seg[2]
            info.append(_defs_uses(stmts))
        slots: dict = {"x": 0, "y": 1}
        bools = set()
        for d, _, b in info:
            bools |= b
        later_uses = [set() for _ in segs]
        acc = set(result_names)
        for k in range(len(segs) - 1, -1, -1):
            later_uses[k] = set(acc)
            acc |= set(info[k][1])

        def slot(name):
            if name not in slots:
                slots[name] = len(slots)
            return slots[name]

        def load(name, pad):
            at = f"S[{slot(name) * BLOCK} + i]"
            return f"{pad}{name} = {at} != 0.0" if name in bools else f"{pad}{name} = {at}"

        def store(name, pad):
            at = f"S[{slot(name) * BLOCK} + i]"
            return f"{pad}{at} = _sel({name}, 1.0, 0.0)" if name in bools else f"{pad}{at} = {name}"

        body.append("    for i in range(n):")
        body += load_point
        body += [f"        S[i] = _sel(ok, x, 0.0)", f"        S[{BLOCK} + i] = _sel(ok, y, 0.0)"]
        for k, seg in enumerate(segs):
            defs, uses, _ = info[k]
            live_out = [n for n in defs if n in later_uses[k]]
            if seg[0] == "line":
                pad = "        "
                body.append("    for i in range(n):")
                body += [load(n, pad) for n in uses]
                body += [pad + st for st in seg[1]]
                body += [store(n, pad) for n in live_out]
            else:
                header, stmts = seg[1], seg[2]
                loop_var = header.split()[1]
                hoisted: dict = {}

                def hoist(mt, loop_var=loop_var, hoisted=hoisted):
                    if mt.group(2) != loop_var:
                        return mt.group(0)
                    key = (mt.group(1), mt.group(3))
                    if key not in hoisted:
                        hoisted[key] = f"h{mt.group(1)[2:]}_{mt.group(3)}"
                    return hoisted[key]

                stmts = [_TABLE_READ.sub(hoist, st) for st in stmts]
                defs, uses, _ = _defs_uses(stmts)
                carried = [n for n in defs if n in uses or n in later_uses[k]]
                body.append(f"    {header}")
                body += [f"        {name} = {t}[{loop_var}, {col}]"
                         for (t, col), name in sorted(hoisted.items(), key=lambda kv: kv[1])]
                pad = "            "
                body.append("        for i in range(n):")
                body += [load(n, pad) for n in uses]
                body += [pad + st for st in stmts]
                body += [store(n, pad) for n in carried]
        body.append("    for i in range(n):")
        body += load_point
        body += store_results(8, [f"S[{slot(n) * BLOCK} + i]" for n in result_names])
        nslots = len(slots)
    sig = ", ".join(args)
    views = ", ".join(["xs[s:e]", "ys[s:e]", "out[s:e]"] + (["g[2 * s:2 * e]"] if grad else [])
                      + list(extra_args))
    flat = "\n    g = grad.reshape(-1)" if grad else ""
    scratch = f"np.empty({max(nslots, 1) * BLOCK})"
    src = f'''

@njit(cache=True, nogil=True, error_model="numpy")
def _block_{kind}({sig}, S):
    """{'Value and gradient' if grad else 'Value'} at the points of one block (at most {BLOCK}):
    ``xs``, ``ys``, ``out`` hold the block's points{', ``grad`` their gradients, flat (x, y pairs)' if grad else ''}."""
{chr(10).join(body)}


@njit(cache=True, parallel=True, error_model="numpy")
def batch_{kind}_par({sig}, chunks):
    n = xs.shape[0]{flat}
    blocks = (n + {BLOCK - 1}) // {BLOCK}
    chunks = max(1, min(blocks, chunks))
    for c in prange(chunks):
        S = {scratch}
        for b in range(c * blocks // chunks, (c + 1) * blocks // chunks):
            s = b * {BLOCK}
            e = min(s + {BLOCK}, n)
            _block_{kind}({views}, S)


@njit(cache=True, error_model="numpy")
def batch_{kind}_ser({sig}):
    n = xs.shape[0]{flat}
    S = {scratch}
    for s in range(0, n, {BLOCK}):
        e = min(s + {BLOCK}, n)
        _block_{kind}({views}, S)
'''
    return src


def vmath_import() -> str:
    """Import of the vectorizable functions, with a hash of their source: numba's cache does not
    notice changes in a callee's module, so a changed ``_vmath.py`` must change the scene file."""
    from . import _vmath
    with open(_vmath.__file__, "rb") as fh:
        digest = hashlib.sha256(fh.read()).hexdigest()[:16]
    return ("from fastsdf._vmath import vexp as _vexp, vlog as _vlog, vlog1p as _vlog1p, "
            f"vlength as _vlength  # _vmath.py sha256 {digest}\n")
