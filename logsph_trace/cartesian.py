"""A Cartesian voxel box traced by Amanatides & Woo: the baseline every timing is a ratio to."""

import time

import numpy as np

from . import _validate as validate
from ._batching import BatchKernels, lap, run_batch
from .kernels.baselines import amanatides_woo as _kernels
from .traces import Traces

BOX_KERNELS = BatchKernels(_kernels.box_span, _kernels.box_ordered,
                           _kernels.box_bounds)


class CartesianGrid:
    """An axis-aligned box of ``shape`` equal voxels from ``low`` to ``high``.

    Parameters
    ----------
    low, high : sequence of 3 floats
        Opposite corners of the box, ``low < high`` on every axis.
    shape : sequence of 3 ints
        Voxel counts along x, y, z.
    """

    def __init__(self, low, high, shape):
        low = np.array([validate.finite(f"low[{axis}]", v) for axis, v in enumerate(low)])
        high = np.array([validate.finite(f"high[{axis}]", v) for axis, v in enumerate(high)])
        shape = np.array([validate.count(f"shape[{axis}]", n) for axis, n in enumerate(shape)])
        if low.shape != (3,) or high.shape != (3,) or shape.shape != (3,):
            raise ValueError("low, high and shape must each have 3 entries")
        if np.any(low >= high):
            raise ValueError(f"low must be < high on every axis, got low={low}, high={high}")
        self.low = low
        self.high = high
        self.shape = tuple(int(n) for n in shape)
        self._shape = shape.astype(np.int64)
        self.voxel_size = (high - low) / shape

    def __repr__(self):
        return (f"CartesianGrid(low={self.low.tolist()}, high={self.high.tolist()}, "
                f"shape={self.shape})")

    def trace_many(self, origins, directions=None, parallel=True):
        """Voxels each ray crosses, as :class:`~logsph_trace.Traces` (the CSR of trace_many)."""
        start = time.perf_counter()
        origins, directions = validate.rays(origins, directions)
        lap("check", start)
        inputs = (origins, directions, self.low, self.voxel_size, self._shape)
        worst = int(self._shape.sum())
        return run_batch(BOX_KERNELS, inputs, inputs, inputs, origins.shape[0], worst, parallel)


__all__ = ["CartesianGrid", "Traces"]
