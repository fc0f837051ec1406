"""A software prefetch for the compiled CPU kernels: loops that gather rows scattered over a large array (the map's
concentrations in the model's order, the projection's per-Gaussian outputs) ask for the row a few iterations
ahead, so that its cache misses overlap the work on the current one instead of stalling it."""
from __future__ import annotations

from llvmlite import ir
from numba import njit
from numba.core import cgutils, types
from numba.extending import intrinsic


@intrinsic
def prefetch(typingctx, arr, index):  # pragma: no cover - compiled
    """Prefetch the cache line holding ``arr[index]`` for reading (``index``: an integer or a tuple of them, not
    bounds-checked: a hint, never a load, so an index past the end is harmless)."""
    sig = types.void(arr, index)

    def codegen(context, builder, signature, args):
        aryty, idxty = signature.args
        ary = context.make_array(aryty)(context, builder, args[0])
        if isinstance(idxty, types.BaseTuple):
            raw = cgutils.unpack_tuple(builder, args[1], len(idxty))
            inds = [context.cast(builder, i, t, types.intp) for i, t in zip(raw, idxty)]
        else:
            inds = [context.cast(builder, args[1], idxty, types.intp)]
        ptr = cgutils.get_item_pointer(context, builder, aryty, ary, inds, wraparound=False)
        i32 = ir.IntType(32)
        byte_ptr = builder.bitcast(ptr, ir.IntType(8).as_pointer())  # one declaration for every array type
        fnty = ir.FunctionType(ir.VoidType(), [byte_ptr.type, i32, i32, i32])
        fn = cgutils.get_or_insert_function(builder.module, fnty, "llvm.prefetch.p0")
        builder.call(fn, [byte_ptr, i32(0), i32(3), i32(1)])  # read, keep in every cache level, data
        return context.get_dummy_value()
    return sig, codegen


#: How many iterations ahead a gathering loop asks for its row: on the 500k room's add pass (50k rows of 28 float64
#: scattered over 500k) 4 rows ahead took 30 % off the pass, 16 rows 33 %, 32 rows 30 % (benchmarks/README.md).
AHEAD = 16


@njit(inline="always")
def prefetch_row(arr, row):  # pragma: no cover
    """Prefetch every cache line of row ``row`` of a C-contiguous 2-D array."""
    step = max(1, 64 // arr.itemsize)
    n = arr.shape[1]
    for c in range(0, n, step):
        prefetch(arr, (row, c))
    prefetch(arr, (row, n - 1))


@njit(inline="always")
def prefetch_ahead(arr, ids, j):  # pragma: no cover
    """In a loop over ``ids`` at position j: prefetch row ``ids[j + AHEAD]`` of ``arr`` (nothing near the end)."""
    if j + AHEAD < ids.shape[0]:
        prefetch_row(arr, ids[j + AHEAD])
