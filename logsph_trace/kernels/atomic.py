"""Flags that several threads set in one array: single stores with a defined meaning.

The occupancy update marks a scan's cells, those its rays cross and those
they end in, in one shared array of bytes, from all threads at once. Two
rays that cross or end in the same cell store the same flag there; with
ordinary stores that is a data race, which LLVM's memory model leaves
undefined. ``store_relaxed`` and ``load_relaxed`` are atomic accesses
without ordering (LLVM ``monotonic``): on x86 and AArch64 the same single
instructions, now with a defined result. The walk that stores the crossed
cells' flags also compiles for the GPU, where numba-cuda's NVVM takes no
atomic store: there ``store_relaxed`` is PTX's ``st.volatile``, which PTX's
memory model makes a relaxed store (``.sys`` scope) since sm_70. ``exchange`` swaps a flag
out atomically (``xchg``, a locked instruction, so worth a relaxed load
first), so that of all the rays ending in one cell exactly one takes its
flag, and the cell is updated once, whichever thread that is.

The batch path that places chunks of rays in order (``kernels.ordered``)
hands out chunks with ``fetch_add`` and passes their positions from thread
to thread with ``store_ordered`` and ``load_ordered``: sequentially
consistent accesses (LLVM ``seq_cst``), so that of two threads that each
store one value and then load the other's, at least one sees the other's
store.

The coherent scan's samples, the first ray of each direction bin, are
found by all threads at once with ``fetch_min`` (the lowest row wins,
whichever thread gets there first); so are its bins' limits. The radial
scan's free extent of each column is raised with ``fetch_max``. A minimum
or a maximum does not depend on the order the threads come in, so one
shared array gives the same result on any number of threads, where a row
per thread would have to be read, all rows, by whatever merges them.
``lower_to`` and ``raise_to`` wrap the two with a relaxed load first, so
the locked instruction runs only where it changes the value.

A thread that waits for another's store spins on its loads a while, then
calls ``yield_thread`` between them (``ordered.pause``): the C library's
``sched_yield``, which hands the CPU to another runnable thread, if any.
With more threads than CPUs the one being waited for may be among those.

These are LLVM instructions that Numba does not offer: they are written
with ``numba.extending.intrinsic``, LLVM IR through llvmlite, and Numba's
``cgutils``. Where a release lacks any of those, ``AVAILABLE`` is False and
all nine are plain loads and stores, as they are under
``NUMBA_DISABLE_JIT=1``: every parallel kernel then runs on one thread
(``_jit.Guarded``), and a batch takes the serial pass, so nothing races.
``tests/test_nojit.py`` imports the package so, in a fresh process.
"""

import ctypes
import sys

import numba

from .._jit import jit

try:
    from llvmlite import binding as llvm
    from llvmlite import ir
    from numba import types
    from numba.core import cgutils
    from numba.extending import intrinsic

    _get_item_pointer = cgutils.get_item_pointer
    _get_or_insert_function = cgutils.get_or_insert_function
    AVAILABLE = not numba.config.DISABLE_JIT
except (ImportError, AttributeError):
    AVAILABLE = False

if not AVAILABLE:

    def store_relaxed(array, index, value):
        """Stand-in: ``array[index] = value``."""
        array[index] = value

    def load_relaxed(array, index):
        """Stand-in: ``array[index]``."""
        return array[index]

    def exchange(array, index, value):
        """Stand-in: set ``array[index]`` to ``value``; return what it held."""
        old = array[index]
        array[index] = value
        return old

    def fetch_add(array, index, value):
        """Stand-in: add ``value`` to ``array[index]``; return what it held."""
        old = array[index]
        array[index] = old + value
        return old

    def fetch_min(array, index, value):
        """Stand-in: lower ``array[index]`` to ``value`` if above; return what it held."""
        old = array[index]
        array[index] = min(old, value)
        return old

    def fetch_max(array, index, value):
        """Stand-in: raise ``array[index]`` to ``value`` if below; return what it held."""
        old = array[index]
        array[index] = max(old, value)
        return old

    store_ordered = store_relaxed
    load_ordered = load_relaxed

    def yield_thread():
        """Stand-in: nothing (the kernels that wait run on one thread here)."""

    if not numba.config.DISABLE_JIT:  # the stand-ins, compiled
        (store_relaxed, load_relaxed, exchange, fetch_add, fetch_min, fetch_max, yield_thread) = (
            jit(inline="always")(f) for f in (store_relaxed, load_relaxed, exchange, fetch_add,
                                              fetch_min, fetch_max, yield_thread))
        store_ordered = store_relaxed
        load_ordered = load_relaxed

