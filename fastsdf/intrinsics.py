"""Numeric intrinsics that the evaluators and the physics both compile (the bottom layer:
every kernel may import them).

numba lowers ``a if c else b`` to a branch. In SDF code the condition (which operand of a min
wins, which side of a blend is larger) flips from point to point, so such branches mispredict
about half the time; :func:`select` emits LLVM's branch-free ``select`` instead. Both operands
are always evaluated, so they must be safe to compute (no side effects, no traps).

:func:`f64_bits` and :func:`bits_f64` reinterpret a float64 as an int64 and back (no
conversion) and :func:`fmuladd` is a multiply-add that may be fused: the vectorizable elementary
functions of :mod:`fastsdf.backends.kernel.vmath` are built from them.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from llvmlite import ir
from numba import types
from numba.core import cgutils
from numba.extending import intrinsic

__all__ = ["select", "f64_bits", "bits_f64", "fmuladd"]


@intrinsic
def select(
    typingctx: object, cond: types.Type, a: types.Type, b: types.Type
) -> tuple[Any, Callable] | None:
    """``a if cond else b`` for float64 values, compiled without a branch."""
    if not isinstance(cond, types.Boolean):
        return None
    sig = types.float64(cond, types.float64, types.float64)

    def codegen(context, builder, signature, args):
        c, x, y = args
        x = context.cast(builder, x, signature.args[1], types.float64)
        y = context.cast(builder, y, signature.args[2], types.float64)
        return builder.select(c, x, y)

    return sig, codegen


@intrinsic
def f64_bits(typingctx: object, x: types.Type) -> tuple[Any, Callable] | None:
    """The IEEE-754 bit pattern of a float64 as an int64 (a bit cast, no conversion)."""
    if not isinstance(x, types.Float):
        return None
    sig = types.int64(x)

    def codegen(context, builder, signature, args):
        v = context.cast(builder, args[0], signature.args[0], types.float64)
        return builder.bitcast(v, ir.IntType(64))

    return sig, codegen


@intrinsic
def bits_f64(typingctx: object, i: types.Type) -> tuple[Any, Callable] | None:
    """The float64 whose IEEE-754 bit pattern is the int64 ``i`` (a bit cast, no conversion)."""
    if not isinstance(i, types.Integer):
        return None
    sig = types.float64(i)

    def codegen(context, builder, signature, args):
        v = context.cast(builder, args[0], signature.args[0], types.int64)
        return builder.bitcast(v, ir.DoubleType())

    return sig, codegen


@intrinsic
def fmuladd(
    typingctx: object, a: types.Type, b: types.Type, c: types.Type
) -> tuple[Any, Callable] | None:
    """``a * b + c`` for float64, fused into one FMA instruction where the CPU has one (then
    rounded once, so the result may differ from ``a * b + c`` in the last bit); otherwise a
    multiplication and an addition. Vectorizes like plain arithmetic (LLVM's ``fmuladd``)."""
    if not all(isinstance(t, types.Float) for t in (a, b, c)):
        return None
    sig = types.float64(a, b, c)

    def codegen(context, builder, signature, args):
        vals = [context.cast(builder, v, t, types.float64) for v, t in zip(args, signature.args)]
        dbl = ir.DoubleType()
        fn = cgutils.get_or_insert_function(
            builder.module, ir.FunctionType(dbl, [dbl] * 3), "llvm.fmuladd.f64"
        )
        return builder.call(fn, vals)

    return sig, codegen
