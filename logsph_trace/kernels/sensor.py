"""Depth-camera kernels (``@jit`` only): pixels to points in the map's frame."""

import numpy as np
from numba import prange

from .._jit import jit
from .locate import BLOCK


@jit(parallel=True)
def back_project(depth, pixels, columns, scale, fx, fy, cx, cy, skew, rotation, translation,
                 out, rows_columns):
    """Point of each valid pixel: ``out[n] = R @ p + t`` for flat pixel ``pixels[n]``,
    and that pixel's (row, column) in ``rows_columns[n]``.

    ``depth`` is the image, flat and row-major, ``columns`` wide; pixel
    (row v, column u) at depth Z is ``p = (x Z, y Z, Z)`` in OpenCV's camera
    frame, with ``y = (v - cy) / fy`` and ``x = (u - cx - skew y) / fx``.
    """
    n = pixels.shape[0]
    for block in prange((n + BLOCK - 1) // BLOCK):
        for row in range(block * BLOCK, min(n, (block + 1) * BLOCK)):
            flat = pixels[row]
            v = flat // columns
            u = flat - v * columns
            rows_columns[row, 0] = v
            rows_columns[row, 1] = u
            z = np.float64(depth[flat]) * scale
            y_n = (v - cy) / fy
            x_n = (u - cx - skew * y_n) / fx
            x = x_n * z
            y = y_n * z
            for axis in range(3):
                out[row, axis] = (rotation[axis, 0] * x + rotation[axis, 1] * y
                                  + rotation[axis, 2] * z + translation[axis])
