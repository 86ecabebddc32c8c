"""What a trace returns: ``Trace`` for one ray, ``Traces`` (CSR) for a batch."""

from dataclasses import dataclass

import numpy as np

from . import _validate as validate


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

    From ``trace_many(..., device="cuda")`` the four arrays are numba-cuda
    device arrays, in the same layout: they stay on the GPU and speak the
    CUDA Array Interface (``cupy.asarray(traces.cells)``,
    ``torch.as_tensor(traces.cells, device="cuda")``). :meth:`to_host`
    copies them to numpy; ``traces[r]`` copies one ray's.
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
        lo, hi = int(self.offsets[row]), int(self.offsets[row + 1])
        return Trace(*(_host(array[lo:hi]) for array in (self.cells, self.t_enter, self.t_exit)))

    @property
    def device(self):
        """``"cuda"`` when the arrays are on a GPU, else ``"cpu"``."""
        return "cpu" if isinstance(self.cells, np.ndarray) else "cuda"

    def to_host(self):
        """Return the same traces with numpy arrays (``self`` when they already are)."""
        if self.device == "cpu":
            return self
        return Traces(*(_host(array) for array in (self.offsets, self.cells, self.t_enter,
                                                   self.t_exit)))

    def __iter__(self):
        for row in range(len(self)):
            yield self[row]

    @property
    def counts(self):
        """Number of segments of each ray, shape (m,) (a numpy array)."""
        return np.diff(_host(self.offsets))

    @property
    def ray_index(self):
        """For each segment, the ray it belongs to, shape (K,) (a numpy array)."""
        return np.repeat(np.arange(len(self)), self.counts)

    def __repr__(self):
        return f"Traces({len(self)} rays, {self.cells.shape[0]} segments)"


def _host(array):
    """``array`` as numpy: device arrays are copied back, numpy arrays pass through."""
    return array if isinstance(array, np.ndarray) else array.copy_to_host()


def _read_only(name, doc):
    """Return a read-only attribute whose value is ``self.<name>``."""
    return property(lambda self: getattr(self, name), doc=doc)


class TraceBuffers:
    """Output arrays kept between calls: ``trace_many(..., out=buffers)``.

    A robot traces every frame. With fresh arrays each call pays for their
    allocation and for the first touch of every page (on the 2-core test
    machine 11-12% of a one-thread call: ``python -m bench.run``). Buffers
    keep the arrays, and their pages, from call to call: they grow when a
    batch needs more and never shrink. On two threads or more a batch needs
    the room its ordered chunks reserve (sampled upper bounds on its
    segments, with a margin), not just its output.

    The :class:`Traces` a call returns are views into these arrays, valid
    until the next call that uses the same buffers: copy what you keep.
    One ``TraceBuffers`` per thread: two calls at once must not share one.

    Examples
    --------
    >>> buffers = TraceBuffers()
    >>> for origins, directions in frames:  # doctest: +SKIP
    ...     traces = trace_many(grid, origins, directions, out=buffers)
    """

    def __init__(self):
        self._offsets = np.empty(0, dtype=np.int64)
        self._cells = np.empty((0, 3), dtype=np.int32)
        self._t_enter = np.empty(0, dtype=np.float64)
        self._t_exit = np.empty(0, dtype=np.float64)

    # The arrays are read-only attributes: the kernels write into them up to
    # the capacity they report, so an array swapped in from outside could be
    # written out of bounds. Their contents are the caller's to read.
    offsets = _read_only("_offsets", "Ray offsets, int64; the last call's are the first rays + 1.")
    cells = _read_only("_cells", "Cells, int32, shape (capacity, 3).")
    t_enter = _read_only("_t_enter", "Entry distances, float64, shape (capacity,).")
    t_exit = _read_only("_t_exit", "Exit distances, float64, shape (capacity,).")

    @property
    def capacity(self):
        """Segments the buffers hold room for now."""
        return self._t_enter.shape[0]

    @property
    def nbytes(self):
        """Memory the buffers hold, in bytes."""
        return sum(a.nbytes for a in (self._offsets, self._cells, self._t_enter, self._t_exit))

    def ray_offsets(self, n_rays):
        """Return the offsets array for ``n_rays`` rays (a view; grown when too short)."""
        if self._offsets.shape[0] < n_rays + 1:
            self._offsets = np.empty(n_rays + 1 + n_rays // 4, dtype=np.int64)
        return self._offsets[:n_rays + 1]

    def segments(self):
        """(cells, t_enter, t_exit), or None while they hold no room."""
        if self.capacity == 0:
            return None
        return self._cells, self._t_enter, self._t_exit

    def keep(self, segments):
        """Hold ``segments`` (cells, t_enter, t_exit) from now on."""
        self._cells, self._t_enter, self._t_exit = segments

    def check(self):
        """Raise ValueError unless the kernels may write the capacity's rows of every array.

        ``trace_many`` calls it before any kernel runs. O(1): numpy lets an
        array's shape, dtype and flags be changed in place, so this reads
        them again on every call.
        """
        remedy = "use a new TraceBuffers()"
        validate.held("TraceBuffers.t_enter", self._t_enter, np.float64, (None,), remedy)
        n = self.capacity  # the rows every segment array must hold
        for name, dtype, shape in (("offsets", np.int64, (None,)), ("cells", np.int32, (n, 3)),
                                   ("t_exit", np.float64, (n,))):
            validate.held(f"TraceBuffers.{name}", getattr(self, "_" + name), dtype, shape,
                          remedy)

    def __repr__(self):
        return f"TraceBuffers({self.capacity:,} segments, {self.nbytes / 2**20:.1f} MiB)"
