"""Public tracing API: validate once in Python, then hand batches to the kernels."""

from dataclasses import dataclass

import numba
import numpy as np

from .grid import Grid
from .kernels import bisect as _bisect
from .kernels import exact as _exact
from .kernels import thibaudeau as _thibaudeau

METHODS = ("exact", "bisect", "thibaudeau")
PAPER_DEFAULT_T = 1.5531  # metres: the step the paper tuned for Algorithm 1 (section 3.2)


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


def _check_grid(grid):
    if not isinstance(grid, Grid):
        raise ValueError(f"grid must be a logsph_trace.Grid, got {type(grid).__name__}")


def _check_method(method):
    if method not in METHODS:
        raise ValueError(f"method must be one of {METHODS}, got {method!r}")


def _vectors(name, value, rows=None):
    """Coerce to a C-contiguous (m, 3) float64 array; reject NaN and inf."""
    try:
        array = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be numeric, got {value!r}") from None
    if array.ndim == 1:
        array = array[None, :]
    if array.ndim != 2 or array.shape[1] != 3:
        raise ValueError(f"{name} must have shape (m, 3) or (3,), got {np.shape(value)}")
    if rows is not None and array.shape[0] != rows:
        raise ValueError(f"{name} has {array.shape[0]} rows but origins has {rows}")
    finite = np.all(np.isfinite(array), axis=1)
    if not np.all(finite):
        row = int(np.argmin(finite))
        raise ValueError(f"{name} must be finite; row {row} is {array[row].tolist()}")
    return np.ascontiguousarray(array)


# A row's squared length must lie in this range to be summed as it is: beyond
# it a component of ~1e154 overflows (a direction of 1e200 became (0, 0, 0))
# or one of ~1e-154 underflows and loses its digits. Such rows, and only they,
# are scaled by their largest component first.
_SQUARES_LOW, _SQUARES_HIGH = 1e-300, 1e300


def _row_norms(vectors):
    """Euclidean length of each row of an (m, 3) array, without overflow or underflow.

    Ordinary rows cost one pass and are bit-identical to ``sqrt(x^2 + y^2 + z^2)``.
    """
    squares = np.einsum("ij,ij->i", vectors, vectors)
    norms = np.sqrt(squares)
    extreme = ~((squares >= _SQUARES_LOW) & (squares <= _SQUARES_HIGH))
    if np.any(extreme):
        rows = vectors[extreme]
        scale = np.max(np.abs(rows), axis=1)
        scaled = rows / np.where(scale > 0.0, scale, 1.0)[:, None]
        norms[extreme] = scale * np.sqrt(np.einsum("ij,ij->i", scaled, scaled))
    return norms


def _unit_directions(directions, name="directions"):
    """Rows scaled to unit length without overflow or underflow; zero rows are an error."""
    norms = _row_norms(directions)
    if np.any(norms == 0.0):
        row = int(np.argmin(norms))
        raise ValueError(f"{name} must be non-zero; row {row} is {directions[row].tolist()}")
    return np.ascontiguousarray(directions / norms[:, None])


def _check_origin_size(name, origins):
    """Reject origins beyond ~1.3e154, whose squared length (the kernels use it) overflows."""
    squares = np.einsum("ij,ij->i", origins, origins)
    if not np.all(np.isfinite(squares)):
        row = int(np.argmin(np.isfinite(squares)))
        raise ValueError(f"{name} must be shorter than about 1e154 (its square must be "
                         f"finite); row {row} is {origins[row].tolist()}")
    return origins


def _rays(origins, directions):
    if directions is None:
        array = np.asarray(origins, dtype=np.float64)
        if array.ndim != 2 or array.shape[1] != 6:
            raise ValueError(
                "with directions=None, origins must be one (m, 6) array of origin + direction, "
                f"got shape {np.shape(origins)}"
            )
        origins, directions = array[:, :3], array[:, 3:]
    origins = _check_origin_size("origins", _vectors("origins", origins))
    directions = _vectors("directions", directions, rows=origins.shape[0])
    return origins, _unit_directions(directions)


def _segment_arrays(length):
    """Empty (cells, t_enter, t_exit) for ``length`` segments."""
    return (
        np.empty((length, 3), dtype=np.int32),
        np.empty(length, dtype=np.float64),
        np.empty(length, dtype=np.float64),
    )


