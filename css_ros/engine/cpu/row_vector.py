"""An 8-wide float32 row accumulation for the compiled CPU kernels: ``acc[:8] += sum_i w_i rows[j_i, :8]`` as one
vector step per row.

numba compiles with LLVM's straight-line (SLP) vectoriser off, and a loop over a row's 8 columns into an
accumulator array is left scalar (LLVM cannot tell that the accumulator and the rows do not overlap): 8 loads, 32
scalar FMAs and 8 stores for every four rows of the render's short shading path. Here the rows are loaded as
``<8 x float>`` vectors (no row views either, so no reference counting per row).

The sums are formed as the loops they replace wrote them (``(w0 r0 + w1 r1) + (w2 r2 + w3 r3)``, then added to the
accumulator), with LLVM free to contract multiplies and adds into FMAs as under the kernels' ``fastmath``.
"""
from __future__ import annotations

from llvmlite import ir
from numba.core import types
from numba.extending import intrinsic

#: Columns of one vector step (float32 lanes of a 256-bit register).
WIDTH = 8
_FLAGS = ("contract", "reassoc")


def _check(acc: types.Type, rows: types.Type) -> bool:
    return (isinstance(acc, types.Array) and acc.ndim == 1 and acc.dtype == types.float32 and acc.layout == "C"
            and isinstance(rows, types.Array) and rows.ndim == 2 and rows.dtype == types.float32
            and rows.layout == "C")


def _row_loader(context, builder, rows_ty, rows_val):  # pragma: no cover - compiled
    """A function j -> the <8 x float> at rows[j, 0:8] (no bounds check: the callers' indices are list entries)."""
    rows = context.make_array(rows_ty)(context, builder, rows_val)
    stride = builder.extract_value(rows.strides, 0)
    base = builder.ptrtoint(rows.data, stride.type)
    vec = ir.VectorType(ir.FloatType(), WIDTH)

    def load(j, j_ty):
        j = context.cast(builder, j, j_ty, types.intp)
        addr = builder.add(base, builder.mul(j, stride))
        return builder.load(builder.inttoptr(addr, vec.as_pointer()), align=4)
    return load


def _splat(builder, w):  # pragma: no cover - compiled
    vec = ir.VectorType(ir.FloatType(), WIDTH)
    one = builder.insert_element(ir.Constant(vec, ir.Undefined), w, ir.IntType(32)(0))
    return builder.shuffle_vector(one, ir.Constant(vec, ir.Undefined), ir.Constant(ir.VectorType(ir.IntType(32),
                                                                                                  WIDTH), [0] * WIDTH))


def _add_to(context, builder, acc_ty, acc_val, value):  # pragma: no cover - compiled
    acc = context.make_array(acc_ty)(context, builder, acc_val)
    ptr = builder.bitcast(acc.data, value.type.as_pointer())
    builder.store(builder.fadd(builder.load(ptr, align=4), value, flags=_FLAGS), ptr, align=4)


@intrinsic
def add_rows4(typingctx, acc, rows, j0, j1, j2, j3, w0, w1, w2, w3):  # pragma: no cover - compiled
    """acc[:8] += (w0 rows[j0, :8] + w1 rows[j1, :8]) + (w2 rows[j2, :8] + w3 rows[j3, :8]).

    acc: 1-D C float32 (>= 8 entries); rows: 2-D C float32 (>= 8 columns, indices not checked); w: float32."""
    if not _check(acc, rows) or any(w != types.float32 for w in (w0, w1, w2, w3)):
        return None
    sig = types.void(acc, rows, j0, j1, j2, j3, w0, w1, w2, w3)

    def codegen(context, builder, signature, args):
        load = _row_loader(context, builder, signature.args[1], args[1])
        terms = [builder.fmul(_splat(builder, args[6 + i]), load(args[2 + i], signature.args[2 + i]), flags=_FLAGS)
                 for i in range(4)]
        s = builder.fadd(builder.fadd(terms[0], terms[1], flags=_FLAGS), builder.fadd(terms[2], terms[3],
                                                                                         flags=_FLAGS), flags=_FLAGS)
        _add_to(context, builder, signature.args[0], args[0], s)
        return context.get_dummy_value()
    return sig, codegen


@intrinsic
def add_row(typingctx, acc, rows, j, w):  # pragma: no cover - compiled
    """acc[:8] += w rows[j, :8] (types as :func:`add_rows4`)."""
    if not _check(acc, rows) or w != types.float32:
        return None
    sig = types.void(acc, rows, j, w)

    def codegen(context, builder, signature, args):
        load = _row_loader(context, builder, signature.args[1], args[1])
        _add_to(context, builder, signature.args[0], args[0],
                builder.fmul(_splat(builder, args[3]), load(args[2], signature.args[2]), flags=_FLAGS))
        return context.get_dummy_value()
    return sig, codegen
