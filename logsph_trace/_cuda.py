"""The exact traversal on a CUDA GPU (numba-cuda): ``trace_many(..., device="cuda")``.

Imported only when a call asks for ``device="cuda"``, so ``import
logsph_trace`` never needs CUDA. The per-ray code is the CPU's own
``kernels.exact.trace_ray``, compiled a second time by numba-cuda: there is
no second copy of the traversal.

A batch runs in five device steps, and nothing but a few totals comes back
to the host:

1. a bound kernel: each ray's upper bound on its segments (``trace_ray``'s
   ``BOUND`` mode, phase 1 only);
2. an exclusive prefix sum of the bounds, on the device (``exclusive_scan``):
   every ray's region;
3. a trace kernel (``FULL`` mode) writing each ray into its region, and its
   segment count;
4. a prefix sum of the counts: the output's CSR offsets;
5. a copy of every region into the exact-size output.

The per-ray scratch (crossing times and zones, ``(3, size)`` each) is laid
out ray-fastest, ``(3, size, rays in flight)``, so neighbouring threads read
neighbouring words, and is allocated for at most ``RAYS_IN_FLIGHT`` rays,
fewer when it would not fit in ``MEMORY_SHARE`` of the free device memory.
Rays are taken in parts whose regions fit in that share too; each part's
output is exact, and the parts are joined at the end.
"""

import math

import numpy as np
from numba import cuda

from .kernels import exact
from .traces import Traces

THREADS = 128  # threads per block
SCAN_CHUNK = 32  # values one thread of the prefix sum adds up in order
RAYS_IN_FLIGHT = 65_536  # rays whose scratch is on the device at once
MEMORY_SHARE = 0.5  # of the free device memory, what the scratch or one part's regions may take
SEGMENT_BYTES = 4 * 3 + 8 + 8  # a cell, t_enter and t_exit


def require():
    """Raise one clear error unless a CUDA GPU can be used (or Numba's simulator is on)."""
    try:
        available = cuda.is_available()
    except Exception as error:  # a broken driver or toolkit raises rather than answers
        raise RuntimeError(f"device='cuda': CUDA could not be initialised ({error})") from None
    if not available:
        raise RuntimeError(
            "device='cuda' needs an NVIDIA GPU with a working driver, and numba-cuda "
            "(pip install 'logsph_trace[cuda]'); numba.cuda.is_available() is False here. "
            "Use device='cpu'.")


# ---- kernels --------------------------------------------------------------------------------

@cuda.jit
def _bound_kernel(origins, directions, t_max, grid, first, times, zones, lookups, bounds, cells,
                  t_enter, t_exit):
    """Ray ``first + k`` (thread k): its bound on segments into ``bounds[first + k]``."""
    k = cuda.grid(1)
    row = first + k
    if k < lookups.shape[0] and row < origins.shape[0]:
        bounds[row] = exact.trace_ray(origins, directions, row, grid, t_max[row],
                                      times[:, :, k], zones[:, :, k], lookups[k], cells, t_enter,
                                      t_exit, 0, exact.BOUND)


@cuda.jit
def _trace_kernel(origins, directions, t_max, grid, first, times, zones, lookups, regions, base,
                  cells, t_enter, t_exit, counts):
    """Ray ``first + k`` (thread k) into its region, ``regions[row] - base`` on; its count."""
    k = cuda.grid(1)
    row = first + k
    if k < lookups.shape[0] and row < origins.shape[0]:
        counts[row] = exact.trace_ray(origins, directions, row, grid, t_max[row], times[:, :, k],
                                      zones[:, :, k], lookups[k], cells, t_enter, t_exit,
                                      regions[row] - base, exact.FULL)


