"""Numba kernels. Everything here is ``@jit``-compiled and takes plain arrays and scalars."""
