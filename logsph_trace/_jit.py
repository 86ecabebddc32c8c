"""One place for the Numba options every kernel shares, and the one way to apply them.

Every kernel is decorated where it is defined: ``@jit`` for serial code (with
``inline="always"`` for the small per-ray helpers), ``@jit(parallel=True)``
for a ``prange`` kernel that only runs in parallel, and ``@jit_twins`` for a
``prange`` kernel that also runs on one thread.

``cache=True`` keeps the first call after install cheap: each kernel compiles
once and is loaded from ``__pycache__`` afterwards. ``LOGSPH_TRACE_CACHE=0``
in the environment turns the cache off (a read-only install, or a kernel
being edited: Numba re-validates a cached kernel against its own file only,
so a change in a function it calls from another file goes unseen until the
cache is cleared). ``error_model="numpy"`` makes a float division by zero
return ``inf``/``nan`` as IEEE says instead of raising, which the root solvers
rely on (a ray parallel to a plane has its crossing at infinity).
``fastmath`` stays off: it may reorder the tie rules and NaN checks the
exactness tests hold us to.
"""

import os
import types
from typing import NamedTuple

import numba

CACHE = os.environ.get("LOGSPH_TRACE_CACHE", "1").strip() != "0"
_OPTIONS = dict(cache=CACHE, nogil=True, error_model="numpy")


def jit(func=None, **overrides):
    """``numba.njit`` with the project's options (``parallel=True`` may be added)."""
    options = dict(_OPTIONS, **overrides)
    if func is None:
        return lambda f: numba.njit(**options)(f)
    return numba.njit(**options)(func)


class Twins(NamedTuple):
    """The serial and the parallel build of one ``prange`` kernel."""

    serial: object
    parallel: object

    def pick(self, parallel):
        """Return the build for ``parallel`` (True: all threads; False: this thread)."""
        return self.parallel if parallel else self.serial


def jit_twins(func):
    """Compile one ``prange`` source twice, serially and with ``parallel=True``.

    Numba's on-disk cache names its files after the function's qualified name,
    so the two builds of one function would overwrite each other's cache and a
    later process could load the serial code for the parallel entry point. The
    parallel build therefore gets its own copy of the function, named
    ``<name>_parallel``.
    """
    twin = types.FunctionType(
        func.__code__, func.__globals__, func.__name__ + "_parallel",
        func.__defaults__, func.__closure__,
    )
    twin.__qualname__ = func.__qualname__ + "_parallel"
    twin.__doc__ = func.__doc__
    return Twins(jit(func), jit(twin, parallel=True))
