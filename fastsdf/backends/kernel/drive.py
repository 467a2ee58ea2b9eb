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

from fastsdf.intrinsics import select as _sel
from fastsdf.backends.kernel.layout import BLOCK
from fastsdf.backends.kernel.vmath import vexp as _vexp
from fastsdf.backends.kernel.vmath import vlog as _vlog

__all__ = [
    "BLOCK_SIG",
    "BlockFn",
    "NOFOLD",
    "PROG_COLS",
    "max_threads",
    "run_par",
    "run_ser",
    "NOGRAD",
    "NOROWS",
    "tiles_par",
    "run_prog_par",
    "run_prog_ser",
    "combine_point_v",
    "combine_point_vg",
    "scratch",
]

_P = types.CPointer(types.float64)
_I = types.CPointer(types.int64)
#: ``(xs, ys, out, grad, n, scratch, act, off)``: pointers to the block's first point in each
#: array, ``grad`` flat (x, y pairs; ignored by value-only blocks), the block's scratch space,
#: and the row lists of the scene's loops over tables (rows ``act[off[g]:off[g + 1]]`` for loop
#: ``g``: all rows, or a tile's pruned lists; ignored by scenes without such loops).
BLOCK_SIG = types.void(_P, _P, _P, _P, types.intp, _P, _I, _I)


@intrinsic
def _call(typingctx, address, xp, yp, op, gp, n, sp, ap, fp):
    """Call the compiled function at ``address`` (an integer: the C-callable wrapper of a
    function with the signature :data:`BLOCK_SIG`) with the other arguments."""
    sig = types.void(types.intp, _P, _P, _P, _P, types.intp, _P, _I, _I)

    def codegen(context, builder, signature, args):
        fnty = ir.FunctionType(
            context.get_value_type(types.none), [context.get_value_type(t) for t in BLOCK_SIG.args]
        )
        fn = builder.inttoptr(args[0], fnty.as_pointer())
        builder.call(fn, args[1:])
        return context.get_dummy_value()

    return sig, codegen


@intrinsic
def _at(typingctx, arr, index):
    """Pointer to ``arr[index]`` (1-d contiguous array); no bounds check."""
    sig = types.CPointer(arr.dtype)(arr, index)

    def codegen(context, builder, signature, args):
        ary = context.make_array(signature.args[0])(context, builder, args[0])
        return builder.gep(ary.data, [args[1]])

    return sig, codegen


class BlockFn:
    """A scene's block function (an ``@njit(cache=True)`` dispatcher) for the kernels here:
    ``address`` is its compiled C-callable wrapper, compiled (or loaded from the disk cache) on
    first use. An integer argument keeps numba's dispatch of the kernels as cheap as for any
    array call (a first-class function object is typed in Python on every call: +25 us)."""

    def __init__(self, dispatcher: Any) -> None:
        self.dispatcher = dispatcher
        self._addr: int | None = None

    @property
    def address(self) -> int:
        """The C-callable address of the compiled block function."""
        if self._addr is None:
            args = BLOCK_SIG.args
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
def _nofold(xp, yp, op, gp, n, sp, ap, fp):
    """The ``pre`` function of a scene without loops of its own to run first: nothing."""
    return


#: ``pre`` for scenes whose block function needs nothing before it.
NOFOLD = BlockFn(_nofold)
#: The row lists of scenes without loops over tables (never read).
NOROWS = np.zeros(1, dtype=np.int64)
#: The ``grad`` of :func:`tiles_par` for the value alone.
NOGRAD = np.empty((0, 2))


@njit(nogil=True, error_model="numpy", inline="always")
def _run_block(pre, fn, xs, ys, out, grad, gs, S, at, s, n, act, off):
    """``pre`` then ``fn`` on the block of points from ``s`` (of ``n``), in the scratch space
    from ``S[at]``; the block's gradient starts at ``grad[gs * s]`` (``gs``: 2 for x y pairs,
    or 1 where ``grad`` is ``out`` and value-only blocks never read it)."""
    m = min(s + BLOCK, n) - s
    xp, yp, op, gp, sp = _at(xs, s), _at(ys, s), _at(out, s), _at(grad, gs * s), _at(S, at)
    _call(pre, xp, yp, op, gp, m, sp, _at(act, 0), _at(off, 0))
    _call(fn, xp, yp, op, gp, m, sp, _at(act, 0), _at(off, 0))