else:

    def _element_pointer(context, builder, array_type, array, index):
        return _get_item_pointer(context, builder, array_type,
                                        context.make_array(array_type)(context, builder, array),
                                        [index], wraparound=False)

    # PTX's ``st.volatile``, by the size of the item: since sm_70 it is
    # ``st.relaxed.sys``, a relaxed store (PTX ISA, memory consistency model),
    # and older GPUs take it too. Items of 1 and 2 bytes come from a 16-bit
    # register.
    _PTX_STORES = {1: ("u8", "h", 16), 2: ("u16", "h", 16), 4: ("u32", "r", 32),
                   8: ("u64", "l", 64)}

    def _store(ordering):
        """Code for ``array[index] = value`` as one atomic store with ``ordering``.

        numba-cuda compiles through NVVM, which takes no atomic store. There,
        where only the relaxed store is asked for (the one ``walk_ray``, which
        also runs on the GPU, uses), it is PTX's volatile store, the relaxed
        store of PTX's own memory model.
        """

        def codegen(context, builder, signature, args):
            array_type, _, value_type = signature.args
            pointer = _element_pointer(context, builder, array_type, args[0], args[1])
            item = context.cast(builder, args[2], value_type, array_type.dtype)
            size = context.get_abi_sizeof(context.get_data_type(array_type.dtype))
            if getattr(context, "target_name", "cpu") != "cuda":
                builder.store_atomic(item, pointer, ordering, size)
            elif ordering == "monotonic" and size in _PTX_STORES:
                kind, register, bits = _PTX_STORES[size]
                width = ir.IntType(bits)
                if isinstance(item.type, ir.IntType):
                    value = builder.zext(item, width) if item.type.width < bits else item
                else:
                    value = builder.bitcast(item, width)
                store = ir.InlineAsm(ir.FunctionType(ir.VoidType(), [ir.IntType(64), width]),
                                     f"st.volatile.{kind} [$0], $1;", f"l,{register},~{{memory}}",
                                     side_effect=True)
                builder.call(store, [builder.ptrtoint(pointer, ir.IntType(64)), value])
            else:
                raise NotImplementedError(f"no {ordering} store of {size} bytes under CUDA")
            return context.get_dummy_value()

        return codegen

    def _load(ordering):
        """Code for ``array[index]`` as one atomic load with ``ordering``."""

        def codegen(context, builder, signature, args):
            array_type, _ = signature.args
            pointer = _element_pointer(context, builder, array_type, args[0], args[1])
            size = context.get_abi_sizeof(context.get_data_type(array_type.dtype))
            return builder.load_atomic(pointer, ordering, size)

        return codegen

    def _read_modify_write(operation, ordering):
        """Code for an atomic ``operation`` on ``array[index]`` returning the old value.

        ``min`` and ``max`` compare as the array's integers do: unsigned
        (``umin``, ``umax``) for an unsigned dtype.
        """

        def codegen(context, builder, signature, args):
            array_type, _, value_type = signature.args
            unsigned = getattr(array_type.dtype, "signed", True) is False
            op = "u" + operation if unsigned and operation in ("min", "max") else operation
            pointer = _element_pointer(context, builder, array_type, args[0], args[1])
            item = context.cast(builder, args[2], value_type, array_type.dtype)
            return builder.atomic_rmw(op, pointer, item, ordering)

        return codegen

    @intrinsic
    def store_relaxed(typingctx, array, index, value):
        """``array[index] = value`` as one atomic store, unordered (1D integer
        array; no bounds check: the caller checks the index)."""
        return types.void(array, index, value), _store("monotonic")

    @intrinsic
    def load_relaxed(typingctx, array, index):
        """``array[index]`` as one atomic load, unordered (1D integer array; no
        bounds check)."""
        return array.dtype(array, index), _load("monotonic")

    @intrinsic
    def exchange(typingctx, array, index, value):
        """Set ``array[index]`` to ``value`` atomically and return what it held
        (1D integer array; no bounds check)."""
        return array.dtype(array, index, value), _read_modify_write("xchg", "monotonic")

    @intrinsic
    def fetch_add(typingctx, array, index, value):
        """Add ``value`` to ``array[index]`` atomically and return what it held
        (``lock xadd``; 1D integer array; no bounds check)."""
        return array.dtype(array, index, value), _read_modify_write("add", "seq_cst")

    @intrinsic
    def fetch_min(typingctx, array, index, value):
        """Lower ``array[index]`` to ``value`` if above, atomically, unordered, and
        return what it held (``atomicrmw min``, or ``umin`` for an unsigned
        array: a locked compare-exchange loop on x86, so worth a relaxed load
        first; 1D integer array; no bounds check)."""
        return array.dtype(array, index, value), _read_modify_write("min", "monotonic")

    @intrinsic
    def fetch_max(typingctx, array, index, value):
        """Raise ``array[index]`` to ``value`` if below, atomically, unordered, and
        return what it held (``atomicrmw max``, or ``umax`` for an unsigned
        array; worth a relaxed load first, as ``fetch_min``; 1D integer array;
        no bounds check)."""
        return array.dtype(array, index, value), _read_modify_write("max", "monotonic")

    @intrinsic
    def store_ordered(typingctx, array, index, value):
        """``array[index] = value`` as one sequentially consistent atomic store
        (1D integer array; no bounds check)."""
        return types.void(array, index, value), _store("seq_cst")

    @intrinsic
    def load_ordered(typingctx, array, index):
        """``array[index]`` as one sequentially consistent atomic load (1D integer
        array; no bounds check)."""
        return array.dtype(array, index), _load("seq_cst")

    # The C library's "give my CPU to another runnable thread" (POSIX; Windows
    # calls it SwitchToThread). Linked by name, so a cached kernel still finds
    # it; the name is given its address here for LLVM's linker, which looks up
    # only some platforms' C library by itself.
    # Where that fails, a waiting thread only spins.
    _YIELD = "SwitchToThread" if sys.platform == "win32" else "sched_yield"
    try:
        if not llvm.address_of_symbol(_YIELD):
            _library = ctypes.WinDLL("kernel32") if sys.platform == "win32" else ctypes.CDLL(None)
            llvm.add_symbol(_YIELD, ctypes.cast(getattr(_library, _YIELD), ctypes.c_void_p).value)
        _CAN_YIELD = True
    except (OSError, AttributeError):
        _CAN_YIELD = False

    @intrinsic
    def yield_thread(typingctx):
        """Offer this thread's CPU to another runnable thread (``sched_yield``);
        returns at once when none is waiting for it."""

        def codegen(context, builder, signature, args):
            if _CAN_YIELD:
                function = _get_or_insert_function(
                    builder.module, ir.FunctionType(ir.IntType(32), []), _YIELD)
                builder.call(function, [])
            return context.get_dummy_value()

        return types.void(), codegen


@jit(inline="always")
def lower_to(array, index, value):
    """``array[index] = min(array[index], value)`` from any thread: a relaxed
    load first, the locked ``fetch_min`` only where it lowers."""
    if value < load_relaxed(array, index):
        fetch_min(array, index, value)


@jit(inline="always")
def raise_to(array, index, value):
    """``array[index] = max(array[index], value)`` from any thread: a relaxed
    load first, the locked ``fetch_max`` only where it raises."""
    if value > load_relaxed(array, index):
        fetch_max(array, index, value)
