"""Scene-independent batch kernels: they call a scene's block functions through pointers.

A scene's generated module defines ``_block_v`` / ``_block_vg`` (see :mod:`fastsdf._simd`), one
block of at most ``BLOCK`` points, over raw pointers with the signature :data:`BLOCK_SIG`
``(xs, ys, out, grad, n, scratch)``, and for long scenes ``_fold_v`` / ``_fold_vg`` (the loops
over same-shape subexpressions, run first on the same block). The kernels here loop over the
blocks (``prange`` over chunks of blocks, or serially) and call those functions by address: they
do not depend on the scene, so each is compiled once per installation and cached beside this
file. A new scene then compiles only its block functions. The parallel kernel used to be
compiled per scene (numba's ``parfor`` lowering and its gufunc, and LLVM optimizing the block
function again inside every caller it was linked into), which cost about as much as the block
function itself. Two indirect calls per block of 512 points cost nothing measurable.
"""

from __future__ import annotations

import sys

import numba
import numpy as np
from llvmlite import ir
from numba import get_thread_id, njit, prange, types
from numba.extending import intrinsic

from ._simd import BLOCK

__all__ = ["BLOCK_SIG", "BlockFn", "NOFOLD", "max_threads", "run_v_par", "run_v_ser", "run_vg_par",
           "run_vg_ser"]

_P = types.CPointer(types.float64)
#: ``(xs, ys, out, grad, n, scratch)``: pointers to the block's first point in each array,
#: ``grad`` flat (x, y pairs; ignored by value-only blocks), and the block's scratch space.
BLOCK_SIG = types.void(_P, _P, _P, _P, types.intp, _P)


@intrinsic
def _call(typingctx, address, xp, yp, op, gp, n, sp):
    """Call the compiled function at ``address`` (an integer: the C-callable wrapper of a
    function with the signature :data:`BLOCK_SIG`) with the other arguments."""
    sig = types.void(types.intp, _P, _P, _P, _P, types.intp, _P)

    def codegen(context, builder, signature, args):
        fnty = ir.FunctionType(context.get_value_type(types.none),
                               [context.get_value_type(t) for t in BLOCK_SIG.args])
        fn = builder.inttoptr(args[0], fnty.as_pointer())
        builder.call(fn, args[1:])
        return context.get_dummy_value()

    return sig, codegen


@intrinsic
def _at(typingctx, arr, index):
    """Pointer to ``arr[index]`` (1-d contiguous float64 array); no bounds check."""
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

    def __init__(self, dispatcher):
        self.dispatcher = dispatcher
        self._addr = None

    @property
    def address(self) -> int:
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


@njit(cache=True, nogil=True, error_model="numpy")
def _nofold(xp, yp, op, gp, n, sp):
    """The ``pre`` function of a scene without loops of its own to run first: nothing."""
    return


#: ``pre`` for scenes whose block function needs nothing before it.
NOFOLD = BlockFn(_nofold)


@njit(cache=True, parallel=True, error_model="numpy")
def run_vg_par(pre, fn, xs, ys, out, grad, size, chunks, threads):
    """Value and gradient (``grad`` flat, x y pairs) at all points: ``pre`` then ``fn`` on each
    block, blocks in parallel chunks, each thread with ``size`` floats of scratch space
    (``threads``: :func:`max_threads`)."""
    n = xs.shape[0]
    blocks = (n + BLOCK - 1) // BLOCK
    chunks = max(1, min(blocks, chunks))
    S = np.empty(threads * size)
    for c in prange(chunks):
        at = get_thread_id() * size
        for b in range(c * blocks // chunks, (c + 1) * blocks // chunks):
            s = b * BLOCK
            m = min(s + BLOCK, n) - s
            _call(pre, _at(xs, s), _at(ys, s), _at(out, s), _at(grad, 2 * s), m, _at(S, at))
            _call(fn, _at(xs, s), _at(ys, s), _at(out, s), _at(grad, 2 * s), m, _at(S, at))


@njit(cache=True, nogil=True, error_model="numpy")
def run_vg_ser(pre, fn, xs, ys, out, grad, size):
    """:func:`run_vg_par` in this thread."""
    n = xs.shape[0]
    S = np.empty(size)
    for s in range(0, n, BLOCK):
        m = min(s + BLOCK, n) - s
        _call(pre, _at(xs, s), _at(ys, s), _at(out, s), _at(grad, 2 * s), m, _at(S, 0))
        _call(fn, _at(xs, s), _at(ys, s), _at(out, s), _at(grad, 2 * s), m, _at(S, 0))


@njit(cache=True, parallel=True, error_model="numpy")
def run_v_par(pre, fn, xs, ys, out, size, chunks, threads):
    """Value at all points (the block functions' ``grad`` pointer is not used)."""
    n = xs.shape[0]
    blocks = (n + BLOCK - 1) // BLOCK
    chunks = max(1, min(blocks, chunks))
    S = np.empty(threads * size)
    for c in prange(chunks):
        at = get_thread_id() * size
        for b in range(c * blocks // chunks, (c + 1) * blocks // chunks):
            s = b * BLOCK
            m = min(s + BLOCK, n) - s
            _call(pre, _at(xs, s), _at(ys, s), _at(out, s), _at(out, s), m, _at(S, at))
            _call(fn, _at(xs, s), _at(ys, s), _at(out, s), _at(out, s), m, _at(S, at))


@njit(cache=True, nogil=True, error_model="numpy")
def run_v_ser(pre, fn, xs, ys, out, size):
    """:func:`run_v_par` in this thread."""
    n = xs.shape[0]
    S = np.empty(size)
    for s in range(0, n, BLOCK):
        m = min(s + BLOCK, n) - s
        _call(pre, _at(xs, s), _at(ys, s), _at(out, s), _at(out, s), m, _at(S, 0))
        _call(fn, _at(xs, s), _at(ys, s), _at(out, s), _at(out, s), m, _at(S, 0))


def _guard():
    from ._cache import guard_module
    guard_module(sys.modules[__name__])


_guard()