@njit(cache=True, parallel=True, error_model="numpy")
def run_par(
    pre: int,
    fn: int,
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
) -> None:
    """All points: ``pre`` then ``fn`` on each block, blocks in parallel chunks, each thread
    with ``size`` floats of the scratch space ``S`` (at least ``threads * size`` floats,
    ``threads``: :func:`max_threads`; see :func:`scratch`); ``act``, ``off``: the row lists of
    every block (all rows: the scene's ``_ACTG``, ``_OFFG``). Value and gradient: ``grad``
    flat (x y pairs) and ``gs`` = 2; the value alone: ``grad`` is ``out`` and ``gs`` = 1 (the
    block functions do not use it)."""
    n = xs.shape[0]
    blocks = (n + BLOCK - 1) // BLOCK
    chunks = max(1, min(blocks, chunks))
    _check_scratch(S, threads * size)
    for c in prange(chunks):
        at = get_thread_id() * size
        for b in range(c * blocks // chunks, (c + 1) * blocks // chunks):
            _run_block(pre, fn, xs, ys, out, grad, gs, S, at, b * BLOCK, n, act, off)


@njit(cache=True, nogil=True, error_model="numpy")
def run_ser(
    pre: int,
    fn: int,
    xs: np.ndarray,
    ys: np.ndarray,
    out: np.ndarray,
    grad: np.ndarray,
    gs: int,
    S: np.ndarray,
    size: int,
    act: np.ndarray,
    off: np.ndarray,
) -> None:
    """:func:`run_par` in this thread (``S``: at least ``size`` floats)."""
    n = xs.shape[0]
    _check_scratch(S, size)
    for s in range(0, n, BLOCK):
        _run_block(pre, fn, xs, ys, out, grad, gs, S, 0, s, n, act, off)


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
) -> None:
    """:func:`run_par` (``grad`` of shape (n, 2), or :data:`NOGRAD` for the value alone) on
    points sorted by tile (tile ``t``: ``order[starts[t]:starts[t + 1]]``),
    each block with its tile's row lists (``act``, ``offs`` of shape (tiles, loops + 1);
    ``rows``: the total number of rows of all loops). The points of a block are gathered into
    contiguous buffers and the results scattered back; a block shared by the last points of
    several tiles runs the union of their lists. Only ``S`` comes from the caller: the other
    buffers here are a few KiB per thread, and the tile path serves large inputs only."""
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
            _call(pre, _at(xb, 0), _at(yb, 0), _at(ob, 0), gp, m, _at(S, at), ap, fp)
            _call(fn, _at(xb, 0), _at(yb, 0), _at(ob, 0), gp, m, _at(S, at), ap, fp)
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
# rows. Instead of straight-line code per scene (numba's and LLVM's time grows faster than its
# length), the chains run as a program: one row of ``prog`` per step, each step a loop over the
# block's points with the opcode branch outside it (so each step vectorizes). The formulas, the
# operand order and the tie rule are those of ``codegen._Emitter.chain``: the same bits.

#: Columns of a program row: opcode; the operand's first row (its value; then the x and y
#: gradient components in the next rows); the accumulator's first row (m; then the gradient
#: components, then s, the smooth sum); -k (polynomial blends: k); 1/k; whether the operand's
#: x and y gradient components are known to be zero (as in the straight-line code: no
#: product); the same for the accumulator (polynomial blends). Rows are offsets in the block's
#: scratch space, in floats. Each step works on two slices of it (operand, accumulator): LLVM
#: then checks their overlap once and vectorizes the step.
PROG_COLS = 9
#: Opcodes: copy the first operand into the accumulator (s = 1); one hard or smooth step of a
#: min (``<``) or max (``>``) chain; finish a smooth chain (m -/+ log(s) / k, gradient / s);
#: the last row: the result's rows, copied to the outputs; a smooth blend of two operands, the
#: first already in the accumulator (blend and finish in one pass, s never stored); the
#: negated operand (a gradient component known to be zero stays +0, as in the straight-line
#: code, where it is no variable at all).
(
    OP_INIT,
    OP_MIN,
    OP_MAX,
    OP_SMIN,
    OP_SMAX,
    OP_FIN_SMIN,
    OP_FIN_SMAX,
    OP_OUT,
    OP_SMIN2,
    OP_SMAX2,
    OP_NEG,
    OP_QMIN,
    OP_CMIN,
) = range(13)


