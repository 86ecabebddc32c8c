"""One place for the Numba options every kernel shares.

``cache=True`` keeps the first call after install cheap: each kernel compiles
once and is loaded from ``__pycache__`` afterwards.  ``error_model="numpy"``
makes a float division by zero return ``inf``/``nan`` as IEEE says instead of
raising, which the root solvers rely on (a ray parallel to a plane has its
crossing at infinity).  ``fastmath`` stays off: it may reorder the tie rules
and NaN checks the exactness tests hold us to.
"""

import types

import numba

_OPTIONS = dict(cache=True, nogil=True, error_model="numpy")


def jit(func=None, **overrides):
    """``numba.njit`` with the project's options (``parallel=True`` may be added)."""
    options = dict(_OPTIONS, **overrides)
    if func is None:
        return lambda f: numba.njit(**options)(f)
    return numba.njit(**options)(func)


def jit_serial_and_parallel(func):
    """Compile one ``prange`` source twice: serially, and with ``parallel=True``.

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
    return jit(func), jit(twin, parallel=True)