def _offsets(counts):
    """CSR offsets (m + 1,) from per-ray counts."""
    offsets = np.zeros(counts.shape[0] + 1, dtype=np.int64)
    np.cumsum(counts, out=offsets[1:])
    return offsets


def run_csr(rows, origins, directions, args):
    """Trace by a count pass, a prefix sum and a fill pass of one ``*_rows`` kernel.

    Every ray writes its own slice, so the result does not depend on the
    thread count or the order rays finish in.
    """
    no_offsets = np.empty(0, dtype=np.int64)
    counts = rows(origins, directions, *args, no_offsets, *_segment_arrays(0), False)
    offsets = _offsets(counts)
    segments = _segment_arrays(int(offsets[-1]))
    rows(origins, directions, *args, offsets, *segments, True)
    return Traces(offsets, *segments)


def _grown(array, capacity, used):
    bigger = np.empty((capacity,) + array.shape[1:], dtype=array.dtype)
    bigger[:used] = array[:used]
    return bigger


def _run_exact_serial(grid, origins, directions, t_max, args):
    """One appending pass.

    The arrays are numpy's, allocated here rather than in the kernel: numpy asks
    the OS for huge pages, which makes first touch of a large output several ns
    per segment cheaper. They start small (a small batch must not pay for
    zeroing a 2 MB page it barely uses); when the kernel runs out of room it
    stops before the next ray, and they grow to the batch's expected size,
    extrapolated from the rays so far with a fifth to spare.
    """
    n_rays = origins.shape[0]
    worst = int(_exact.max_segments(*grid.shape))
    size = int(_exact.scratch_size(*grid.shape))
    times = np.empty((3, size), dtype=np.float64)
    zones = np.empty((3, size), dtype=np.int64)
    lookups = np.empty(8, dtype=np.int64)
    offsets = np.empty(n_rays + 1, dtype=np.int64)
    offsets[0] = 0
    capacity = 2 * worst + 32 * min(n_rays, _exact.BLOCK)
    cells, t_enter, t_exit = _segment_arrays(capacity)
    used = 0
    row = 0
    while row < n_rays:
        used, row = _exact.trace_span(row, n_rays, origins, directions, t_max, *args, times, zones,
                                      lookups, cells, t_enter, t_exit, offsets, used, capacity)
        used, row = int(used), int(row)
        if row < n_rays:
            expected = int(1.2 * used / max(row, 1) * n_rays)
            capacity = max(capacity + capacity // 2, expected) + 2 * worst
            cells, t_enter, t_exit = (_grown(a, capacity, used) for a in (cells, t_enter, t_exit))
    return Traces(offsets, cells[:used], t_enter[:used], t_exit[:used])


# Below this many rays a batch is traced on one thread even with parallel=True.
PARALLEL_MIN_RAYS = 512


def _run_exact(grid, origins, directions, t_max, parallel):
    """Trace with the exact method, serially or on all threads.

    Serial: one appending pass. Parallel: one appending chunk per thread, then
    packing; or, if a chunk outgrows its estimated room, a bound pass (set-up
    only, no stepping), a trace pass into bounded slices and a gather.
    Every path runs the same per-ray code, so the outputs are identical.
    """
    args = grid.kernel_args()
    if not parallel:
        return _run_exact_serial(grid, origins, directions, t_max, args)
    threads = numba.get_num_threads()
    if threads == 1 or origins.shape[0] < PARALLEL_MIN_RAYS:
        return _run_exact_serial(grid, origins, directions, t_max, args)  # too few to split
    chunked = _run_exact_chunks(grid, origins, directions, t_max, args, threads)
    if chunked is not None:
        return chunked
    return _run_exact_bounded(grid, origins, directions, t_max, args)


def _run_exact_chunks(grid, origins, directions, t_max, args, threads):
    """Trace in parallel into fresh arrays, then pack the regions left in place.

    Uses :func:`trace_regions`; returns None if a chunk did not fit.
    """
    traced = trace_regions(grid, origins, directions, t_max, args, threads, _segment_arrays)
    if traced is None:
        return None
    starts, regions, ends, offsets, cells, t_enter, t_exit = traced
    total = int(_exact.pack_chunks(starts, regions, ends, offsets, cells, t_enter, t_exit))
    return Traces(offsets, cells[:total], t_enter[:total], t_exit[:total])


def trace_regions(grid, origins, directions, t_max, args, chunks, segment_arrays):
    """Trace ``chunks`` contiguous chunks of rays, each into its own region.

    Each chunk is one ``prange`` iteration and appends to its region.

    Regions are sized from a sample of the rays with a half to spare (all
    rays' worst case when there are too few to sample); ``segment_arrays(n)``
    provides (cells, t_enter, t_exit) with room for at least ``n`` segments.
    Returns ``(starts, regions, ends, offsets, cells, t_enter, t_exit)``:
    chunk ``c`` holds rays ``starts[c]:starts[c + 1]``, written from
    ``regions[c]`` to ``ends[c]``, and ray ``r``'s segments are
    ``offsets[r]:offsets[r + 1]`` (gaps between regions). None if a chunk did
    not fit.
    """
    n_rays = origins.shape[0]
    worst = int(_exact.max_segments(*grid.shape))
    sampled = min(_exact.BLOCK, max(32, n_rays // 16))  # traced twice: keep it small
    starts = np.linspace(0, n_rays, chunks + 1).astype(np.int64)
    if n_rays <= sampled:
        room = np.diff(starts) * worst
    else:
        sample = _run_exact_serial(grid, origins[:sampled], directions[:sampled],
                                   t_max[:sampled], args)
        per_ray = sample.cells.shape[0] / sampled
        room = (1.5 * per_ray * np.diff(starts)).astype(np.int64) + 4 * worst
    regions = np.zeros(chunks + 1, dtype=np.int64)
    np.cumsum(room, out=regions[1:])
    cells, t_enter, t_exit = segment_arrays(int(regions[-1]))
    offsets = np.empty(n_rays + 1, dtype=np.int64)
    offsets[0] = 0
    ends, reached = _exact.trace_chunks(starts, regions, origins, directions, t_max, *args,
                                        cells, t_enter, t_exit, offsets)
    if np.any(reached != starts[1:]):
        return None
    return starts, regions, ends, offsets, cells, t_enter, t_exit


def _run_exact_bounded(grid, origins, directions, t_max, args):
    """Parallel fallback: bound pass, prefix sum, trace pass, gather (no estimate needed)."""
    bounds, lookups = _exact.bound_rows(origins, directions, *args)
    bound_offsets = _offsets(bounds)
    loose = _segment_arrays(int(bound_offsets[-1]))
    offsets = _offsets(
        _exact.trace_rows(origins, directions, t_max, *args, lookups, bound_offsets, *loose)
    )
    segments = _segment_arrays(int(offsets[-1]))
    _exact.gather_rows(bound_offsets, offsets, *loose, *segments)
    return Traces(offsets, *segments)


def _distances(t_max, n_rays):
    """``t_max`` as a contiguous (m,) float64 array; ``None`` is no limit."""
    if t_max is None:
        return np.full(n_rays, np.inf)
    try:
        array = np.asarray(t_max, dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError(f"t_max must be a number or an array of numbers, got {t_max!r}") from None
    if array.ndim == 0:
        array = np.full(n_rays, float(array))
    if array.shape != (n_rays,):
        raise ValueError(f"t_max must be a number or have shape ({n_rays},), got {array.shape}")
    if np.any(np.isnan(array)) or np.any(array < 0):
        bad = int(np.argmax(np.isnan(array) | (array < 0)))
        raise ValueError(f"t_max must be >= 0 (inf allowed); row {bad} is {float(array[bad])!r}")
    return np.ascontiguousarray(array)


def _bisect_options(grid, default_t, max_iter):
    try:
        default_t = float(default_t)
    except (TypeError, ValueError):
        raise ValueError(f"default_t must be a positive number, got {default_t!r}") from None
    if not (np.isfinite(default_t) and default_t > 0):
        raise ValueError(f"default_t must be a positive finite number, got {default_t!r}")
    if max_iter is None:
        n_rho, n_theta, n_phi = grid.shape
        max_iter = 64 * (2 * n_rho + n_theta + 2 * n_phi + 4)
    if isinstance(max_iter, bool) or not isinstance(max_iter, (int, np.integer)) or max_iter < 1:
        raise ValueError(f"max_iter must be a positive integer, got {max_iter!r}")
    return default_t, int(max_iter)


def trace_many(grid, origins, directions=None, method="exact", parallel=True,
               default_t=PAPER_DEFAULT_T, max_iter=None, t_max=None):
    """Trace many rays through ``grid``.

    Parameters
    ----------
    grid : Grid
    origins : array_like, shape (m, 3), or (m, 6) with ``directions=None``
        Ray origins; or one array of origin + direction per row (as Open3D does).
    directions : array_like, shape (m, 3), optional
        Ray directions, any non-zero length; they are normalised, so every
        ``t`` returned is a distance from the origin.
    method : {"exact", "bisect", "thibaudeau"}
        ``"exact"`` (default): boundary stepping -- every cell, exact entry and
        exit distances. ``"bisect"``: the paper's Algorithm 1, a baseline that
        may skip cells and stops at the first exit; its distances are sample
        positions, not boundaries. ``"thibaudeau"``: all crossings with all
        boundaries, sorted and classified -- exact but O(n log n).
    parallel : bool
        Trace rays on all Numba threads (``prange``). The output is identical
        to the serial run. For ``"exact"`` every ray is traced once: serially
        by appending; in parallel as one chunk of rays per thread, each
        appending to its own region, the regions then packed (if a chunk
        outgrows its estimated room: a bound pass, a trace pass into bounded
        slices and a gather). The returned arrays may be views of arrays up to
        about 1.5 times longer. The baselines use a count pass and a fill pass.
    default_t : float
        ``"bisect"`` only: the first step of every search, in length units
        (paper: 1.5531 m).
    max_iter : int, optional
        ``"bisect"`` only: samples allowed per ray, so a ray grazing a boundary
        cannot loop forever. Default ``64 * (2 n_rho + n_theta + 2 n_phi + 4)``.
    t_max : float or array_like, shape (m,), optional
        ``"exact"`` only: trace each ray up to this distance (e.g. a sensor
        ray up to its hit point); the last segment ends there. Default: to the
        end of the region.

    Returns
    -------
    Traces
        CSR segments: ``traces[r]`` is the :class:`Trace` of ray ``r``.

    Raises
    ------
    ValueError
        Wrong shapes, NaN or infinite values, zero directions, unknown method,
        bad ``default_t``, ``max_iter`` or ``t_max``, or ``grid`` not a
        :class:`Grid` -- before any kernel runs.
    """
    _check_grid(grid)
    _check_method(method)
    if method == "bisect":
        default_t, max_iter = _bisect_options(grid, default_t, max_iter)
    if t_max is not None and method != "exact":
        raise ValueError(f"t_max is supported by method='exact' only, got method={method!r}")
    origins, directions = _rays(origins, directions)
    parallel = bool(parallel)
    if method == "exact":
        return _run_exact(grid, origins, directions, _distances(t_max, origins.shape[0]), parallel)
    kinds = (grid.rho_edges, grid.rho_kind, grid.theta_edges, grid.theta_kind)
    if method == "bisect":
        args = kinds + (grid.theta_full, grid.phi_edges, grid.phi_kind, default_t, max_iter)
        rows = _bisect.bisect_rows
    else:
        args = kinds + (grid.phi_edges, grid.phi_kind)
        rows = _thibaudeau.thibaudeau_rows
    return run_csr(rows.pick(parallel), origins, directions, args)


def trace(grid, origin, direction, method="exact", default_t=PAPER_DEFAULT_T, max_iter=None,
          t_max=None):
    """Trace one ray; see :func:`trace_many`.

    Parameters
    ----------
    grid : Grid
    origin, direction : array_like, shape (3,)
    method : {"exact", "bisect", "thibaudeau"}
    default_t, max_iter :
        ``"bisect"`` only, see :func:`trace_many`.
    t_max : float, optional
        ``"exact"`` only: trace up to this distance.

    Returns
    -------
    Trace
    """
    for name, value in (("origin", origin), ("direction", direction)):
        if np.shape(value) != (3,):
            raise ValueError(f"{name} must have shape (3,), got {np.shape(value)}")
    return trace_many(grid, origin, direction, method=method, parallel=False,
                      default_t=default_t, max_iter=max_iter, t_max=t_max)[0]
