"""Low-level helpers for generated kernels.

numba lowers ``a if c else b`` to a branch. In SDF code the condition (which operand of a min
wins, which side of a blend is larger) flips from point to point, so such branches mispredict
about half the time; :func:`select` emits LLVM's branch-free ``select`` instead. Both operands
are always evaluated, so they must be safe to compute (no side effects, no traps).
"""

from numba import types
from numba.extending import intrinsic


@intrinsic
def select(typingctx, cond, a, b):
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