@njit(nogil=True, error_model="numpy", inline="always")
def _poly(a, b, k, ik, cubic):
    """The quadratic (cubic) polynomial blend of ``a`` (the running value) and ``b`` as
    ``ops._emit_poly`` writes it: value and the weight of ``a`` in the gradient."""
    w = a <= b
    t = k - abs(a - b)
    h = _sel(t > 0.0, t, 0.0) * ik
    m = _sel(w, a, b)
    hh = h * h
    r = _sel(cubic, m - hh * h * (k / 6.0), m - hh * (k / 4.0))
    o = _sel(cubic, hh * 0.5, h * 0.5)
    return r, _sel(w, 1.0 - o, o)


@njit(nogil=True, error_model="numpy", inline="always")
def _poly_grad(ga, gb, wa, wb, za, zb):
    """``ga * wa + gb * wb`` without the terms of components known to be zero."""
    ta = ga * wa
    tb = gb * wb
    return _sel(za, _sel(zb, 0.0, tb), _sel(zb, ta, ta + tb))


@njit(nogil=True, error_model="numpy")
def _step_vg(op, A, M, nk, ik, zx, zy, zax, zay, nv):
    """One step with gradients: operand rows ``A`` (v, gx, gy), accumulator ``M`` (m, gx, gy, s);
    the first ``nv`` points of each row."""
    B = BLOCK
    if op == OP_INIT:
        for i in range(nv):
            M[i] = A[i]
            M[B + i] = A[B + i]
            M[2 * B + i] = A[2 * B + i]
            M[3 * B + i] = 1.0
    elif op == OP_NEG:
        for i in range(nv):
            M[i] = -A[i]
            M[B + i] = _sel(zx, 0.0, -A[B + i])
            M[2 * B + i] = _sel(zy, 0.0, -A[2 * B + i])
    elif op == OP_QMIN or op == OP_CMIN:
        cubic = op == OP_CMIN
        for i in range(nv):
            r, wa = _poly(M[i], A[i], nk, ik, cubic)
            wb = 1.0 - wa
            M[B + i] = _poly_grad(M[B + i], A[B + i], wa, wb, zax, zx)
            M[2 * B + i] = _poly_grad(M[2 * B + i], A[2 * B + i], wa, wb, zay, zy)
            M[i] = r
    elif op == OP_MIN:
        for i in range(nv):
            w = A[i] < M[i]
            M[B + i] = _sel(w, A[B + i], M[B + i])
            M[2 * B + i] = _sel(w, A[2 * B + i], M[2 * B + i])
            M[i] = _sel(w, A[i], M[i])
    elif op == OP_MAX:
        for i in range(nv):
            w = A[i] > M[i]
            M[B + i] = _sel(w, A[B + i], M[B + i])
            M[2 * B + i] = _sel(w, A[2 * B + i], M[2 * B + i])
            M[i] = _sel(w, A[i], M[i])
    elif op == OP_SMIN or op == OP_SMAX:
        lt = op == OP_SMIN
        gt = not lt
        for i in range(nv):
            v = A[i]
            c = M[i]
            w = ((v < c) & lt) | ((v > c) & gt)
            e = _vexp(nk * abs(v - c))
            acc = M[3 * B + i]
            M[3 * B + i] = _sel(w, acc * e + 1.0, acc + e)
            vx = A[B + i]
            vy = A[2 * B + i]
            cx = M[B + i]
            cy = M[2 * B + i]
            M[B + i] = _sel(w, cx * e + vx, cx + _sel(zx, 0.0, vx * e))
            M[2 * B + i] = _sel(w, cy * e + vy, cy + _sel(zy, 0.0, vy * e))
            M[i] = _sel(w, v, c)
    elif op == OP_SMIN2 or op == OP_SMAX2:
        lt = op == OP_SMIN2
        gt = not lt
        sign = -1.0 if lt else 1.0
        for i in range(nv):
            v = A[i]
            c = M[i]
            w = ((v < c) & lt) | ((v > c) & gt)
            e = _vexp(nk * abs(v - c))
            acc = _sel(w, 1.0 * e + 1.0, 1.0 + e)
            vx = A[B + i]
            vy = A[2 * B + i]
            cx = M[B + i]
            cy = M[2 * B + i]
            r = 1.0 / acc
            M[B + i] = _sel(w, cx * e + vx, cx + _sel(zx, 0.0, vx * e)) * r
            M[2 * B + i] = _sel(w, cy * e + vy, cy + _sel(zy, 0.0, vy * e)) * r
            M[i] = _sel(w, v, c) + sign * (_vlog(acc) * ik)
    elif op == OP_FIN_SMIN or op == OP_FIN_SMAX:
        sign = -1.0 if op == OP_FIN_SMIN else 1.0
        for i in range(nv):
            acc = M[3 * B + i]
            M[i] = M[i] + sign * (_vlog(acc) * ik)  # m - t is m + (-t), bit for bit
            r = 1.0 / acc
            M[B + i] = M[B + i] * r
            M[2 * B + i] = M[2 * B + i] * r


