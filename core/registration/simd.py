"""An 8 x 8 block transpose in vector registers, for the compiled kernel (a numba intrinsic).

Numba compiles `out[j, i] = a[i, j]` to one scalar load and store per element (about a cycle
each); LLVM's vector shuffles do a block of 64 in 8 loads, 24 shuffles and 8 stores, ~3x faster
on the kernel's affinity matrices. Numba has no way to write a shuffle, hence this intrinsic,
which emits LLVM `shufflevector`s directly (portable IR: LLVM picks the instructions, e.g.
unpcklps / shufps / vperm2f128 on x86). A copy, so the values are exactly the inputs.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING, TypeGuard

from llvmlite import ir
from numba import types
from numba.core import cgutils
from numba.extending import intrinsic

if TYPE_CHECKING:
    from numba.core.base import BaseContext
    from numba.core.typing.templates import Signature

BLOCK = 8  # rows and columns of one transposed block

# The classic three-stage 8 x 8 transpose: interleave pairs of rows within 128-bit halves, then
# pairs of pairs, then swap halves. Indices select from the concatenation of two 8-vectors.
_PAIR_LO = (0, 8, 1, 9, 4, 12, 5, 13)
_PAIR_HI = (2, 10, 3, 11, 6, 14, 7, 15)
_QUAD_LO = (0, 1, 8, 9, 4, 5, 12, 13)
_QUAD_HI = (2, 3, 10, 11, 6, 7, 14, 15)
_HALF_LO = (0, 1, 2, 3, 8, 9, 10, 11)
_HALF_HI = (4, 5, 6, 7, 12, 13, 14, 15)


def _is_float_matrix(ty: types.Type) -> TypeGuard[types.Array]:
    return (
        isinstance(ty, types.Array)
        and ty.ndim == 2
        and ty.layout == "C"
        and ty.dtype in (types.float32, types.float64)
    )


@intrinsic
def transpose_block(
    typingctx: object, src: types.Type, i0: types.Type, j0: types.Type, dst: types.Type
) -> tuple[Signature, Callable[..., ir.Value]] | None:
    """dst[j0 + c, i0 + r] = src[i0 + r, j0 + c] for r, c < BLOCK (no bounds checks).

    The caller guarantees the block lies inside both arrays (C-contiguous, same float dtype).
    """
    if not (_is_float_matrix(src) and _is_float_matrix(dst) and src.dtype == dst.dtype):
        return None
    if not (isinstance(i0, types.Integer) and isinstance(j0, types.Integer)):
        return None
    sig = types.void(src, i0, j0, dst)

    def codegen(
        context: BaseContext,
        builder: ir.IRBuilder,
        signature: Signature,
        args: Sequence[ir.Value],
    ) -> ir.Value:
        src_val, i_val, j_val, dst_val = args
        src_ty, i_ty, j_ty, dst_ty = signature.args
        vec = ir.VectorType(context.get_value_type(src_ty.dtype), BLOCK)
        align = src_ty.dtype.bitwidth // 8  # rows need only element alignment
        i64 = ir.IntType(64)
        row0 = context.cast(builder, i_val, i_ty, types.int64)
        col0 = context.cast(builder, j_val, j_ty, types.int64)

        def vector_at(
            arr_ty: types.Array, arr_val: ir.Value, row: ir.Value, offset: int, col: ir.Value
        ) -> ir.Value:
            ary = context.make_array(arr_ty)(context, builder, arr_val)
            shape = cgutils.unpack_tuple(builder, ary.shape, 2)
            strides = cgutils.unpack_tuple(builder, ary.strides, 2)
            index = [builder.add(row, ir.Constant(i64, offset)), col]
            ptr = cgutils.get_item_pointer2(
                context, builder, ary.data, shape, strides, arr_ty.layout, index
            )
            return builder.bitcast(ptr, vec.as_pointer())

        def shuffle(a: ir.Value, b: ir.Value, mask: tuple[int, ...]) -> ir.Value:
            return builder.shuffle_vector(
                a, b, ir.Constant(ir.VectorType(ir.IntType(32), BLOCK), list(mask))
            )

        rows = [
            builder.load(vector_at(src_ty, src_val, row0, r, col0), align=align)
            for r in range(BLOCK)
        ]
        pairs = []
        for q in range(0, BLOCK, 2):
            pairs += [
                shuffle(rows[q], rows[q + 1], _PAIR_LO),
                shuffle(rows[q], rows[q + 1], _PAIR_HI),
            ]
        quads = []
        for base in (0, 4):
            a0, a1, a2, a3 = pairs[base : base + 4]
            quads += [
                shuffle(a0, a2, _QUAD_LO),
                shuffle(a0, a2, _QUAD_HI),
                shuffle(a1, a3, _QUAD_LO),
                shuffle(a1, a3, _QUAD_HI),
            ]
        cols = [shuffle(quads[c], quads[c + 4], _HALF_LO) for c in range(4)]
        cols += [shuffle(quads[c], quads[c + 4], _HALF_HI) for c in range(4)]
        for c in range(BLOCK):
            builder.store(cols[c], vector_at(dst_ty, dst_val, col0, c, row0), align=align)
        return context.get_dummy_value()

    return sig, codegen
