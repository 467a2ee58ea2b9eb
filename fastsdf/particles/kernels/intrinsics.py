"""Intrinsics of the particle kernels (numba ``@intrinsic``: no Python, no scene): views of
arrays without reference counts, calls through C function pointers, and the dense grid's vector
cell gathers used by the block step (the branch-free select and bit casts are
:mod:`fastsdf.intrinsics`').

Generated kernel modules import these by name (the import line carries this file's hash, so an
edit here invalidates every cached kernel)."""

from typing import Any

from llvmlite import ir
from numba import types
from numba.core import cgutils
from numba.extending import intrinsic

__all__ = ["borrow_all", "call_vg"]


def _borrowed_codegen(context, builder, ty, val):
    """``val`` of type ``ty`` with every array in it (recursively in tuples) made a view
    without a reference count."""
    if isinstance(ty, types.Array):
        src = context.make_array(ty)(context, builder, val)
        out = context.make_array(ty)(context, builder)
        for field in ("nitems", "itemsize", "data", "shape", "strides"):
            setattr(out, field, getattr(src, field))
        out.meminfo = cgutils.get_null_value(out.meminfo.type)
        out.parent = cgutils.get_null_value(out.parent.type)
        return out._getvalue()
    if isinstance(ty, types.BaseTuple):
        vals = [
            _borrowed_codegen(context, builder, t, builder.extract_value(val, k))
            for k, t in enumerate(ty.types)
        ]
        return context.make_tuple(builder, ty, vals)
    return val


def _borrowable(ty: Any) -> bool:
    if isinstance(ty, types.BaseTuple):
        return all(_borrowable(t) for t in ty.types)
    return isinstance(ty, (types.Array, types.Number, types.Boolean))


@intrinsic
def borrow_all(typingctx, data):
    """``data`` (an array, a number, or tuples of them, nested) with every array replaced by a
    view without a reference count (null meminfo).

    Passing an array to a function numba does not inline costs an atomic increment and
    decrement of its reference count around every call; with several threads querying one
    grid, those atomics on one shared cache line serialise the threads. The kernel makes such
    views once per block; the caller keeps the real arrays alive.
    """
    if not _borrowable(data):
        return None

    def codegen(context, builder, signature, args):
        return _borrowed_codegen(context, builder, signature.args[0], args[0])

    return data(data), codegen


@intrinsic
def call_vg(typingctx, address, x, y):
    """``(d, dd/dx, dd/dy)`` from the C function ``void f(double x, double y, double *out)`` at
    ``address`` (a numba ``cfunc``): the exact fallback of grid worlds, bound at run time so
    that the kernel does not depend on the scene."""
    if not isinstance(address, types.Integer):
        return None
    sig = types.UniTuple(types.float64, 3)(address, types.float64, types.float64)

    def codegen(context, builder, signature, args):
        a, xv, yv = args
        dbl = ir.DoubleType()
        fnty = ir.FunctionType(ir.VoidType(), [dbl, dbl, dbl.as_pointer()])
        fp = builder.inttoptr(a, fnty.as_pointer())
        out = cgutils.alloca_once(builder, dbl, size=3)
        builder.call(fp, [xv, yv, out])
        vals = [builder.load(builder.gep(out, [ir.Constant(ir.IntType(32), k)])) for k in range(3)]
        return context.make_tuple(builder, signature.return_type, vals)

    return sig, codegen


