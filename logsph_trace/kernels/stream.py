"""Copies that bypass the cache, for output written once and read later.

The ordered chunks (``ordered.place``) cannot write a segment straight to
its final place: they trace into a small scratch and copy it there
afterwards. An ordinary store to memory that is not in the
cache first reads the line it writes into (a read for ownership), so such a
copy moves each target byte between memory and the cache twice. A
non-temporal store writes the line without reading it, and leaves the cache
to the tracing. On a 2-core AMD EPYC, copying 6M
segments (168 MB) from a 32K-segment scratch into memory took 16.0 ms as a
loop of plain stores, 13.3 ms as three ``memcpy`` and 7.5 ms with these
stores.

The stores are 32 bytes wide and aligned, through LLVM's ``!nontemporal``
hint (``movnt`` on x86, ``stnp`` on AArch64); the few elements before the
first aligned address and after the last whole vector are copied plainly.
Non-temporal stores are weakly ordered, so every copy ends with a full
fence: the thread that made it has finished writing before it returns.

With ``NUMBA_DISABLE_JIT=1``, or where Numba lacks the parts the stores
are written with (as ``atomic.AVAILABLE``), the stores are plain copies.
"""

import numba

from .._jit import jit
from .atomic import AVAILABLE

# Bytes one non-temporal store writes; its target address must be a multiple.
STREAM_BYTES = 32

if not AVAILABLE:

    def _stream32(dst, di, src, si):
        """Stand-in: copy 32 bytes' worth of elements from src[si] to dst[di], plainly."""
        for k in range(STREAM_BYTES // dst.itemsize):
            dst[di + k] = src[si + k]

    def _store_fence():
        """Stand-in: nothing to order."""

    if not numba.config.DISABLE_JIT:
        _stream32 = jit(inline="always")(_stream32)
        _store_fence = jit(inline="always")(_store_fence)

else:
    from llvmlite import ir
    from numba import types
    from numba.core import cgutils
    from numba.extending import intrinsic

    @intrinsic
    def _stream32(typingctx, dst, di, src, si):
        """Copy 32 bytes from ``&src[si]`` to ``&dst[di]`` (32-byte aligned), non-temporally.

        1D arrays of one dtype; no bounds check (the caller's loop has one).
        """
        sig = types.void(dst, di, src, si)

        def codegen(context, builder, signature, args):
            dst_type, _, src_type, _ = signature.args
            dst_array = context.make_array(dst_type)(context, builder, args[0])
            src_array = context.make_array(src_type)(context, builder, args[2])
            target = cgutils.get_item_pointer(context, builder, dst_type, dst_array, [args[1]],
                                              wraparound=False)
            source = cgutils.get_item_pointer(context, builder, src_type, src_array, [args[3]],
                                              wraparound=False)
            vector = ir.VectorType(ir.IntType(64), STREAM_BYTES // 8).as_pointer()
            value = builder.load(builder.bitcast(source, vector), align=1)
            store = builder.store(value, builder.bitcast(target, vector), align=STREAM_BYTES)
            store.set_metadata("nontemporal",
                               builder.module.add_metadata([ir.Constant(ir.IntType(32), 1)]))
            return context.get_dummy_value()

        return sig, codegen

    @intrinsic
    def _store_fence(typingctx):
        """A full memory fence (``mfence`` on x86): orders the non-temporal stores before it."""
        sig = types.void()

        def codegen(context, builder, signature, args):
            builder.fence("seq_cst")
            return context.get_dummy_value()

        return sig, codegen


@jit(inline="always")
def stream_copy(src, source, dst, target, count):
    """``dst[target:target + count] = src[source:source + count]`` with non-temporal stores.

    1D C-contiguous arrays of one dtype that do not overlap; the caller
    fences (``stream_segments``). A target whose elements are not aligned to
    their size (never one numpy allocated) is copied with plain stores.
    """
    size = dst.itemsize
    per = STREAM_BYTES // size
    address = dst.ctypes.data + target * size
    head = min(count, ((STREAM_BYTES - address % STREAM_BYTES) % STREAM_BYTES) // size)
    if (address + head * size) % STREAM_BYTES != 0:
        head = count  # elements not aligned to their size (not numpy's allocator): all plain
    for k in range(head):
        dst[target + k] = src[source + k]
    k = head
    while k + per <= count:
        _stream32(dst, target + k, src, source + k)
        k += per
    for m in range(k, count):
        dst[target + m] = src[source + m]


@jit(inline="always")
def stream_segments(from_cells, from_enter, from_exit, source, count, cells, t_enter, t_exit,
                    target):
    """Copy ``count`` segments from row ``source`` of the first arrays to row ``target``
    of the others, bypassing the cache (C-contiguous arrays; see the module docstring)."""
    stream_copy(from_cells.reshape(-1), 3 * source, cells.reshape(-1), 3 * target, 3 * count)
    stream_copy(from_enter, source, t_enter, target, count)
    stream_copy(from_exit, source, t_exit, target, count)
    _store_fence()