@cuda.jit
def _compact_kernel(regions, base, offsets, loose_cells, loose_enter, loose_exit, cells, t_enter,
                    t_exit):
    """Ray ``row``'s segments from its region to ``offsets[row] - offsets[0]`` on."""
    row = cuda.grid(1)
    if row < offsets.shape[0] - 1:
        source = regions[row] - base
        target = offsets[row] - offsets[0]
        for s in range(offsets[row + 1] - offsets[row]):
            cells[target + s, 0] = loose_cells[source + s, 0]
            cells[target + s, 1] = loose_cells[source + s, 1]
            cells[target + s, 2] = loose_cells[source + s, 2]
            t_enter[target + s] = loose_enter[source + s]
            t_exit[target + s] = loose_exit[source + s]


@cuda.jit
def _chunk_sums(values, sums):
    """Thread t: the total of chunk t of ``values`` (``SCAN_CHUNK`` values)."""
    t = cuda.grid(1)
    low = t * SCAN_CHUNK
    if low < values.shape[0]:
        total = 0
        for i in range(low, min(low + SCAN_CHUNK, values.shape[0])):
            total += values[i]
        sums[t] = total


@cuda.jit
def _chunk_scan(values, chunk_offsets, out):
    """Thread t: the running totals of chunk t, from the chunks before it, into ``out``."""
    t = cuda.grid(1)
    if t == 0:
        out[0] = 0
    low = t * SCAN_CHUNK
    if low < values.shape[0]:
        running = chunk_offsets[t]
        for i in range(low, min(low + SCAN_CHUNK, values.shape[0])):
            running += values[i]
            out[i + 1] = running


def exclusive_scan(values):
    """Device array (n + 1,) int64: 0, then the running totals of ``values`` (n,) int64.

    Each thread adds up a chunk of ``SCAN_CHUNK`` values in order; the chunk
    totals are scanned the same way (recursively, 32 times fewer each level),
    then each thread writes its chunk's running totals. No barriers and no
    shared memory: cheap enough under Numba's CUDA simulator too, which runs
    each thread as Python.
    """
    n = values.shape[0]
    out = cuda.device_array(n + 1, dtype=np.int64)
    chunks = max(1, math.ceil(n / SCAN_CHUNK))
    if chunks == 1:
        chunk_offsets = cuda.to_device(np.zeros(1, dtype=np.int64))
    else:
        sums = cuda.device_array(chunks, dtype=np.int64)
        _launch(_chunk_sums, chunks, values, sums)
        chunk_offsets = exclusive_scan(sums)
    _launch(_chunk_scan, chunks, values, chunk_offsets, out)
    return out


# ---- the batch ------------------------------------------------------------------------------

def _device_grid(grid):
    """Return the grid's ``GridArrays`` with its arrays on the device (cached on the grid)."""
    cached = getattr(grid, "_cuda_args", None)
    if cached is None:
        args = grid.kernel_args()
        cached = type(args)(*[cuda.to_device(np.ascontiguousarray(a))
                              if isinstance(a, np.ndarray) else a for a in args])
        object.__setattr__(grid, "_cuda_args", cached)
    return cached


def _launch(kernel, n, *args):
    kernel[max(1, math.ceil(n / THREADS)), THREADS](*args)


def _free_bytes():
    try:
        free, _ = cuda.current_context().get_memory_info()
        return int(free)
    except Exception:  # the simulator has no memory to ask about
        return 1 << 30


