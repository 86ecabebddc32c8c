"""The memory strategy for batches: how traced segments reach their arrays.

A trace's length is unknown before it is traced, so every batch path decides
where each ray's segments go without a second pass where it can:

* **One thread** (``run_exact_serial``): rays are traced in order, each
  appending to numpy arrays (numpy, not Numba, allocates them: it asks the OS
  for huge pages, which makes first touch cheaper). They start small and grow
  to the batch's expected size when the kernel runs out of room.
* **Many threads** (``run_exact_chunks`` via ``trace_regions``): one
  contiguous chunk of rays per thread, each appending into its own region of
  the arrays, sized from a sample of the batch; the regions are then packed
  left in place (``exact.pack_chunks``).
* **Fallback** (``run_exact_bounded``): if a chunk outgrows its region, a
  bound pass (each ray's set-up only, no stepping) gives every ray an upper
  bound, rays are traced into bounded slices, and a gather packs them.
* **Baselines** (``run_csr``): a count pass, a prefix sum and a fill pass of
  one ``*_rows`` kernel.
* **Cones** reuse per-Python-thread scratch arrays (``scratch_segments``):
  their segments are read once, by the aggregation.

Every path runs the same per-ray code and each ray writes only its own slice
or region, so the output does not depend on the number of threads.
"""

import threading

import numba
import numpy as np

from .kernels import exact as _exact
from .traces import Traces


def segment_arrays(length):
    """Empty (cells, t_enter, t_exit) for ``length`` segments."""
    return (
        np.empty((length, 3), dtype=np.int32),
        np.empty(length, dtype=np.float64),
        np.empty(length, dtype=np.float64),
    )


def csr_offsets(counts):
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
    counts = rows(origins, directions, *args, no_offsets, *segment_arrays(0), False)
    offsets = csr_offsets(counts)
    segments = segment_arrays(int(offsets[-1]))
    rows(origins, directions, *args, offsets, *segments, True)
    return Traces(offsets, *segments)


def grown(array, capacity, used):
    bigger = np.empty((capacity,) + array.shape[1:], dtype=array.dtype)
    bigger[:used] = array[:used]
    return bigger


def run_exact_serial(grid, origins, directions, t_max, args):
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
    cells, t_enter, t_exit = segment_arrays(capacity)
    used = 0
    row = 0
    while row < n_rays:
        used, row = _exact.trace_span(row, n_rays, origins, directions, t_max, args, times, zones,
                                      lookups, cells, t_enter, t_exit, offsets, used, capacity)
        used, row = int(used), int(row)
        if row < n_rays:
            expected = int(1.2 * used / max(row, 1) * n_rays)
            capacity = max(capacity + capacity // 2, expected) + 2 * worst
            cells, t_enter, t_exit = (grown(a, capacity, used) for a in (cells, t_enter, t_exit))
    return Traces(offsets, cells[:used], t_enter[:used], t_exit[:used])


# Below this many rays a batch is traced on one thread even with parallel=True.
PARALLEL_MIN_RAYS = 512


def run_exact(grid, origins, directions, t_max, parallel):
    """Trace with the exact method, serially or on all threads.

    Serial: one appending pass. Parallel: one appending chunk per thread, then
    packing; or, if a chunk outgrows its estimated room, a bound pass (set-up
    only, no stepping), a trace pass into bounded slices and a gather.
    Every path runs the same per-ray code, so the outputs are identical.
    """
    args = grid.kernel_args()
    if not parallel:
        return run_exact_serial(grid, origins, directions, t_max, args)
    threads = numba.get_num_threads()
    if threads == 1 or origins.shape[0] < PARALLEL_MIN_RAYS:
        return run_exact_serial(grid, origins, directions, t_max, args)  # too few to split
    chunked = run_exact_chunks(grid, origins, directions, t_max, args, threads)
    if chunked is not None:
        return chunked
    return run_exact_bounded(grid, origins, directions, t_max, args)


def run_exact_chunks(grid, origins, directions, t_max, args, threads):
    """Trace in parallel into fresh arrays, then pack the regions left in place.

    Uses :func:`trace_regions`; returns None if a chunk did not fit.
    """
    traced = trace_regions(grid, origins, directions, t_max, args, threads, segment_arrays)
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
        sample = run_exact_serial(grid, origins[:sampled], directions[:sampled],
                                   t_max[:sampled], args)
        per_ray = sample.cells.shape[0] / sampled
        room = (1.5 * per_ray * np.diff(starts)).astype(np.int64) + 4 * worst
    regions = np.zeros(chunks + 1, dtype=np.int64)
    np.cumsum(room, out=regions[1:])
    cells, t_enter, t_exit = segment_arrays(int(regions[-1]))
    offsets = np.empty(n_rays + 1, dtype=np.int64)
    offsets[0] = 0
    ends, reached = _exact.trace_chunks(starts, regions, origins, directions, t_max, args,
                                        cells, t_enter, t_exit, offsets)
    if np.any(reached != starts[1:]):
        return None
    return starts, regions, ends, offsets, cells, t_enter, t_exit


def run_exact_bounded(grid, origins, directions, t_max, args):
    """Parallel fallback: bound pass, prefix sum, trace pass, gather (no estimate needed)."""
    bounds, lookups = _exact.bound_rows(origins, directions, args)
    bound_offsets = csr_offsets(bounds)
    loose = segment_arrays(int(bound_offsets[-1]))
    offsets = csr_offsets(
        _exact.trace_rows(origins, directions, t_max, args, lookups, bound_offsets, *loose)
    )
    segments = segment_arrays(int(offsets[-1]))
    _exact.gather_rows(bound_offsets, offsets, *loose, *segments)
    return Traces(offsets, *segments)


_scratch = threading.local()


def scratch_segments(length):
    """Segment arrays reused by this Python thread's cone traces, grown as needed.

    A cone's segments are read once, by the aggregation; faulting in fresh
    pages for them each call took longer than tracing into them (1.0 of 2.0
    ms for a 1,000-ray cone, measured). Per Python thread, so concurrent
    calls never share them.
    """
    held = getattr(_scratch, "segments", None)
    if held is None or held[0].shape[0] < length:
        held = segment_arrays(length + length // 4)
        _scratch.segments = held
    return held
