"""What a trace returns: ``Trace`` for one ray, ``Traces`` (CSR) for a batch."""

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Trace:
    """The voxels one ray crosses, in order.

    Attributes
    ----------
    cells : numpy.ndarray, int32, shape (n, 3)
        ``(i, j, k)`` = (rho, theta, phi) cell indices, in the order the ray meets them.
    t_enter, t_exit : numpy.ndarray, float64, shape (n,)
        Distance along the ray (normalised direction, so in length units) at which
        it enters and leaves each cell. Consecutive segments either touch
        (``t_exit[s] == t_enter[s+1]``) and differ in their cell, or are separated
        by a stretch outside the region (the egocentric gap, or outside a partial
        angular range).
    """

    cells: np.ndarray
    t_enter: np.ndarray
    t_exit: np.ndarray

    def __len__(self):
        return self.cells.shape[0]

    @property
    def lengths(self):
        """Length of the ray inside each cell, ``t_exit - t_enter``."""
        return self.t_exit - self.t_enter

    def unique(self):
        """Return each cell once, in order of first entry (the set the paper returns).

        Returns
        -------
        numpy.ndarray, int32, shape (u, 3)
        """
        if len(self) == 0:
            return self.cells.copy()
        _, first = np.unique(self.cells, axis=0, return_index=True)
        return self.cells[np.sort(first)]

    def __repr__(self):
        return f"Trace({len(self)} segments)"


@dataclass(frozen=True)
class Traces:
    """Many traces in compressed-row (CSR) form.

    Attributes
    ----------
    offsets : numpy.ndarray, int64, shape (m + 1,)
        Ray ``r`` owns segments ``offsets[r]:offsets[r+1]``.
    cells : numpy.ndarray, int32, shape (K, 3)
    t_enter, t_exit : numpy.ndarray, float64, shape (K,)
    """

    offsets: np.ndarray
    cells: np.ndarray
    t_enter: np.ndarray
    t_exit: np.ndarray

    def __len__(self):
        return self.offsets.shape[0] - 1

    def __getitem__(self, row):
        n_rays = len(self)
        if not isinstance(row, (int, np.integer)):
            raise TypeError(f"Traces index must be an integer, got {type(row).__name__}")
        if row < 0:
            row += n_rays
        if not 0 <= row < n_rays:
            raise IndexError(f"ray {row} out of range for {n_rays} traces")
        lo, hi = self.offsets[row], self.offsets[row + 1]
        return Trace(self.cells[lo:hi], self.t_enter[lo:hi], self.t_exit[lo:hi])

    def __iter__(self):
        for row in range(len(self)):
            yield self[row]

    @property
    def counts(self):
        """Number of segments of each ray, shape (m,)."""
        return np.diff(self.offsets)

    @property
    def ray_index(self):
        """For each segment, the ray it belongs to, shape (K,)."""
        return np.repeat(np.arange(len(self)), self.counts)

    def __repr__(self):
        return f"Traces({len(self)} rays, {self.cells.shape[0]} segments)"