def trace_many(grid, origins, directions, t_max):
    """Trace checked rays (C-contiguous float64 arrays, unit directions) on the GPU.

    Returns a :class:`Traces` whose arrays are numba-cuda device arrays (they
    speak the CUDA Array Interface); ``Traces.to_host()`` copies them back.
    """
    require()
    n_rays = origins.shape[0]
    args = _device_grid(grid)
    size = int(exact.scratch_size(*grid.shape))
    d_origins = cuda.to_device(origins)
    d_directions = cuda.to_device(directions)
    d_t_max = cuda.to_device(np.ascontiguousarray(t_max, dtype=np.float64))
    # Rays in flight: their scratch (times and zones) in a share of the free memory.
    per_ray = 2 * 3 * size * 8 + 8 * 8
    in_flight = max(1, min(RAYS_IN_FLIGHT, n_rays, int(_free_bytes() * MEMORY_SHARE) // per_ray))
    times = cuda.device_array((3, size, in_flight), dtype=np.float64)
    zones = cuda.device_array((3, size, in_flight), dtype=np.int64)
    lookups = cuda.device_array((in_flight, 8), dtype=np.int64)
    no_cells = cuda.device_array((1, 3), dtype=np.int32)
    no_times = cuda.device_array(1, dtype=np.float64)

    bounds = cuda.device_array(max(n_rays, 1), dtype=np.int64)
    for first in range(0, n_rays, in_flight):
        _launch(_bound_kernel, in_flight, d_origins, d_directions, d_t_max, args, first, times,
                zones, lookups, bounds, no_cells, no_times, no_times)
    regions = exclusive_scan(bounds[:n_rays])
    budget = max(int(_free_bytes() * MEMORY_SHARE) // SEGMENT_BYTES, 1)
    if int(regions[n_rays]) <= budget:  # the usual case: one total comes back
        splits = [0, n_rays]
    else:  # split where the regions fill the budget, at least one ray a part
        host_regions = regions.copy_to_host()
        splits = [0]
        while splits[-1] < n_rays:
            start = splits[-1]
            stop = int(np.searchsorted(host_regions, host_regions[start] + budget,
                                       side="right")) - 1
            splits.append(min(max(stop, start + 1), n_rays))

    counts = cuda.device_array(max(n_rays, 1), dtype=np.int64)
    parts = [_trace_part(args, d_origins, d_directions, d_t_max, regions, start, stop, times,
                         zones, lookups, counts) for start, stop in zip(splits[:-1], splits[1:])]
    offsets = exclusive_scan(counts[:n_rays])
    if len(parts) == 1:
        cells, t_enter, t_exit = parts[0]
    else:
        cells, t_enter, t_exit = _join(parts)
    return Traces(offsets, cells, t_enter, t_exit)


def _trace_part(args, origins, directions, t_max, regions, start, stop, times, zones, lookups,
                counts):
    """Trace rays ``start:stop`` into their regions, then copy them to exact-size arrays."""
    base = int(regions[start])
    room = max(int(regions[stop]) - base, 1)
    loose_cells = cuda.device_array((room, 3), dtype=np.int32)
    loose_enter = cuda.device_array(room, dtype=np.float64)
    loose_exit = cuda.device_array(room, dtype=np.float64)
    in_flight = lookups.shape[0]
    for first in range(start, stop, in_flight):
        _launch(_trace_kernel, min(in_flight, stop - first), origins, directions, t_max, args,
                first, times, zones, lookups[:min(in_flight, stop - first)], regions, base,
                loose_cells, loose_enter, loose_exit, counts)
    offsets = exclusive_scan(counts[start:stop])
    total = int(offsets[stop - start])  # one number back to the host
    cells = cuda.device_array((total, 3), dtype=np.int32)
    t_enter = cuda.device_array(total, dtype=np.float64)
    t_exit = cuda.device_array(total, dtype=np.float64)
    _launch(_compact_kernel, stop - start, regions[start:stop + 1], base, offsets, loose_cells,
            loose_enter, loose_exit, cells, t_enter, t_exit)
    return cells, t_enter, t_exit


def _join(parts):
    """Concatenate the super-batches' segment arrays on the device."""
    total = sum(part[1].shape[0] for part in parts)
    cells = cuda.device_array((total, 3), dtype=np.int32)
    t_enter = cuda.device_array(total, dtype=np.float64)
    t_exit = cuda.device_array(total, dtype=np.float64)
    at = 0
    for part_cells, part_enter, part_exit in parts:
        n = part_enter.shape[0]
        if n:
            cells[at:at + n].copy_to_device(part_cells)
            t_enter[at:at + n].copy_to_device(part_enter)
            t_exit[at:at + n].copy_to_device(part_exit)
        at += n
    return cells, t_enter, t_exit