@njit(nogil=True, error_model="numpy")
def _step_v(op, A, M, nk, ik, nv):
    """One value-only step: operand row ``A`` (v), accumulator ``M`` (m, s); the first ``nv``
    points of each row."""
    B = BLOCK
    if op == OP_INIT:
        for i in range(nv):
            M[i] = A[i]
            M[B + i] = 1.0
    elif op == OP_NEG:
        for i in range(nv):
            M[i] = -A[i]
    elif op == OP_QMIN or op == OP_CMIN:
        cubic = op == OP_CMIN
        for i in range(nv):
            M[i] = _poly(M[i], A[i], nk, ik, cubic)[0]
    elif op == OP_MIN:
        for i in range(nv):
            M[i] = _sel(A[i] < M[i], A[i], M[i])
    elif op == OP_MAX:
        for i in range(nv):
            M[i] = _sel(A[i] > M[i], A[i], M[i])
    elif op == OP_SMIN or op == OP_SMAX:
        lt = op == OP_SMIN
        gt = not lt
        for i in range(nv):
            v = A[i]
            c = M[i]
            w = ((v < c) & lt) | ((v > c) & gt)
            e = _vexp(nk * abs(v - c))
            acc = M[B + i]
            M[B + i] = _sel(w, acc * e + 1.0, acc + e)
            M[i] = _sel(w, v, c)
    elif op == OP_SMIN2 or op == OP_SMAX2:
        lt = op == OP_SMIN2
        gt = not lt
        sign = -1.0 if lt else 1.0
        for i in range(nv):
            v = A[i]
            c = M[i]
            w = ((v < c) & lt) | ((v > c) & gt)
            e = _vexp(nk * abs(v - c))
            acc = _sel(w, 1.0 * e + 1.0, 1.0 + e)
            M[i] = _sel(w, v, c) + sign * (_vlog(acc) * ik)
    elif op == OP_FIN_SMIN or op == OP_FIN_SMAX:
        sign = -1.0 if op == OP_FIN_SMIN else 1.0
        for i in range(nv):
            M[i] = M[i] + sign * (_vlog(M[B + i]) * ik)


