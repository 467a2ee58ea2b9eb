"""Scene-independent batch kernels: they call a scene's block functions through pointers.

A scene's generated module defines ``_block_v`` / ``_block_vg`` (see
:mod:`fastsdf.backends.kernel.simd`), one block of at most ``BLOCK`` points, over raw pointers with
the signature :data:`BLOCK_SIG` ``(xs, ys, out, grad, n, scratch)``, and for long scenes ``_fold_v``
/ ``_fold_vg`` (the loops over same-shape subexpressions, run first on the same block). The kernels
here loop over the blocks (``prange`` over chunks of blocks, or serially) and call those functions
by address: they do not depend on the scene, so each is compiled once per installation and cached
beside this file. A new scene then compiles only its block functions. The parallel kernel used to be
compiled per scene (numba's ``parfor`` lowering and its gufunc, and LLVM optimizing the block
function again inside every caller it was linked into), which cost about as much as the block
function itself. Two indirect calls per block of 512 points cost nothing measurable.
"""

from __future__ import annotations

import math
import sys
from typing import Any

import numba
import numpy as np
from llvmlite import ir
from numba import get_thread_id, njit, prange, types
from numba.extending import intrinsic

from fastsdf.backends.kernel.layout import BLOCK
from fastsdf.backends.lower import PROGRAM_STEPS
from fastsdf.intrinsics import select as _sel

__all__ = [
    "BLOCK_SIG",
    "STEP_SIG",
    "BlockFn",
    "NOFOLD",
    "PROG_COLS",
    "max_threads",
    "run_par",
    "run_ser",
    "NOGRAD",
    "NOROWS",
    "element_ptr",
    "tiles_par",
    "scratch",
]

_P = types.CPointer(types.float64)
_I = types.CPointer(types.int64)
#: ``(xs, ys, out, grad, n, scratch, act, off, data)``: pointers to the block's first point in
#: each array, ``grad`` flat (x, y pairs, or x, y, t triples with the time derivative; ignored
#: by value-only blocks), the block's scratch space, the row lists of the scene's loops over
#: tables (rows ``act[off[g]:off[g + 1]]`` for loop ``g``: all rows, or a tile's pruned lists;
#: ignored by scenes without such loops), and the values a call passes (the time, then the
#: parameters; ignored by static scenes).
BLOCK_SIG = types.void(_P, _P, _P, _P, types.intp, _P, _I, _I, _P)
#: ``(op, operand rows, accumulator rows, program row, points)``: one step of a combine program
#: on a block's scratch space (:mod:`fastsdf.backends.kernel.combine`).
STEP_SIG = types.void(types.int64, _P, _P, _P, types.int64)


@intrinsic
def _call(typingctx, address, xp, yp, op, gp, n, sp, ap, fp, dp):
    """Call the compiled function at ``address`` (an integer: the C-callable wrapper of a
    function with the signature :data:`BLOCK_SIG`) with the other arguments."""
    sig = types.void(types.intp, _P, _P, _P, _P, types.intp, _P, _I, _I, _P)

    def codegen(context, builder, signature, args):
        fnty = ir.FunctionType(
            context.get_value_type(types.none), [context.get_value_type(t) for t in BLOCK_SIG.args]
        )
        fn = builder.inttoptr(args[0], fnty.as_pointer())
        builder.call(fn, args[1:])
        return context.get_dummy_value()

    return sig, codegen


@intrinsic
def element_ptr(typingctx: object, arr: types.Array, index: types.Integer) -> tuple:
    """Pointer to ``arr[index]`` (1-d contiguous array); no bounds check."""
    sig = types.CPointer(arr.dtype)(arr, index)

    def codegen(context, builder, signature, args):
        ary = context.make_array(signature.args[0])(context, builder, args[0])
        return builder.gep(ary.data, [args[1]])

    return sig, codegen


_at = element_ptr


