"""One place for the Numba options every kernel shares.

``cache=True`` keeps the first call after install cheap: each kernel compiles
once and is loaded from ``__pycache__`` afterwards.  ``error_model="numpy"``
makes a float division by zero return ``inf``/``nan`` as IEEE says instead of
raising, which the root solvers rely on (a ray parallel to a plane has its
crossing at infinity).  ``fastmath`` stays off: it may reorder the tie rules
and NaN checks the exactness tests hold us to.
"""

import numba

_OPTIONS = dict(cache=True, nogil=True, error_model="numpy")


def jit(func=None, **overrides):
    """``numba.njit`` with the project's options (``parallel=True`` may be added)."""
    options = dict(_OPTIONS, **overrides)
    if func is None:
        return lambda f: numba.njit(**options)(f)
    return numba.njit(**options)(func)