@intrinsic
def _cell_vg(typingctx, grid, a, c, tx, ty):
    """``(d, dd/dx, dd/dy)``: the bilinear blends of a stored-gradient grid's cell, from its two
    runs ``grid[a:a + 6]`` (nodes (i, j), (i, j + 1)) and ``grid[c:c + 6]`` (nodes (i + 1, j),
    (i + 1, j + 1)), each ``[d, dd/dx, dd/dy]`` per node: the three channels in the lanes of
    one vector (two loads per run, the same operations per channel as the scalar blend, so the
    same bits). Reads only inside the runs."""
    if not (
        isinstance(grid, types.Array)
        and grid.dtype in (types.float64, types.float32)
        and isinstance(a, types.Integer)
        and isinstance(c, types.Integer)
    ):
        return None
    sig = types.UniTuple(types.float64, 3)(grid, a, c, tx, ty)

    def codegen(context, builder, signature, args):
        ary = context.make_array(signature.args[0])(context, builder, args[0])
        el = context.get_data_type(signature.args[0].dtype)
        dbl = ir.DoubleType()
        vd = ir.VectorType(dbl, 4)
        i32 = ir.IntType(32)
        intp = context.get_value_type(types.intp)

        def load4(idx):
            ptr = builder.bitcast(builder.gep(ary.data, [idx]), ir.VectorType(el, 4).as_pointer())
            v = builder.load(ptr, align=signature.args[0].dtype.bitwidth // 8)
            return v if el == dbl else builder.fpext(v, vd)

        def runs(start):
            start = context.cast(builder, start, signature.args[1], types.intp)
            lo = load4(start)  # n0.d, n0.gx, n0.gy, n1.d
            hi = load4(builder.add(start, ir.Constant(intp, 2)))  # n0.gy, n1.d, n1.gx, n1.gy
            mask = ir.Constant(ir.VectorType(i32, 4), [1, 2, 3, 3])
            return lo, builder.shuffle_vector(hi, hi, mask)  # n1.d, n1.gx, n1.gy, -

        def splat(x, ty):
            x = context.cast(builder, x, ty, types.float64)
            v = builder.insert_element(ir.Constant(vd, ir.Undefined), x, ir.Constant(i32, 0))
            return builder.shuffle_vector(v, v, ir.Constant(ir.VectorType(i32, 4), [0] * 4))

        a0, a1 = runs(args[1])
        c0, c1 = runs(args[2])
        vtx = splat(args[3], signature.args[3])
        vty = splat(args[4], signature.args[4])
        lo = builder.fadd(a0, builder.fmul(vty, builder.fsub(a1, a0)))
        hi = builder.fadd(c0, builder.fmul(vty, builder.fsub(c1, c0)))
        r = builder.fadd(lo, builder.fmul(vtx, builder.fsub(hi, lo)))
        vals = [builder.extract_element(r, ir.Constant(i32, k)) for k in range(3)]
        return context.make_tuple(builder, signature.return_type, vals)

    return sig, codegen


@intrinsic
def _gather4(typingctx, grid, S, q, row, rows):
    """:func:`_cell_vg` for the four particles ``q .. q + 3`` of a block. ``rows``: the
    offsets in ``S`` of seven rows ``(idx_at, tx_at, ty_at, d_at, gx_at, gy_at, r_at)``: their
    flat indices (int64 bits in ``S[idx_at + q:]``), fractions (``tx_at``, ``ty_at``) in, the
    values and gradients out as three vector stores into ``S[d_at + q:]``, ``gx_at``,
    ``gy_at`` (the four results transposed in registers; a scalar store per value would make
    the store port the bottleneck). Returns how many of the four have ``d <= S[r_at + q]``."""
    if not (
        isinstance(grid, types.Array)
        and grid.dtype in (types.float64, types.float32)
        and isinstance(S, types.Array)
        and S.dtype == types.float64
        and isinstance(rows, types.UniTuple)
        and rows.count == 7
        and isinstance(rows.dtype, types.Integer)
    ):
        return None
    sig = types.int64(grid, S, q, row, rows)

    def codegen(context, builder, signature, args):
        gty = signature.args[0]
        g = context.make_array(gty)(context, builder, args[0])
        sa = context.make_array(signature.args[1])(context, builder, args[1])
        el = context.get_data_type(gty.dtype)
        dbl = ir.DoubleType()
        i32 = ir.IntType(32)
        i64 = ir.IntType(64)
        vd = ir.VectorType(dbl, 4)
        intp = context.get_value_type(types.intp)

        def idx(k):
            """Argument ``k`` as an index; 4 and on: the offsets in ``rows``."""
            if k < 4:
                return context.cast(builder, args[k], signature.args[k], types.intp)
            rty = signature.args[4]
            return context.cast(
                builder, builder.extract_value(args[4], k - 4), rty.dtype, types.intp
            )

        qi = idx(2)
        rowi = idx(3)

        def sptr(k):
            ptr = builder.gep(sa.data, [builder.add(idx(k), qi)])
            return builder.bitcast(ptr, vd.as_pointer())

        def mask(vals):
            return ir.Constant(ir.VectorType(i32, len(vals)), vals)

        def load4(start):
            ptr = builder.bitcast(builder.gep(g.data, [start]), ir.VectorType(el, 4).as_pointer())
            v = builder.load(ptr, align=gty.dtype.bitwidth // 8)
            return v if el == dbl else builder.fpext(v, vd)

        def runs(start):
            lo = load4(start)
            hi = load4(builder.add(start, ir.Constant(intp, 2)))
            return lo, builder.shuffle_vector(hi, hi, mask([1, 2, 3, 3]))

        def splat(vec, k):
            return builder.shuffle_vector(vec, vec, mask([k] * 4))

        ivec = builder.bitcast(builder.load(sptr(4), align=8), ir.VectorType(i64, 4))
        txv = builder.load(sptr(5), align=8)
        tyv = builder.load(sptr(6), align=8)
        res = []
        for k in range(4):
            a = builder.extract_element(ivec, ir.Constant(i32, k))
            a0, a1 = runs(a)
            c0, c1 = runs(builder.add(a, rowi))
            tx = splat(txv, k)
            ty = splat(tyv, k)
            lo = builder.fadd(a0, builder.fmul(ty, builder.fsub(a1, a0)))
            hi = builder.fadd(c0, builder.fmul(ty, builder.fsub(c1, c0)))
            res.append(builder.fadd(lo, builder.fmul(tx, builder.fsub(hi, lo))))
        t0 = builder.shuffle_vector(res[0], res[1], mask([0, 4, 2, 6]))
        t1 = builder.shuffle_vector(res[2], res[3], mask([0, 4, 2, 6]))
        t2 = builder.shuffle_vector(res[0], res[1], mask([1, 5, 3, 7]))
        t3 = builder.shuffle_vector(res[2], res[3], mask([1, 5, 3, 7]))
        dv = builder.shuffle_vector(t0, t1, mask([0, 1, 4, 5]))
        builder.store(dv, sptr(7), align=8)
        builder.store(builder.shuffle_vector(t2, t3, mask([0, 1, 4, 5])), sptr(8), align=8)
        builder.store(builder.shuffle_vector(t0, t1, mask([2, 3, 6, 7])), sptr(9), align=8)
        le = builder.zext(
            builder.fcmp_ordered("<=", dv, builder.load(sptr(10), align=8)), ir.VectorType(i64, 4)
        )
        n = builder.extract_element(le, ir.Constant(i32, 0))
        for k in range(1, 4):
            n = builder.add(n, builder.extract_element(le, ir.Constant(i32, k)))
        return n

    return sig, codegen