@njit(nogil=True, inline="always")
def _lanes(m):
    """The points of a block of ``m`` that the fold loops and the program compute: ``m``
    rounded up to a multiple of 8 (whole vectors), so that a call on a few points does not pay
    for a whole block. Rows past them hold stale values that nothing reads."""
    return min(BLOCK, (m + 7) // 8 * 8)


@njit(nogil=True, error_model="numpy")
def _combine(S, at, prog, grad, nv):
    """Run the program ``prog`` on one block's scratch space ``S[at:]`` (its first ``nv``
    points: :func:`_lanes`)."""
    rows = 3 if grad else 1
    acc_rows = 4 if grad else 2
    for p in range(prog.shape[0] - 1):
        op = int(prog[p, 0])
        a = at + int(prog[p, 1])
        m = at + int(prog[p, 2])
        A = S[a : a + rows * BLOCK]
        M = S[m : m + acc_rows * BLOCK]
        if grad:
            _step_vg(
                op,
                A,
                M,
                prog[p, 3],
                prog[p, 4],
                prog[p, 5] != 0.0,
                prog[p, 6] != 0.0,
                prog[p, 7] != 0.0,
                prog[p, 8] != 0.0,
                nv,
            )
        else:
            _step_v(op, A, M, prog[p, 3], prog[p, 4], nv)


@njit(cache=True, nogil=True, error_model="numpy")
def combine_point_vg(F: np.ndarray, prog: np.ndarray) -> tuple[float, float, float]:
    """The program ``prog`` at one point: rows are single floats ``F[row]`` (the program's
    offsets divided by ``BLOCK``); the same formulas as :func:`_step_vg`, so the same bits.
    Returns the value and gradient."""
    for p in range(prog.shape[0] - 1):
        op = int(prog[p, 0])
        a = int(prog[p, 1]) // BLOCK
        m = int(prog[p, 2]) // BLOCK
        nk = prog[p, 3]
        ik = prog[p, 4]
        zx = prog[p, 5] != 0.0
        zy = prog[p, 6] != 0.0
        if op == OP_INIT:
            F[m] = F[a]
            F[m + 1] = F[a + 1]
            F[m + 2] = F[a + 2]
            F[m + 3] = 1.0
        elif op == OP_NEG:
            F[m] = -F[a]
            F[m + 1] = _sel(zx, 0.0, -F[a + 1])
            F[m + 2] = _sel(zy, 0.0, -F[a + 2])
        elif op == OP_QMIN or op == OP_CMIN:
            r, wa = _poly(F[m], F[a], nk, ik, op == OP_CMIN)
            wb = 1.0 - wa
            F[m + 1] = _poly_grad(F[m + 1], F[a + 1], wa, wb, prog[p, 7] != 0.0, zx)
            F[m + 2] = _poly_grad(F[m + 2], F[a + 2], wa, wb, prog[p, 8] != 0.0, zy)
            F[m] = r
        elif op == OP_MIN or op == OP_MAX:
            w = F[a] < F[m] if op == OP_MIN else F[a] > F[m]
            F[m + 1] = _sel(w, F[a + 1], F[m + 1])
            F[m + 2] = _sel(w, F[a + 2], F[m + 2])
            F[m] = _sel(w, F[a], F[m])
        elif op == OP_SMIN or op == OP_SMAX:
            v = F[a]
            c = F[m]
            w = v < c if op == OP_SMIN else v > c
            e = _vexp(nk * abs(v - c))
            acc = F[m + 3]
            F[m + 3] = _sel(w, acc * e + 1.0, acc + e)
            vx = F[a + 1]
            vy = F[a + 2]
            cx = F[m + 1]
            cy = F[m + 2]
            F[m + 1] = _sel(w, cx * e + vx, cx + _sel(zx, 0.0, vx * e))
            F[m + 2] = _sel(w, cy * e + vy, cy + _sel(zy, 0.0, vy * e))
            F[m] = _sel(w, v, c)
        elif op == OP_SMIN2 or op == OP_SMAX2:
            lt = op == OP_SMIN2
            sign = -1.0 if lt else 1.0
            v = F[a]
            c = F[m]
            w = v < c if lt else v > c
            e = _vexp(nk * abs(v - c))
            acc = _sel(w, 1.0 * e + 1.0, 1.0 + e)
            vx = F[a + 1]
            vy = F[a + 2]
            cx = F[m + 1]
            cy = F[m + 2]
            r = 1.0 / acc
            F[m + 1] = _sel(w, cx * e + vx, cx + _sel(zx, 0.0, vx * e)) * r
            F[m + 2] = _sel(w, cy * e + vy, cy + _sel(zy, 0.0, vy * e)) * r
            F[m] = _sel(w, v, c) + sign * (_vlog(acc) * ik)
        elif op == OP_FIN_SMIN or op == OP_FIN_SMAX:
            sign = -1.0 if op == OP_FIN_SMIN else 1.0
            acc = F[m + 3]
            F[m] = F[m] + sign * (_vlog(acc) * ik)
            r = 1.0 / acc
            F[m + 1] = F[m + 1] * r
            F[m + 2] = F[m + 2] * r
    a = int(prog[prog.shape[0] - 1, 1]) // BLOCK
    return F[a], F[a + 1], F[a + 2]


@njit(cache=True, nogil=True, error_model="numpy")
def combine_point_v(F: np.ndarray, prog: np.ndarray) -> float:
    """:func:`combine_point_vg` for the value alone (the rows of :func:`_step_v`)."""
    for p in range(prog.shape[0] - 1):
        op = int(prog[p, 0])
        a = int(prog[p, 1]) // BLOCK
        m = int(prog[p, 2]) // BLOCK
        nk = prog[p, 3]
        ik = prog[p, 4]
        if op == OP_INIT:
            F[m] = F[a]
            F[m + 1] = 1.0
        elif op == OP_NEG:
            F[m] = -F[a]
        elif op == OP_QMIN or op == OP_CMIN:
            F[m] = _poly(F[m], F[a], nk, ik, op == OP_CMIN)[0]
        elif op == OP_MIN:
            F[m] = _sel(F[a] < F[m], F[a], F[m])
        elif op == OP_MAX:
            F[m] = _sel(F[a] > F[m], F[a], F[m])
        elif op == OP_SMIN or op == OP_SMAX:
            v = F[a]
            c = F[m]
            w = v < c if op == OP_SMIN else v > c
            e = _vexp(nk * abs(v - c))
            acc = F[m + 1]
            F[m + 1] = _sel(w, acc * e + 1.0, acc + e)
            F[m] = _sel(w, v, c)
        elif op == OP_SMIN2 or op == OP_SMAX2:
            lt = op == OP_SMIN2
            sign = -1.0 if lt else 1.0
            v = F[a]
            c = F[m]
            w = v < c if lt else v > c
            e = _vexp(nk * abs(v - c))
            acc = _sel(w, 1.0 * e + 1.0, 1.0 + e)
            F[m] = _sel(w, v, c) + sign * (_vlog(acc) * ik)
        elif op == OP_FIN_SMIN or op == OP_FIN_SMAX:
            sign = -1.0 if op == OP_FIN_SMIN else 1.0
            F[m] = F[m] + sign * (_vlog(F[m + 1]) * ik)
    return F[int(prog[prog.shape[0] - 1, 1]) // BLOCK]


@njit(nogil=True, error_model="numpy", inline="always")
def _outputs(S, at, prog, xs, ys, out, grad, start, m, with_grad):
    """The last program row (``OP_OUT``) names the result rows: copy them out, NaN where the
    point is not finite."""
    last = prog.shape[0] - 1
    a = at + int(prog[last, 1])
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


@njit(nogil=True, error_model="numpy", inline="always")
def _run_prog_block(pre, prog, xs, ys, out, grad, gs, S, at, s, n, z, with_grad):
    """Per block: ``pre`` (the scene's loops over tables, filling the scratch rows), the combine
    program ``prog``, the outputs (``gs`` and ``grad`` as in :func:`_run_block`)."""
    m = min(s + BLOCK, n) - s
    gp = _at(grad, gs * s)
    _call(pre, _at(xs, s), _at(ys, s), _at(out, s), gp, m, _at(S, at), _at(z, 0), _at(z, 0))
    _combine(S, at, prog, with_grad, _lanes(m))
    _outputs(S, at, prog, xs, ys, out, grad, s, m, with_grad)


@njit(cache=True, parallel=True, error_model="numpy")
def run_prog_par(
    pre: int,
    prog: np.ndarray,
    xs: np.ndarray,
    ys: np.ndarray,
    out: np.ndarray,
    grad: np.ndarray,
    gs: int,
    S: np.ndarray,
    size: int,
    chunks: int,
    threads: int,
) -> None:
    """All points: per block, ``pre`` (the scene's loops over tables, filling the scratch
    rows) then the combine program ``prog``; blocks in parallel chunks (``grad`` and ``gs`` as
    in :func:`run_par`)."""
    n = xs.shape[0]
    blocks = (n + BLOCK - 1) // BLOCK
    chunks = max(1, min(blocks, chunks))
    _check_scratch(S, threads * size)
    z = np.zeros(1, dtype=np.int64)  # no row lists: the scene has no loops over rows
    for c in prange(chunks):
        at = get_thread_id() * size
        for b in range(c * blocks // chunks, (c + 1) * blocks // chunks):
            _run_prog_block(pre, prog, xs, ys, out, grad, gs, S, at, b * BLOCK, n, z, gs == 2)


@njit(cache=True, nogil=True, error_model="numpy")
def run_prog_ser(
    pre: int,
    prog: np.ndarray,
    xs: np.ndarray,
    ys: np.ndarray,
    out: np.ndarray,
    grad: np.ndarray,
    gs: int,
    S: np.ndarray,
    size: int,
) -> None:
    """:func:`run_prog_par` in this thread."""
    n = xs.shape[0]
    _check_scratch(S, size)
    z = np.zeros(1, dtype=np.int64)
    for s in range(0, n, BLOCK):
        _run_prog_block(pre, prog, xs, ys, out, grad, gs, S, 0, s, n, z, gs == 2)


def _guard():
    from fastsdf.backends.kernel.cache import guard_module

    guard_module(sys.modules[__name__])


_guard()