class BlockFn:
    """A compiled function the kernels here call by address (an ``@njit(cache=True)``
    dispatcher of signature ``sig``: a scene's block function, :data:`BLOCK_SIG`, or a combine
    program's step function): ``address`` is its compiled C-callable wrapper, compiled (or
    loaded from the disk cache) on first use. An integer argument keeps numba's dispatch of the
    kernels as cheap as for any array call (a first-class function object is typed in Python
    on every call: +25 us)."""

    def __init__(self, dispatcher: Any, sig: Any = BLOCK_SIG) -> None:
        self.dispatcher = dispatcher
        self.sig = sig
        self._addr: int | None = None

    @property
    def address(self) -> int:
        """The C-callable address of the compiled function."""
        if self._addr is None:
            args = self.sig.args
            self.dispatcher.compile(args)
            cres = self.dispatcher.overloads[args]
            self._addr = cres.library.get_pointer_to_function(cres.fndesc.llvm_cfunc_wrapper_name)
        return self._addr


def max_threads() -> int:
    """The most threads a parallel region can run on (``NUMBA_NUM_THREADS``): thread ids
    (``numba.get_thread_id``) index the scratch space."""
    return numba.config.NUMBA_NUM_THREADS


@njit(cache=True, nogil=True, inline="always")
def _check_scratch(S, need):
    # The block functions write through raw pointers: a short buffer would corrupt memory.
    if S.shape[0] < need:
        raise ValueError("scratch buffer too small for this scene's kernels")


def scratch(floats: int) -> np.ndarray:
    """A scratch buffer of ``floats`` float64 for the kernels here (``size`` per thread that
    runs them: ``max_threads() * size`` for the parallel ones). The kernels take it from the
    caller rather than allocating it: a long scene's scratch space is hundreds of rows of
    ``BLOCK`` floats, one 4 KiB page each, and a fresh allocation page-faults every row it
    uses on every call (about 1 ms for a single point of a 200-primitive scene). Its contents
    between calls do not matter: every row is written before it is read."""
    return np.empty(max(int(floats), 1))


@njit(cache=True, nogil=True, error_model="numpy")
def _nofold(xp, yp, op, gp, n, sp, ap, fp, dp):
    """The ``pre`` function of a scene without loops of its own to run first: nothing."""
    return


#: ``pre`` for scenes whose block function needs nothing before it.
NOFOLD = BlockFn(_nofold)
#: The row lists of scenes without loops over tables (never read).
NOROWS = np.zeros(1, dtype=np.int64)
#: The ``grad`` of :func:`tiles_par` for the value alone.
NOGRAD = np.empty((0, 2))


@njit(nogil=True, error_model="numpy", inline="always")
def _run_block(pre, fn, step, xs, ys, out, grad, gs, S, at, s, n, act, off, data):
    """``pre`` then ``fn`` on the block of points from ``s`` (of ``n``), in the scratch space
    from ``S[at]``; the block's gradient starts at ``grad[gs * s]`` (``gs``: 2 for x y pairs,
    3 with the time derivative, or 1 where ``grad`` is ``out`` and value-only blocks never read
    it); ``data``: the call's time and parameters. With a ``step`` function (a combine
    program's), ``data`` is the program (flat rows) and it runs in place of ``fn``."""
    m = min(s + BLOCK, n) - s
    xp, yp, op, gp, sp = _at(xs, s), _at(ys, s), _at(out, s), _at(grad, gs * s), _at(S, at)
    dp = _at(data, 0)
    _call(pre, xp, yp, op, gp, m, sp, _at(act, 0), _at(off, 0), dp)
    if step == 0:
        _call(fn, xp, yp, op, gp, m, sp, _at(act, 0), _at(off, 0), dp)
    else:
        last = _combine(S, at, data, step, _lanes(m))
        _outputs(S, at + int(data[last + 1]), xs, ys, out, grad, s, m, gs == 2)


