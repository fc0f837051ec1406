"""Borrowed arrays for the compiled CPU kernels' hot loops: the same memory, without reference counting.

Every numba array view (``kidx[p]``, ``cols[0][base:top]``, ``st_k[ch, a:b]``) takes a reference on its parent's
memory: two calls into numba's runtime, each an atomic increment or decrement of a counter that both threads share
when the parent is a kernel argument. The walk and the update make tens of views per pixel (the compositing's
per-chunk slices, each pixel's contribution rows); on the 500k room the runtime's two functions took 20 % of the
update's samples. A view of a *borrowed* array (:func:`borrow`: its meminfo is null) costs a test and a return.

The rule that keeps this safe: the borrowed copy must not outlive what it borrows from. Kernel arguments live for
the whole call; arrays a kernel allocates are kept alive by :func:`keep_alive` after the last use of their borrowed
copy (numba frees an array after the last use of the variable that holds it, not at the end of the scope).
"""
from __future__ import annotations

from numba.core import cgutils, types
from numba.extending import intrinsic


def _null_meminfo(context, builder, ty, value):  # pragma: no cover - compiled
    src = context.make_array(ty)(context, builder, value=value)
    out = context.make_array(ty)(context, builder)
    for name in ("nitems", "itemsize", "data", "shape", "strides"):
        setattr(out, name, getattr(src, name))
    out.meminfo = cgutils.get_null_value(out.meminfo.type)
    out.parent = cgutils.get_null_value(out.parent.type)
    return out._getvalue()


@intrinsic
def borrow(typingctx, x):  # pragma: no cover - compiled
    """An array (or each array of a tuple of arrays) with the same data, shape and strides and no reference to
    the memory: its views are not reference counted. See the module's rule on lifetimes."""
    if isinstance(x, types.Array):
        def codegen(context, builder, signature, args):
            return _null_meminfo(context, builder, x, args[0])
        return x(x), codegen
    if isinstance(x, types.BaseTuple) and all(isinstance(t, types.Array) for t in x.types):
        def codegen_tuple(context, builder, signature, args):
            value = args[0]
            for i, t in enumerate(x.types):
                value = builder.insert_value(value, _null_meminfo(context, builder, t,
                                                                  builder.extract_value(args[0], i)), i)
            return value
        return x(x), codegen_tuple
    return None


@intrinsic
def keep_alive(typingctx, x):  # pragma: no cover - compiled
    """A use of ``x`` that does nothing: numba keeps ``x`` (and its memory) until here."""
    def codegen(context, builder, signature, args):
        return context.get_dummy_value()
    return types.void(x), codegen
