"""The memory strategy for batches: how traced segments reach their arrays.

A trace's length is unknown before it is traced. Every path keeps a batch's
peak resident memory close to its output: the output arrays, plus a scratch
of bounded size.

* **One thread** (``run_serial``): rays are traced in order, each
  appending to numpy arrays (numpy, not Numba, allocates them: it asks the OS
  for huge pages, which makes first touch cheaper). They start small (a small
  batch must not pay for a 2 MB page it barely uses) and grow once to the
  batch's expected size (a copy of the few rays' segments traced so far);
  at the end they shrink in place to the exact size (``resized``), so the
  result holds no spare room.
* **Two threads or more** (``run_ordered``): the rays are cut into small chunks,
  taken in order by the threads from a shared counter. A thread traces its
  chunk into one of its two scratch buffers (small enough to stay in the
  cache), posts the chunk's count, and copies the chunk it traced before to
  its place (``kernels.ordered``: a chunk starts where the one before it
  ends, and whoever posts the last count a start depends on publishes it).
  Every segment is written to the output once, bypassing the cache, by the
  thread that traced it; nothing runs on one thread but the sample of
  bounds, and no thread waits for the others to end a round. The output is
  reserved from a sample of upper bounds on the rays' segments, with a
  margin, and shrinks in place to the exact size at the end; its fresh pages are
  faulted in by the same threads between chunks, a block by one thread, a
  little ahead of the chunks. Should it be too small (a sample off by
  more than the margin), the rows placed so far stay, the output grows,
  and the rest is traced again.
* The exact method and the Amanatides-Woo baseline run on both
  (their ``BatchKernels``), so their timings compare like for like. The
  paper's baselines (``run_csr``) take a count pass, a prefix sum and a
  fill pass of one ``*_rows`` kernel.
* **Cones** (``trace_regions``): one region per chunk, sized by a bound pass
  (``bound_counts``: each ray's set-up, no stepping), so none can
  overflow; their segments are read once, by the aggregation.

The ordered path's and the cones' scratch arrays are per Python thread and
reused between calls (``scratch_segments``), unless one call needed more
than ``KEEP_SCRATCH_SEGMENTS``.

Every path runs the same per-ray code and each ray writes only its own slice
or region, so the output does not depend on the number of threads.
"""

import contextlib
import threading
import time
from typing import NamedTuple

import numba
import numpy as np

from . import _validate as validate
from .kernels import atomic as _atomic
from .kernels import exact as _exact
from .kernels import geometry as _geometry
from .kernels import ordered as _ordered
from .kernels.locate import BLOCK
from .traces import TraceBuffers, Traces

SEGMENT_BYTES = 12 + 8 + 8  # a cell (3 x int32), t_enter, t_exit


_phases = threading.local()


@contextlib.contextmanager
def phase_times():
    """Yield a dict of the seconds each batch phase took in this block (a benchmark hook).

    The batch phases are "check" (the input checks of ``trace_many``, on
    all threads from ``_validate.PARALLEL_CHECK_ROWS`` rays), "bound" (the
    ordered chunks' sampled bounds), "allocate", "trace", "shrink" and "other"
    (Python between the kernels); a cone's are "bound", "trace" and
    "aggregate", an integration's "prepare", "mark" and "apply". Only this
    thread's calls are counted.
    """
    times = {}
    _phases.times = times
    try:
        yield times
    finally:
        _phases.times = None


def lap(phase, since):
    """Add the time since ``since`` to ``phase`` (when ``phase_times`` is on); return now."""
    now = time.perf_counter()
    times = getattr(_phases, "times", None)
    if times is not None:
        times[phase] = times.get(phase, 0.0) + now - since
    return now


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


def resized(array, length):
    """``array`` with room for ``length`` rows: in place where the allocator can.

    numpy's ``resize`` reallocates, which for a large array remaps its pages
    instead of copying them, so neither growing nor shrinking holds two
    copies at once. Growing this way zero-fills the new rows on one thread
    and without huge pages (4x the first-touch time of ``np.empty``,
    measured), so it is for shrinking and for rare growth. Only for arrays
    this module allocated and never shared.
    """
    array.resize((length,) + array.shape[1:], refcheck=False)
    return array