@njit(cache=True, parallel=True, error_model="numpy")
def run_par(
    pre: int,
    fn: int,
    step: int,
    xs: np.ndarray,
    ys: np.ndarray,
    out: np.ndarray,
    grad: np.ndarray,
    gs: int,
    S: np.ndarray,
    size: int,
    chunks: int,
    threads: int,
    act: np.ndarray,
    off: np.ndarray,
    data: np.ndarray,
) -> None:
    """All points: ``pre`` then ``fn`` (or the combine program ``data`` by ``step``, see
    :func:`_run_block`; else ``step`` is 0) on each block, blocks in parallel chunks, each thread
    with ``size`` floats of the scratch space ``S`` (at least ``threads * size`` floats,
    ``threads``: :func:`max_threads`; see :func:`scratch`); ``act``, ``off``: the row lists of
    every block (all rows: the scene's ``_ACTG``, ``_OFFG``); ``data``: the call's data (the
    time and parameters, the combine program, the scene's numbers: see
    :class:`fastsdf.backends.kernel.simd.Data`). Value and gradient: ``grad`` flat (x y
    pairs) and ``gs`` = 2 (3 with the time derivative); the value alone: ``grad`` is ``out``
    and ``gs`` = 1 (the block functions do not use it)."""
    n = xs.shape[0]
    blocks = (n + BLOCK - 1) // BLOCK
    chunks = max(1, min(blocks, chunks))
    _check_scratch(S, threads * size)
    for c in prange(chunks):
        at = get_thread_id() * size
        for b in range(c * blocks // chunks, (c + 1) * blocks // chunks):
            _run_block(pre, fn, step, xs, ys, out, grad, gs, S, at, b * BLOCK, n, act, off, data)


@njit(cache=True, nogil=True, error_model="numpy")
def run_ser(
    pre: int,
    fn: int,
    step: int,
    xs: np.ndarray,
    ys: np.ndarray,
    out: np.ndarray,
    grad: np.ndarray,
    gs: int,
    S: np.ndarray,
    size: int,
    act: np.ndarray,
    off: np.ndarray,
    data: np.ndarray,
) -> None:
    """:func:`run_par` in this thread (``S``: at least ``size`` floats)."""
    n = xs.shape[0]
    _check_scratch(S, size)
    for s in range(0, n, BLOCK):
        _run_block(pre, fn, step, xs, ys, out, grad, gs, S, 0, s, n, act, off, data)


@njit(cache=True, nogil=True)
def _tile_work(order, starts):
    """Blocks of at most ``BLOCK`` points sorted by tile (``starts``: tile ``t`` holds
    ``order[starts[t]:starts[t + 1]]``): ``(seq, work)``. Each tile's points fill whole blocks
    first; the rest of every tile (fewer than ``BLOCK`` points) are packed together, in tile
    order, into shared blocks, so that no block is padded while points remain. Block ``b``
    holds the points ``seq[work[b, 0]:work[b, 0] + work[b, 1]]`` of tiles ``work[b, 2]`` to
    ``work[b, 3]``."""
    T = starts.shape[0] - 1
    n = order.shape[0]
    full = 0
    for t in range(T):
        full += (starts[t + 1] - starts[t]) // BLOCK
    rest = n - full * BLOCK
    work = np.empty((full + (rest + BLOCK - 1) // BLOCK, 4), dtype=np.int64)
    seq = np.empty(n, dtype=np.int64)
    k, b = 0, 0
    for t in range(T):
        s0 = starts[t]
        for s in range(s0, s0 + (starts[t + 1] - s0) // BLOCK * BLOCK, BLOCK):
            seq[k : k + BLOCK] = order[s : s + BLOCK]
            work[b, 0], work[b, 1], work[b, 2], work[b, 3] = k, BLOCK, t, t
            k += BLOCK
            b += 1
    first = -1
    m = 0
    for t in range(T):
        s = starts[t] + (starts[t + 1] - starts[t]) // BLOCK * BLOCK
        while s < starts[t + 1]:
            if m == 0:
                first = t
            take = min(starts[t + 1] - s, BLOCK - m)
            seq[k + m : k + m + take] = order[s : s + take]
            s += take
            m += take
            if m == BLOCK:
                work[b, 0], work[b, 1], work[b, 2], work[b, 3] = k, m, first, t
                k += m
                b += 1
                m = 0
    if m:
        work[b, 0], work[b, 1], work[b, 2], work[b, 3] = k, m, first, T - 1
    return seq, work


@njit(cache=True, nogil=True)
def _merge_rows(act, offs, t0, t1, starts, actb, offb, cur):
    """The union of the row lists of tiles ``t0..t1`` (those holding points), per loop, in
    increasing order, into ``actb``/``offb`` (``cur``: room for a cursor per tile). A superset
    of each tile's rows evaluates the same bits: rows are visited in the same order and every
    row that can matter at a point is kept."""
    G = offs.shape[1] - 1
    k = 0
    offb[0] = 0
    for g in range(G):
        for t in range(t0, t1 + 1):
            cur[t - t0] = offs[t, g] if starts[t + 1] > starts[t] else offs[t, g + 1]
        while True:
            best = -1
            for t in range(t0, t1 + 1):
                q = cur[t - t0]
                if q < offs[t, g + 1] and (best < 0 or act[q] < best):
                    best = act[q]
            if best < 0:
                break
            actb[k] = best
            k += 1
            for t in range(t0, t1 + 1):
                q = cur[t - t0]
                if q < offs[t, g + 1] and act[q] == best:
                    cur[t - t0] = q + 1
        offb[g + 1] = k


@njit(cache=True, parallel=True, error_model="numpy")
def tiles_par(
    pre: int,
    fn: int,
    xs: np.ndarray,
    ys: np.ndarray,
    out: np.ndarray,
    grad: np.ndarray,
    S: np.ndarray,
    size: int,
    chunks: int,
    threads: int,
    order: np.ndarray,
    starts: np.ndarray,
    act: np.ndarray,
    offs: np.ndarray,
    rows: int,
    data: np.ndarray,
) -> None:
    """:func:`run_par` (``grad`` of shape (n, 2), or :data:`NOGRAD` for the value alone) on
    points sorted by tile (tile ``t``: ``order[starts[t]:starts[t + 1]]``),
    each block with its tile's row lists (``act``, ``offs`` of shape (tiles, loops + 1);
    ``rows``: the total number of rows of all loops; ``data``: the scene's numbers). The
    points of a block are gathered into contiguous buffers and the results scattered back; a
    block shared by the last points of several tiles runs the union of their lists. Only
    ``S`` comes from the caller: the other buffers here are a few KiB per thread, and the tile
    path serves large inputs only."""
    seq, work = _tile_work(order, starts)
    blocks = work.shape[0]
    chunks = max(1, min(blocks, chunks))
    vg = grad.shape[0] > 0
    G = offs.shape[1]
    _check_scratch(S, threads * size)
    W = 5 * BLOCK
    B = np.empty(threads * W)
    A = np.empty(threads * max(rows, 1), dtype=np.int64)
    F = np.empty(threads * G, dtype=np.int64)
    T = starts.shape[0] - 1
    C = np.empty(threads * T, dtype=np.int64)
    for c in prange(chunks):
        tid = get_thread_id()
        at = tid * size
        xb = B[tid * W : tid * W + BLOCK]
        yb = B[tid * W + BLOCK : tid * W + 2 * BLOCK]
        ob = B[tid * W + 2 * BLOCK : tid * W + 3 * BLOCK]
        gb = B[tid * W + 3 * BLOCK : tid * W + 5 * BLOCK]
        actb = A[tid * max(rows, 1) : (tid + 1) * max(rows, 1)]
        offb = F[tid * G : (tid + 1) * G]
        cur = C[tid * T : (tid + 1) * T]
        for b in range(c * blocks // chunks, (c + 1) * blocks // chunks):
            s, m, t0, t1 = work[b, 0], work[b, 1], work[b, 2], work[b, 3]
            for i in range(m):
                p = seq[s + i]
                xb[i] = xs[p]
                yb[i] = ys[p]
            if t0 == t1:
                ap, fp = _at(act, 0), _at(offs[t0], 0)
            else:
                _merge_rows(act, offs, t0, t1, starts, actb, offb, cur)
                ap, fp = _at(actb, 0), _at(offb, 0)
            gp = _at(gb, 0) if vg else _at(ob, 0)
            dp = _at(data, 0)
            _call(pre, _at(xb, 0), _at(yb, 0), _at(ob, 0), gp, m, _at(S, at), ap, fp, dp)
            _call(fn, _at(xb, 0), _at(yb, 0), _at(ob, 0), gp, m, _at(S, at), ap, fp, dp)
            for i in range(m):
                out[seq[s + i]] = ob[i]
            if vg:
                for i in range(m):
                    p = seq[s + i]
                    grad[p, 0] = gb[2 * i]
                    grad[p, 1] = gb[2 * i + 1]


# ---------------------------------------------------------------------------------------------
# Combine programs: the blends of a scene without repeated structure, as data.
#
# A long scene's primitives are evaluated in loops over tables (the scene's ``_fold_<kind>``
# function) into scratch rows; what remains is a tree of min/max/smin/smax chains over those
# rows, run as a program: one row of ``prog`` per step, each step a loop over the block's points
# with the opcode branch outside it (so each step vectorizes). The steps are the interpreter of
# :mod:`fastsdf.backends.kernel.combine` (generated from the emitter's own chain arithmetic:
# the straight-line code's bits), called by address.

#: Columns of a program row: opcode (:data:`fastsdf.backends.lower.PROGRAM_STEPS`); the
#: operand's first row (its value; then the x and y gradient components in the next rows); the
#: accumulator's first row (m; then the gradient components, then s, the smooth sum); -k
#: (polynomial blends: k); 1/k; whether the operand's x and y gradient components are known to
#: be zero (as in the straight-line code: no product); the same for the accumulator
#: (polynomial blends). Rows are offsets in the block's scratch space, in floats.
PROG_COLS = 9
_OUT = PROGRAM_STEPS.index("out")


@intrinsic
def _call_step(typingctx, address, op, ap, mp, rp, nv):
    """Call the step function at ``address`` (the C-callable wrapper of a function with the
    signature :data:`STEP_SIG`)."""
    sig = types.void(types.intp, types.int64, _P, _P, _P, types.int64)

    def codegen(context, builder, signature, args):
        dbl = ir.DoubleType().as_pointer()
        i64 = ir.IntType(64)
        fnty = ir.FunctionType(ir.VoidType(), [i64, dbl, dbl, dbl, i64])
        fn = builder.inttoptr(args[0], fnty.as_pointer())
        builder.call(fn, args[1:])
        return context.get_dummy_value()

    return sig, codegen


@njit(nogil=True, inline="always")
def _lanes(m):
    """The points of a block of ``m`` that the fold loops and the program compute: ``m``
    rounded up to a multiple of 8 (whole vectors), so that a call on a few points does not pay
    for a whole block. Rows past them hold stale values that nothing reads."""
    return min(BLOCK, (m + 7) // 8 * 8)


@njit(nogil=True, error_model="numpy")
def _combine(S, at, prog, step, nv):
    """Run the program at the start of ``prog`` (rows of :data:`PROG_COLS`, up to the row of
    opcode ``out``, which it returns the offset of) on one block's scratch space ``S[at:]``
    (its first ``nv`` points: :func:`_lanes`), each step by the step function at ``step``."""
    r = 0
    while int(prog[r]) != _OUT:
        a = at + int(prog[r + 1])
        m = at + int(prog[r + 2])
        _call_step(step, int(prog[r]), _at(S, a), _at(S, m), _at(prog, r), nv)
        r += PROG_COLS
    return r


@njit(nogil=True, error_model="numpy", inline="always")
def _outputs(S, a, xs, ys, out, grad, start, m, with_grad):
    """Copy the result rows (from ``S[a]``) out, NaN where the point is not finite."""
    ax = a + BLOCK
    ay = a + 2 * BLOCK
    for i in range(m):
        x = xs[start + i]
        y = ys[start + i]
        ok = (abs(x) < math.inf) & (abs(y) < math.inf)
        out[start + i] = _sel(ok, S[a + i], math.nan)
        if with_grad:
            grad[2 * (start + i)] = _sel(ok, S[ax + i], math.nan)
            grad[2 * (start + i) + 1] = _sel(ok, S[ay + i], math.nan)


def _guard():
    from fastsdf.backends.kernel.cache import guard_module

    guard_module(sys.modules[__name__])


_guard()