def grown(array, capacity, used):
    """Return a fresh (huge-page) array of ``capacity`` rows holding ``array[:used]``."""
    bigger = np.empty((capacity,) + array.shape[1:], dtype=array.dtype)
    bigger[:used] = array[:used]
    return bigger


def _ray_offsets(n_rays, buffers):
    """Return CSR offsets (n_rays + 1,) with offsets[0] = 0, from ``buffers`` when given."""
    offsets = np.empty(n_rays + 1, dtype=np.int64) if buffers is None else \
        buffers.ray_offsets(n_rays)
    offsets[0] = 0
    return offsets


def _result(offsets, segments, used, buffers, start):
    """Return the ``Traces`` of the first ``used`` segments.

    With ``buffers``: views, the arrays kept there for the next call.
    Without: the arrays shrunk in place, so they own exactly their data.
    """
    if buffers is not None:
        buffers.keep(segments)
        return Traces(offsets, *(a[:used] for a in segments))
    traces = Traces(offsets, *(resized(a, used) for a in segments))
    lap("shrink", start)
    return traces


def run_serial(span, inputs, n_rays, worst, buffers=None):
    """One appending pass (see the module docstring) of a ``*_span`` kernel.

    ``span(first, last, *inputs, cells, t_enter, t_exit, offsets, used, limit)``
    traces rays in order, appending from ``used``, and stops before a ray
    that might not fit below ``limit`` (``worst`` segments per ray).
    ``buffers``: a ``TraceBuffers`` to write into (the result is views of it).
    """
    start = time.perf_counter()
    offsets = _ray_offsets(n_rays, buffers)
    capacity = 2 * worst + 32 * min(n_rays, BLOCK)
    held = None if buffers is None else buffers.segments()
    if held is not None and held[0].shape[0] >= capacity:
        cells, t_enter, t_exit = held
        capacity = cells.shape[0]
    else:
        cells, t_enter, t_exit = segment_arrays(capacity)
    used = 0
    row = 0
    while row < n_rays:
        start = lap("allocate", start)
        used, row = span(row, n_rays, *inputs, cells, t_enter, t_exit, offsets, used, capacity)
        used, row = int(used), int(row)
        start = lap("trace", start)
        if row < n_rays:
            expected = int(1.2 * used / max(row, 1) * n_rays)
            validate.fits("origins", (capacity + expected) * SEGMENT_BYTES,
                          f"tracing {n_rays:,} rays (about {expected:,} segments)")
            capacity = max(capacity + capacity // 2, expected) + 2 * worst
            cells, t_enter, t_exit = (grown(a, capacity, used) for a in (cells, t_enter, t_exit))
    return _result(offsets, (cells, t_enter, t_exit), used, buffers, start)


# Below this many rays a batch is traced on one thread even with parallel=True:
# waking the threads for the sampled bounds and the chunks costs about what a
# second thread saves (bench.run's grid, 2 threads, best of 200 calls: 1,000
# rays 1.88 ms against 1.78 serial; 2,000 3.30-3.36 against 3.30; 3,000
# 4.62-4.68 against 4.71; 4,000 5.38-5.98 against 6.25-6.33).
PARALLEL_MIN_RAYS = 2048
# A chunk of the ordered path has as many rays as fit in this many segments
# (28 bytes each) at ``max_segments`` per ray, so it always fits its scratch
# buffer. Its rays write about a tenth of that on bench.run's grid (202 rays,
# 340 KB), and only those pages of the buffer are ever touched. On 2 threads,
# 100,000 rays, best of 7, two runs (ms), 1 << 15 to 1 << 19: 73.3-74.5 into
# fresh arrays, 63.9-64.3 into reused ones.
ORDERED_SEGMENTS = 1 << 17
# Fresh output is faulted in by the workers between chunks, in blocks of
# ``ordered.TOUCH_ROWS`` claimed in order, a block by one thread, ahead of the
# chunks (``ordered.touch_ahead``). Faulted in by the chunks' own copies
# instead, chunks of 1 << 15 to 1 << 17 segments took 74.5-76.2 ms against
# 71.4-71.8 for 1 << 19 (same runs as above, otherwise): threads placing
# neighbouring chunks fault the same huge page at once, each clearing a page
# of its own. Without huge pages every size took 126.7-128.4 ms.


class BatchKernels(NamedTuple):
    """One method's kernels for the batch paths (``exact.trace_*``, ``cartesian.box_*``).

    ``span``: one thread, appending (``run_serial``); ``ordered``: chunks
    placed in order (``run_ordered``). ``bounds(*bound_inputs, out)`` writes
    an upper bound on each ray's segments (the ordered chunks reserve their
    output from a sample of them).
    """

    span: object
    ordered: object
    bounds: object


def run_batch(kernels, span_inputs, inputs, bound_inputs, n_rays, worst, parallel, buffers=None):
    """Trace in one pass (``run_serial``) or in ordered chunks on all threads (``run_ordered``).

    Both run the same per-ray code, so the outputs are identical. A batch
    too small to split, one thread, or a Numba without the chunks' atomics
    (``kernels.atomic.AVAILABLE``) takes the serial pass.

    The ordered chunks pay for their machinery: against a plain design (a
    bound pass, offsets, each chunk traced into its region of a reused
    scratch, then one copy that closes the gaps), ``python -m
    bench.batch_designs`` on 2 threads took 55.1 ms against 63.3 (1.15x,
    ``bench/results/batch_designs.md``). Two threads once had a path of
    their own, meeting in the middle of the batch; the ordered chunks were
    as fast in one run (best of 12: 53.9 ms against 55.0 into fresh arrays,
    35.8 against 36.7 into reused ones), so it went.
    """
    threads = numba.get_num_threads() if parallel and _atomic.AVAILABLE else 1
    if threads == 1 or n_rays < PARALLEL_MIN_RAYS:
        return run_serial(kernels.span, span_inputs, n_rays, worst, buffers)
    return run_ordered(kernels, inputs, bound_inputs, n_rays, worst, threads, buffers)


def bound_counts(origins, directions, args, bounds):
    """Write an upper bound on each ray's segments into ``bounds``: its set-up only.

    A ray never writes more segments than its bound (``geometry.segments_bound``),
    so regions sized by the bounds cannot overflow. Blocks of rays on all
    threads (``exact.trace_chunks`` with ``BOUND``).
    """
    n_rays = origins.shape[0]
    starts = np.append(np.arange(0, n_rays, BLOCK), n_rays)
    ends = np.empty(n_rays + 1, dtype=np.int64)
    _exact.trace_chunks(starts, np.zeros(starts.shape[0], dtype=np.int64), origins, directions,
                        _NO_T_MAX, args, *_NO_SEGMENTS, ends, _exact.BOUND)
    bounds[:] = ends[1:]


# What the bound pass neither reads nor writes, with the types of the trace's.
_NO_T_MAX = np.empty(0, dtype=np.float64)
_NO_SEGMENTS = (np.empty((0, 3), dtype=np.int32), np.empty(0), np.empty(0))
EXACT_KERNELS = BatchKernels(_exact.trace_span, _exact.trace_ordered, bound_counts)


def _on_host(kernel):
    """Return a small ``@jit`` helper's Python function, for a call from Python.

    The same arithmetic on Python ints, without compiling it as a kernel of
    its own: 0.2 s less in the first answer (``python -m bench.first_call``).
    """
    return getattr(kernel, "py_func", kernel)


def run_exact(grid, origins, directions, t_max, parallel, buffers=None):
    """Trace with the exact method, serially or on all threads (see the module docstring)."""
    args = grid.kernel_args()
    size = _on_host(_geometry.scratch_size)(*grid.shape)
    scratch = (np.empty((3, size), dtype=np.float64), np.empty((3, size), dtype=np.int64),
               np.empty(8, dtype=np.int64), _exact.TRACE)
    inputs = (origins, directions, t_max, args)
    most = _on_host(_geometry.max_segments)(*grid.shape)
    return run_batch(EXACT_KERNELS, inputs + scratch, inputs, (origins, directions, args),
                     origins.shape[0], most, parallel, buffers)


# The ordered chunks reserve this much more than the sampled bounds promise;
# the bounds are upper bounds (1.0-1.6x the segments on the benchmark's rays),
# so the output outgrows its room only when the sample is off by more than this.
RESERVE_MARGIN = 1.25
# Rays sampled for their bounds, plus one in 512; at most one in 16 (a ray's
# set-up costs about a quarter of tracing it on bench.run's grid), but 64 at
# least.
BOUND_SAMPLES = 512
# A reservation at least this large is checked against the available memory
# first (reading it costs about 0.1 ms); a smaller one that cannot be had
# fails in numpy with a MemoryError of its own.
CHECKED_BYTES = 1 << 28


def _sampled_bounds(kernels, bound_inputs, n_rays):
    """Upper bounds on the segments of the rays, sampled: (strata, bounds).

    One ray at random from each of equal strata (``strata[i]:strata[i + 1]``),
    so the sample is in order and spread evenly; ``bounds[i]`` is that ray's
    bound (``kernels.bounds``: its set-up, no stepping).
    """
    origins, directions, *rest = bound_inputs
    samples = min(n_rays, max(64, min(n_rays // 16, BOUND_SAMPLES + n_rays // 512)))
    strata = np.linspace(0, n_rays, samples + 1).astype(np.int64)
    rows = strata[:-1] + (np.random.default_rng(0).random(samples)
                          * (strata[1:] - strata[:-1])).astype(np.int64)
    bounds = np.empty(samples, dtype=np.int64)
    kernels.bounds(origins[rows], directions[rows], *rest, bounds)
    return strata, bounds


def _check_output(n_rays, per_ray):
    """Raise MemoryError, before tracing, when a batch's output cannot fit.

    ``per_ray``: the sampled bounds' segments per ray (upper bounds, 1.0-1.6x
    the segments traced on bench.run's rays). The output is its segments and
    the rays' offsets; the chunks' scratch is reused and mostly untouched.
    """
    validate.fits("origins", int(per_ray * n_rays) * SEGMENT_BYTES + 8 * n_rays,
                  f"tracing {n_rays:,} rays (about {int(per_ray * n_rays):,} segments)")


def _fits_in_memory(length):
    """Return False when ``length`` segments are known not to fit in the available memory."""
    if length * SEGMENT_BYTES < CHECKED_BYTES:
        return True
    available = validate.available_memory()
    return available is None or length * SEGMENT_BYTES <= available


def run_exact_ordered(grid, origins, directions, t_max, workers, buffers=None, touch_ahead=True):
    """Trace with the exact method in ordered chunks on ``workers`` (``run_ordered``).

    For tests and benchmarks, which pick the worker count.
    """
    inputs = (origins, directions, t_max, grid.kernel_args())
    return run_ordered(EXACT_KERNELS, inputs, (origins, directions, inputs[3]), origins.shape[0],
                       _on_host(_geometry.max_segments)(*grid.shape), workers, buffers, touch_ahead)


def run_ordered(kernels, inputs, bound_inputs, n_rays, worst, workers, buffers=None,
                touch_ahead=True):
    """Trace in chunks taken in order and placed by the threads that traced them.

    See the module docstring and ``kernels.ordered``.
    ``kernels.ordered(first_row, last_row, chunk_rays, workers, *inputs,
    *scratch, cells, t_enter, t_exit, offsets, used, fresh_end, block_rows)``
    traces rows ``first_row..last_row-1`` and places them from segment
    ``used`` on, faulting in the fresh rows ``used..fresh_end-1`` as it goes,
    ``block_rows`` at a time (``kernels.ordered.TOUCH_ROWS``, read here at
    each call); it returns
    per chunk the first row not placed. ``workers`` may exceed the
    thread count (the output is the same). ``buffers``: a ``TraceBuffers``
    to write into (the result is views of it).

    Fresh output is faulted in by the workers as they go, each block of it
    by one thread, ahead of the chunks (``ordered.touched``); with
    ``touch_ahead=False`` (for ``bench.faults``, which times both) it is
    faulted in by the chunks' copies instead.
    """
    start = time.perf_counter()
    strata, bounds = _sampled_bounds(kernels, bound_inputs, n_rays)
    per_ray = float(np.dot(bounds, np.diff(strata))) / n_rays
    chunk_rays = max(1, ORDERED_SEGMENTS // worst)
    room = chunk_rays * worst
    length = int(RESERVE_MARGIN * per_ray * n_rays) + room
    _check_output(n_rays, per_ray)
    if not _fits_in_memory(length):
        # The margin does not fit, the bounds' estimate does: reserve what there
        # is. Should the output need more, it grows, and that is checked.
        length = max(int(validate.available_memory() // SEGMENT_BYTES), room)
    start = lap("bound", start)
    # Kept whatever its size: only the pages a chunk writes are ever touched.
    scratch = scratch_segments(2 * workers * room, "ordered", keep=True)
    offsets = _ray_offsets(n_rays, buffers)
    held = None if buffers is None else buffers.segments()
    fresh = held is None or held[0].shape[0] < length
    output = segment_arrays(length) if fresh else held
    row = 0
    used = 0
    while row < n_rays:
        start = lap("allocate", start)
        reached = kernels.ordered(row, n_rays, chunk_rays, workers, *inputs, *scratch, *output,
                                  offsets, used,
                                  output[0].shape[0] if fresh and touch_ahead else used,
                                  _ordered.TOUCH_ROWS)
        start = lap("trace", start)
        ends = np.minimum(row + chunk_rays * np.arange(1, reached.shape[0] + 1), n_rays)
        short = np.flatnonzero(reached < ends)
        row = int(reached[short[0]]) if short.size else n_rays
        used = int(offsets[row])
        if short.size == 0:
            break
        # The output was too small: keep the rows placed, grow, trace the rest.
        # The whole batch by the segments per ray so far, with 3% to spare.
        expected = int(1.03 * used / row * n_rays) + room if row else 0
        capacity = output[0].shape[0]
        capacity = max(expected, capacity + capacity // 2, used + room) + room
        validate.fits("origins", capacity * SEGMENT_BYTES,
                      f"tracing {n_rays:,} rays (about {capacity:,} segments)")
        start = lap("other", start)
        fresh = True  # the rows past ``used`` of the grown arrays
        if buffers is None:  # in place; buffers may be viewed by an earlier result
            output = tuple(resized(a, capacity) for a in output)
        else:
            output = tuple(grown(a, capacity, used) for a in output)
    return _result(offsets, output, used, buffers, start)


# Below this many rays ``trace_regions`` runs on one thread, and a first call
# compiles neither of its parallel kernels (4.3 s of a cold main job's 18.5 s
# on 2 cores). A gaze's default cone has 200-300 rays (225 for bench.cone's
# gaze, 303 for the README's). ``fixation_probability`` on bench.cone's gaze,
# best of 40 calls on 2 threads, one thread against both: 128 rays 0.46 ms
# against 0.43, 225 rays 0.70 against 0.63, 384 rays 1.04 against 0.86, 512
# rays 1.32 against 1.05, 1,000 rays 2.29 against 1.61. So a default gaze
# pays 0.07-0.15 ms a call (10-20%) for the 4 s it saves once.
CONE_PARALLEL_MIN_RAYS = 512


def trace_regions(grid, origins, directions, t_max, args, starts, segment_arrays):
    """Trace contiguous chunks of rays, ``starts[c]:starts[c + 1]``, each into its own region.

    Each chunk is one ``prange`` iteration and appends to its region; the
    regions are sized by the rays' bounds (``bound_counts``), so none
    can overflow. ``segment_arrays(n)``
    provides (cells, t_enter, t_exit) with room for at least ``n`` segments.
    Returns ``(starts, regions, ends, offsets, cells, t_enter, t_exit)``:
    chunk ``c`` holds rays ``starts[c]:starts[c + 1]``, written from
    ``regions[c]`` to ``ends[c]``, and ray ``r``'s segments are
    ``offsets[r]:offsets[r + 1]`` (gaps between regions).

    Fewer rays than ``CONE_PARALLEL_MIN_RAYS`` (a gaze's cone), or one
    thread: the rays are traced as ``trace_many`` traces them on one thread
    (``run_exact``, into this Python thread's ``TraceBuffers``), the regions
    back to back (no gaps). The chunks are the same, so what is summed per
    chunk is too.
    """
    start = time.perf_counter()
    n_rays = origins.shape[0]
    if n_rays < CONE_PARALLEL_MIN_RAYS or numba.get_num_threads() == 1:
        traces = run_exact(grid, origins, directions, t_max, False, _cone_buffers())
        regions = traces.offsets[starts]
        return (starts, regions, regions[1:].copy(), traces.offsets, traces.cells,
                traces.t_enter, traces.t_exit)
    cumulative = np.zeros(n_rays + 1, dtype=np.int64)
    bound_counts(origins, directions, args, cumulative[1:])
    np.cumsum(cumulative, out=cumulative)
    regions = cumulative[starts]
    validate.fits("n_rays", int(regions[-1]) * SEGMENT_BYTES + 16 * n_rays,
                  f"tracing {n_rays:,} rays of cones (at most {int(regions[-1]):,} segments)")
    cells, t_enter, t_exit = segment_arrays(int(regions[-1]))
    offsets = np.empty(n_rays + 1, dtype=np.int64)
    offsets[0] = 0
    start = lap("bound", start)
    ends = _exact.trace_chunks(starts, regions, origins, directions, t_max, args, cells, t_enter,
                               t_exit, offsets, _exact.TRACE)
    lap("trace", start)
    return starts, regions, ends, offsets, cells, t_enter, t_exit


def _cone_buffers():
    """Return this Python thread's ``TraceBuffers`` for cones traced on one thread."""
    held = getattr(_scratch, "cone_buffers", None)
    if held is None:
        held = _scratch.cone_buffers = TraceBuffers()
    return held


_scratch = threading.local()


# A cone's scratch is kept for the next call only up to this many segments
# (28 bytes each, 112 MB); a larger one is released after its call.
KEEP_SCRATCH_SEGMENTS = 1 << 22


# A cone's per-chunk copies of its boxes (``kernels.cone._boxes``) are kept
# for the next call up to this many boxes and chunks (24 bytes each, 48 MB).
KEEP_BOXES = 1 << 21


def box_pools():
    """Return this Python thread's scratch for a cone's boxes.

    A (float64, int64) pair of arrays, empty until :func:`keep_box_pools`
    sizes them.
    """
    held = getattr(_scratch, "boxes", None)
    if held is None:
        held = (np.empty(0), np.empty(0, dtype=np.int64))
    return held


def keep_box_pools(needed):
    """Size this Python thread's box scratch for ``needed`` boxes and chunks.

    ``needed`` is the kernels' count; the float64 pool holds twice as many
    values. A quarter is added to spare; nothing changes when the scratch
    holds enough already, or when ``needed`` passes ``KEEP_BOXES``.
    """
    if box_pools()[1].shape[0] < needed <= KEEP_BOXES:
        size = needed + needed // 4
        _scratch.boxes = (np.empty(2 * size), np.empty(size, dtype=np.int64))


def scratch_segments(length, kind="segments", keep=False):
    """Segment arrays reused by this Python thread, grown as needed; one set per ``kind``.

    ``"segments"``: a cone's (its segments are read once, by the aggregation;
    faulting in fresh pages for them each call took longer than tracing into
    them: 1.0 of 2.0 ms for a 1,000-ray cone, measured). ``"ordered"``: the
    ordered path's chunk buffers. Per Python thread, so concurrent calls never
    share them. Kept only up to ``KEEP_SCRATCH_SEGMENTS``: a larger request
    (a grid of millions of sectors) gets arrays of its own, freed after use,
    unless ``keep``.
    """
    held = getattr(_scratch, kind, None)
    if held is None or held[0].shape[0] < length:
        held = segment_arrays(length + length // 4)
        if keep or length <= KEEP_SCRATCH_SEGMENTS:
            setattr(_scratch, kind, held)
    return held
