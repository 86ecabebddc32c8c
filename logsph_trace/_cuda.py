"""The exact traversal on a CUDA GPU (numba-cuda): ``trace_many(..., device="cuda")``.

Imported only when a call asks for ``device="cuda"``, so ``import
logsph_trace`` never needs CUDA. The per-ray code is the CPU's own
``kernels.exact.trace_span`` and ``ray_bound``, compiled a second time by
numba-cuda: there is no second copy of the traversal.

A batch runs in five device steps, and nothing but a few totals comes back
to the host:

1. a bound kernel: each ray's upper bound on its segments (``ray_bound``,
   phase 1 only);
2. an exclusive prefix sum of the bounds, on the device (``exclusive_scan``):
   every ray's region;
3. a trace kernel (``trace_span`` of one ray) writing each ray into its
   region, and its segment count;
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
from pathlib import Path

import numpy as np
from numba import cuda

from . import _validate as validate
from ._jit import CACHE, cache_by_package
from .kernels import cone as _cone
from .kernels import exact, geometry, locate
from .kernels import radial as _radial
from .kernels import update as _update
from .kernels import walk as _walk
from .traces import Traces

THREADS = 128  # threads per block
SCAN_CHUNK = 32  # values one thread of the prefix sum adds up in order
RAYS_IN_FLIGHT = 65_536  # rays whose scratch is on the device at once
MEMORY_SHARE = 0.5  # of the free device memory, what the scratch or one part's regions may take
SEGMENT_BYTES = 4 * 3 + 8 + 8  # a cell, t_enter and t_exit
BIG = np.iinfo(np.int64).max  # "none yet" for an atomic min

# Every kernel is cached on disk, as the CPU's are (``LOGSPH_TRACE_CACHE=0`` turns it off),
# and checked against all the package's sources as they are. numba-cuda caches
# through a ``CacheImpl`` of its own; Numba's older built-in ``numba.cuda``
# through Numba's, which ``_jit`` already extends.
try:
    from numba.cuda.core import caching as _cuda_caching
except ImportError:
    pass
else:
    cache_by_package(Path(__file__).parent, _cuda_caching.CacheImpl)
kernel = cuda.jit(cache=CACHE)


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

@kernel
def _bound_kernel(origins, directions, grid, per_log, first, lookups, bounds):
    """Ray ``first + k`` (thread k): its bound on segments into ``bounds[first + k]``.

    ``per_log``: the grid's ``locate.per_log_of``, taken once on the host.
    """
    k = cuda.grid(1)
    row = first + k
    if k < lookups.shape[0] and row < origins.shape[0]:
        bounds[row] = geometry.ray_bound(origins, directions, row, grid, per_log, lookups[k])


@kernel
def _trace_kernel(origins, directions, t_max, grid, first, times, zones, lookups, regions, base,
                  cells, t_enter, t_exit, ends, counts):
    """Ray ``first + k`` (thread k) into its region, ``regions[row] - base`` on; its count.

    ``ends[row + 1]`` gets where its segments end (``trace_span``'s offsets).
    ``False`` is ``exact.TRACE``: a literal is fine here, where this kernel is
    the only one that compiles ``trace_span`` for the GPU.
    """
    k = cuda.grid(1)
    row = first + k
    if k < lookups.shape[0] and row < origins.shape[0]:
        start = regions[row] - base
        end, _ = exact.trace_span(row, row + 1, origins, directions, t_max, grid, times[:, :, k],
                                  zones[:, :, k], lookups[k], False, cells, t_enter, t_exit,
                                  ends, start, BIG)
        counts[row] = end - start


@kernel
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


@kernel
def _chunk_sums(values, sums):
    """Thread t: the total of chunk t of ``values`` (``SCAN_CHUNK`` values)."""
    t = cuda.grid(1)
    low = t * SCAN_CHUNK
    if low < values.shape[0]:
        total = 0
        for i in range(low, min(low + SCAN_CHUNK, values.shape[0])):
            total += values[i]
        sums[t] = total


@kernel
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

def to_device(array):
    """Copy a numpy array to the GPU."""
    return cuda.to_device(array)


def _device_grid(grid):
    """Return the grid's ``GridArrays`` with its arrays on the device (cached on the grid).

    The cone arrays go without the CPU's padding: a GPU thread times only
    the cones it needs (``crossings._branch_times``), where a CPU core computes
    a whole vector of them at no extra cost.
    """
    cached = getattr(grid, "_cuda_args", None)
    if cached is None:
        args = grid.kernel_args()
        cones = args.phi_edges.shape[0]
        args = args._replace(phi_tan2=args.phi_tan2[:cones], phi_nappe=args.phi_nappe[:cones])
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
    return _trace(grid, cuda.to_device(origins), cuda.to_device(directions),
                  cuda.to_device(np.ascontiguousarray(t_max, dtype=np.float64)))


def _scratch(size, n_rays):
    """Allocate the traversal's per-ray scratch for the rays in flight.

    Crossing times and zones, ``(3, size)`` each, and the lookups, for
    ``RAYS_IN_FLIGHT`` rays at most, fewer where that would not fit in
    ``MEMORY_SHARE`` of the free memory.
    """
    per_ray = 2 * 3 * size * 8 + 8 * 8
    in_flight = max(1, min(RAYS_IN_FLIGHT, n_rays, int(_free_bytes() * MEMORY_SHARE) // per_ray))
    return (cuda.device_array((3, size, in_flight), dtype=np.float64),
            cuda.device_array((3, size, in_flight), dtype=np.int64),
            cuda.device_array((in_flight, 8), dtype=np.int64))


def _trace(grid, d_origins, d_directions, d_t_max):
    """``trace_many`` of rays already on the device."""
    n_rays = d_origins.shape[0]
    args = _device_grid(grid)
    size = int(geometry.scratch_size(*grid.shape))
    times, zones, lookups = _scratch(size, n_rays)
    in_flight = lookups.shape[0]

    per_log = float(locate.per_log_of(grid.rho_edges, grid.rho_kind))
    bounds = cuda.device_array(max(n_rays, 1), dtype=np.int64)
    for first in range(0, n_rays, in_flight):
        _launch(_bound_kernel, in_flight, d_origins, d_directions, args, per_log, first, lookups,
                bounds)
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
    ends = cuda.device_array(n_rays + 1, dtype=np.int64)
    parts = [_trace_part(args, d_origins, d_directions, d_t_max, regions, start, stop, times,
                         zones, lookups, ends, counts)
             for start, stop in zip(splits[:-1], splits[1:])]
    offsets = exclusive_scan(counts[:n_rays])
    if len(parts) == 1:
        cells, t_enter, t_exit = parts[0]
    else:
        cells, t_enter, t_exit = _join(parts)
    return Traces(offsets, cells, t_enter, t_exit)


def _trace_part(args, origins, directions, t_max, regions, start, stop, times, zones, lookups,
                ends, counts):
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
                loose_cells, loose_enter, loose_exit, ends, counts)
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


# ---- GPU inputs -----------------------------------------------------------------------------
#
# Arrays already on the GPU are checked there, as ``_validate`` checks numpy
# inputs on the host, with the same messages; only the first bad row of each
# check comes back.

BAD_CHECKS = 5  # origins not finite, origins too long, directions not finite or zero, t_max


@kernel
def _cast_kernel(source, target):
    """Value ``row`` (thread) of ``source`` into the float64 ``target`` (1-D)."""
    row = cuda.grid(1)
    if row < target.shape[0]:
        target[row] = source[row]


@kernel
def _cast_rows_kernel(source, target):
    """Row ``row`` (thread) of ``source`` into the float64 ``target`` (2-D).

    A ``source`` of one row fills every row of ``target``.
    """
    row = cuda.grid(1)
    if row < target.shape[0]:
        read = min(row, source.shape[0] - 1)
        for column in range(target.shape[1]):
            target[row, column] = source[read, column]


def _repeat_row(row, n):
    """Return a (n, columns) float64 device array whose every row is ``row``'s one row."""
    target = cuda.device_array((n, row.shape[1]), dtype=np.float64)
    if n:
        _launch(_cast_rows_kernel, n, row, target)
    return target


@kernel
def _check_rays_kernel(origins, directions, t_max, unit, bad):
    """Ray ``row`` (thread): its unit direction (``norm3``, as ``_validate``).

    The first row failing each check goes into ``bad`` (atomic min).
    """
    row = cuda.grid(1)
    if row < origins.shape[0]:
        ox, oy, oz = origins[row, 0], origins[row, 1], origins[row, 2]
        if not (math.isfinite(ox) and math.isfinite(oy) and math.isfinite(oz)):
            cuda.atomic.min(bad, 0, row)
        elif not math.isfinite(ox * ox + oy * oy + oz * oz):
            cuda.atomic.min(bad, 1, row)
        dx, dy, dz = directions[row, 0], directions[row, 1], directions[row, 2]
        if not (math.isfinite(dx) and math.isfinite(dy) and math.isfinite(dz)):
            cuda.atomic.min(bad, 2, row)
        else:
            length = locate.norm3(dx, dy, dz)
            if length == 0.0:
                cuda.atomic.min(bad, 3, row)
            else:
                unit[row, 0] = dx / length
                unit[row, 1] = dy / length
                unit[row, 2] = dz / length
        if math.isnan(t_max[row]) or t_max[row] < 0.0:
            cuda.atomic.min(bad, 4, row)


@kernel
def _check_points_kernel(points, bad):
    """Point ``row`` (thread): the first row not finite into ``bad[0]``."""
    row = cuda.grid(1)
    if row < points.shape[0]:
        if not (math.isfinite(points[row, 0]) and math.isfinite(points[row, 1])
                and math.isfinite(points[row, 2])):
            cuda.atomic.min(bad, 0, row)


def _gpu_array(name, value, columns):
    """Return ``value`` as a float64 device array, (m, ``columns``) or (m,) for None.

    A GPU array is read in place (converted on the device unless float64);
    a host array is copied.
    """
    if hasattr(value, "__cuda_array_interface__"):
        array = cuda.as_cuda_array(value)
    elif validate.on_gpu(value):  # the simulator's device arrays
        array = value
    else:
        array = validate.real_array(name, value)
        array = cuda.to_device(np.ascontiguousarray(array if columns is None
                                                    else np.atleast_2d(array)))
    wanted = "(m,)" if columns is None else f"(m, {columns})"
    if (array.ndim != 1) if columns is None else (array.ndim != 2 or array.shape[1] != columns):
        raise ValueError(f"{name} must have shape {wanted}, got {tuple(array.shape)}")
    if array.dtype != np.float64:
        if array.dtype.kind not in "fiu":
            raise ValueError(f"{name} must be numeric, got dtype {array.dtype}")
        converted = cuda.device_array(array.shape, dtype=np.float64)
        _launch(_cast_kernel if columns is None else _cast_rows_kernel, array.shape[0], array,
                converted)
        array = converted
    return array


def _first_bad(bad):
    """Return the first row failing each check, or -1 (``bad`` on the device)."""
    rows = bad.copy_to_host()
    return [int(row) if row != BIG else -1 for row in rows]


def trace_gpu_inputs(grid, origins, directions, t_max):
    """``trace_many`` where some input is a GPU array: checked on the device, traced."""
    require()
    if directions is None:
        both = _gpu_array("origins", origins, 6)
        origins, directions = both[:, :3], both[:, 3:]
    else:
        origins, directions = validate.shared_rows(_gpu_array("origins", origins, 3),
                                                   _gpu_array("directions", directions, 3),
                                                   _repeat_row)
    n = origins.shape[0]
    if validate.on_gpu(t_max):
        d_t_max = _gpu_array("t_max", t_max, None)
        if d_t_max.shape != (n,):
            raise ValueError(f"t_max must be a number or have shape ({n},), got "
                             f"{tuple(d_t_max.shape)}")
    else:
        d_t_max = cuda.to_device(validate.distances(t_max, n))
    unit = cuda.device_array((n, 3), dtype=np.float64)
    bad = cuda.to_device(np.full(BAD_CHECKS, BIG, dtype=np.int64))
    if n:
        _launch(_check_rays_kernel, n, origins, directions, d_t_max, unit, bad)
    rows = _first_bad(bad)
    problems = (  # in the order the host checks them
        ("origins", origins, validate.NOT_FINITE), ("origins", origins, validate.TOO_LONG),
        ("directions", directions, validate.NOT_FINITE), ("directions", directions, validate.ZERO),
        ("t_max", d_t_max, validate.NEGATIVE),
    )
    for row, (name, array, message) in zip(rows, problems):
        if row >= 0:
            _bad_row(name, array, row, message)
    return _trace(grid, origins, unit, d_t_max)


def _bad_row(name, array, row, message):
    """Raise ``message`` about row ``row`` of the device array ``array``, as the host would."""
    value = array[row:row + 1].copy_to_host()[0]
    value = float(value) if np.ndim(value) == 0 else value.tolist()
    raise ValueError(message.format(name=name, row=row, value=value))


def cells_of_gpu_points(grid, points):
    """``Grid.cell_of`` of a GPU array of points (M, 3): checked and looked up there."""
    require()
    points = _gpu_array("points", points, 3)
    bad = cuda.to_device(np.full(1, BIG, dtype=np.int64))
    if points.shape[0]:
        _launch(_check_points_kernel, points.shape[0], points, bad)
    row = _first_bad(bad)[0]
    if row >= 0:
        _bad_row("points", points, row, validate.NOT_FINITE)
    return _cells_on_device(grid, points)


# ---- points ---------------------------------------------------------------------------------

@kernel
def _cells_of_kernel(points, grid, out):
    """Point ``row`` (thread): its cell, as the CPU's ``locate.cells_of_points``."""
    row = cuda.grid(1)
    if row < points.shape[0]:
        out[row, 0], out[row, 1], out[row, 2] = locate.cell_of_point(
            points[row, 0], points[row, 1], points[row, 2], grid.rho_edges, grid.rho_kind,
            grid.theta_edges, grid.theta_kind, grid.phi_edges, grid.phi_kind)


def cells_of(grid, points):
    """Look up checked points (C-contiguous (M, 3) float64): a device array (M, 3) int32."""
    require()
    return _cells_on_device(grid, cuda.to_device(points))


def _cells_on_device(grid, points):
    """Look up checked points already on the device: a device array (M, 3) int32."""
    out = cuda.device_array((points.shape[0], 3), dtype=np.int32)
    if points.shape[0]:
        _launch(_cells_of_kernel, points.shape[0], points, _device_grid(grid), out)
    return out


# ---- cones ----------------------------------------------------------------------------------
#
# A cone's cells are aggregated as on the CPU (``kernels.cone``): at each
# shell the cone's cells fill a (theta, phi) box, the boxes of all cones laid
# end to end. One thread per ray: the extents of the boxes (atomic min and
# max), then each ray's weight added once to every box it crosses (atomic
# adds, so the weights' last bits depend on the order the GPU runs rays in)
# and the first reach (atomic min), then one thread per shell writes the
# reached boxes as cells. A ray re-entering a cell is found in a bitmap of
# the boxes of its cone, one per ray in flight.

@kernel
def _extent_kernel(offsets, cells, ray_cone, j_shifts, n_theta, low_j, high_j, low_k, high_k):
    """Ray ``ray`` (thread): widen its cone's per-shell boxes to hold its cells."""
    ray = cuda.grid(1)
    if ray < offsets.shape[0] - 1:
        cone = ray_cone[ray]
        for seg in range(offsets[ray], offsets[ray + 1]):
            i = cells[seg, 0]
            j = _cone.shifted(cells[seg, 1], j_shifts[cone], n_theta)
            k = np.int64(cells[seg, 2])
            cuda.atomic.min(low_j, (cone, i), j)
            cuda.atomic.max(high_j, (cone, i), j)
            cuda.atomic.min(low_k, (cone, i), k)
            cuda.atomic.max(high_k, (cone, i), k)


@kernel
def _weigh_kernel(first_ray, offsets, cells, t_enter, t_exit, ray_cone, ray_weights, j_shifts,
                  n_theta, n_phi, low_j, low_k, span_k, base, seen, fixation, log_odds,
                  min_distance, unknown, free_below, weight, first, reached):
    """Ray ``first_ray + k`` (thread k): its weight once into every box it crosses.

    With ``fixation``, its weight times the probability that the box's cell
    is the first occupied one it meets (as ``kernels.cone.fixation_boxes``).

    ``seen`` (words, rays in flight) uint32: thread k's bitmap of its cone's
    boxes, in column k (neighbouring threads, neighbouring words).
    """
    k = cuda.grid(1)
    ray = first_ray + k
    if k < seen.shape[1] and ray < offsets.shape[0] - 1:
        cone = ray_cone[ray]
        start = base[cone, 0]
        for word in range((base[cone, base.shape[1] - 1] - start + 31) // 32):
            seen[word, k] = 0
        clear = 1.0  # fixation: the probability that nothing so far stopped the gaze
        for seg in range(offsets[ray], offsets[ray + 1]):
            box = _cone.box_of(cells, seg, low_j[cone], low_k[cone], span_k[cone], base[cone],
                               n_theta, j_shifts[cone])
            cuda.atomic.min(first, box, t_enter[seg])
            if fixation and t_exit[seg] <= min_distance:
                continue  # not counted, and not seen: met again beyond, it counts there
            word = (box - start) // 32
            bit = np.uint32(1) << np.uint32((box - start) % 32)
            if (seen[word, k] & bit) == 0:  # not a re-entry
                seen[word, k] |= bit
                reached[box] = 1
                if fixation:
                    p = _cone.stop_probability(log_odds, cells, seg, n_theta, n_phi, unknown,
                                               free_below)
                    cuda.atomic.add(weight, box, ray_weights[ray] * p * clear)
                    clear *= 1.0 - p
                else:
                    cuda.atomic.add(weight, box, ray_weights[ray])


@kernel
def _box_cells_kernel(low_j, low_k, span_k, base, j_shifts, n_theta, weight, first, at,
                      out_cells, out_weight, out_first):
    """Shell ``i`` of cone ``c`` (thread ``c * n_rho + i``): its reached boxes as cells.

    They go to ``at[box]`` on, ``at`` being the exclusive scan of the reached flags.
    """
    t = cuda.grid(1)
    n_rho = base.shape[1] - 1
    cone = t // n_rho
    i = t - cone * n_rho
    if cone < base.shape[0]:
        for box in range(base[cone, i], base[cone, i + 1]):
            found = at[box]
            if at[box + 1] != found:
                out_cells[found, 0] = i
                out_cells[found, 1], out_cells[found, 2] = _cone.unbox(
                    box, i, low_j[cone], low_k[cone], span_k[cone], base[cone], n_theta,
                    j_shifts[cone])
                out_weight[found] = weight[box]
                out_first[found] = first[box]


@kernel
def _gather_kernel(values, index, out):
    """``out[t] = values[index[t]]``."""
    t = cuda.grid(1)
    if t < index.shape[0]:
        out[t] = values[index[t]]


def aggregate_cones(grid, origins, directions, ray_weights, counts, j_shifts, fixation=None):
    """Trace cones' rays on the GPU and aggregate each cone's cells there.

    ``origins``, ``directions`` (m, 3) and ``ray_weights`` (m,): every ray of
    every cone, cone after cone, ``counts[c]`` rays for cone ``c``;
    ``j_shifts`` (c,): each cone's azimuth shift. ``fixation``: ``(log_odds,
    min_distance, unknown, free_below)``, the map flat on the device, for
    first-occupied probabilities instead of weights (see
    ``cone.aggregate_cells``). Returns, per cone, its (cells, summed values,
    t_first) on the host, unsorted (shell by shell, in box order, as the
    CPU's ``aggregate_boxes``).
    """
    require()
    n_cones, n_rho, n_theta = len(counts), grid.n_rho, grid.n_theta
    ray_cone = np.repeat(np.arange(n_cones, dtype=np.int64), counts)
    traces = _trace(grid, cuda.to_device(origins), cuda.to_device(directions),
                    cuda.to_device(np.full(origins.shape[0], np.inf)))
    d_ray_cone = cuda.to_device(ray_cone)
    d_j_shifts = cuda.to_device(np.asarray(j_shifts, dtype=np.int64))
    extents = [np.full((n_cones, n_rho), BIG, dtype=np.int64),
               np.full((n_cones, n_rho), -1, dtype=np.int64)]
    low_j, high_j, low_k, high_k = (cuda.to_device(extents[e]) for e in (0, 1, 0, 1))
    n_rays = origins.shape[0]
    _launch(_extent_kernel, n_rays, traces.offsets, traces.cells, d_ray_cone, d_j_shifts,
            n_theta, low_j, high_j, low_k, high_k)

    # The layout, on the host: 4 x cones x shells numbers.
    low_j, high_j, low_k, high_k = (a.copy_to_host() for a in (low_j, high_j, low_k, high_k))
    span_k = np.zeros((n_cones, n_rho), dtype=np.int64)
    base = np.zeros((n_cones, n_rho + 1), dtype=np.int64)
    for cone in range(n_cones):
        span_k[cone], base[cone] = _cone.box_bases(low_j[cone], high_j[cone], low_k[cone],
                                                   high_k[cone])
    sizes = base[:, n_rho].copy()
    base += np.concatenate(([0], np.cumsum(sizes)[:-1]))[:, None]  # cones end to end
    total = int(sizes.sum())

    d_low_j, d_low_k, d_span_k, d_base = (cuda.to_device(a) for a in (low_j, low_k, span_k, base))
    weight = cuda.to_device(np.zeros(max(total, 1)))
    first = cuda.to_device(np.full(max(total, 1), np.inf))
    reached = cuda.to_device(np.zeros(max(total, 1), dtype=np.int64))
    words = max(1, (int(sizes.max(initial=0)) + 31) // 32)
    share = int(_free_bytes() * MEMORY_SHARE)
    in_flight = max(1, min(RAYS_IN_FLIGHT, n_rays, share // (4 * words)))
    seen = cuda.device_array((words, in_flight), dtype=np.uint32)
    d_weights = cuda.to_device(np.ascontiguousarray(ray_weights, dtype=np.float64))
    # The kernel's fixation switch and its map: a stand-in one when only weights are summed.
    weigh = ((False, cuda.device_array(1, dtype=np.float32), 0.0, 0.0, 0.0) if fixation is None
             else (True, *fixation))
    for first_ray in range(0, n_rays, in_flight):
        _launch(_weigh_kernel, in_flight, first_ray, traces.offsets, traces.cells,
                traces.t_enter, traces.t_exit, d_ray_cone, d_weights, d_j_shifts, n_theta,
                grid.n_phi, d_low_j, d_low_k, d_span_k, d_base, seen, *weigh, weight, first,
                reached)
    at = exclusive_scan(reached[:total])
    n_cells = int(at[total])
    out_cells = cuda.device_array((max(n_cells, 1), 3), dtype=np.int32)
    out_weight = cuda.device_array(max(n_cells, 1))
    out_first = cuda.device_array(max(n_cells, 1))
    _launch(_box_cells_kernel, n_cones * n_rho, d_low_j, d_low_k, d_span_k, d_base, d_j_shifts,
            n_theta, weight, first, at, out_cells, out_weight, out_first)
    cells, weights, t_first = (a.copy_to_host()[:n_cells]
                               for a in (out_cells, out_weight, out_first))
    bounds = cuda.device_array(n_cones + 1, dtype=np.int64)
    _launch(_gather_kernel, n_cones + 1, at, cuda.to_device(np.append(base[:, 0], total)), bounds)
    bounds = bounds.copy_to_host()
    return [(cells[lo:hi], weights[lo:hi], t_first[lo:hi])
            for lo, hi in zip(bounds[:-1], bounds[1:])]


# ---- the occupancy map ----------------------------------------------------------------------
#
# The CPU's per-ray code (``kernels.walk``: ``sensor_ray`` and
# ``walk_ray``, or ``radial_ray`` for a sensor at the centre) marks the cells
# each ray frees, one thread per ray, into flags shared by all threads: every
# write is a 1, so threads may write the same flag. One thread per cell then
# applies OctoMap's update, once per cell, as ``apply_scan`` does.

@kernel
def _mark_scan_kernel(first_row, origin, points, max_range, grid, zone, times, zones, lookups,
                      free, hits):
    """Ray ``first_row + k`` (thread k) of a scan from ``origin``: flag its free cells.

    Flags are column-major, as ``apply_scan``'s; ``hits[row]``: its hit there, or -1.
    """
    k = cuda.grid(1)
    row = first_row + k
    if k < lookups.shape[0] and row < points.shape[0]:
        ox = origin[0]
        oy = origin[1]
        oz = origin[2]
        dx, dy, dz, distance, is_hit, is_ray = _walk.sensor_ray(points, row, ox, oy, oz,
                                                                max_range)
        hits[row] = -1
        if is_ray:
            hits[row] = _walk.walk_ray(ox, oy, oz, dx, dy, dz, distance, is_hit, zone[0],
                                       zone[1], zone[2], grid, times[:, :, k], zones[:, :, k],
                                       lookups[k], free, 0)


@kernel
def _mark_radial_kernel(points, max_range, grid, per_log, free_extent, hits):
    """Ray ``row`` (thread) from the grid's origin: widen its column's free extent.

    ``hits[row]``: its hit cell's map index, or -1.
    """
    row = cuda.grid(1)
    if row < points.shape[0]:
        guesses = cuda.local.array(3, np.int64)
        for zone in range(3):
            guesses[zone] = -1
        column, free, hits[row] = _radial.radial_ray(points, row, max_range, grid, per_log,
                                                     guesses)
        if column >= 0 and free > 0:
            cuda.atomic.max(free_extent, column, free)


@kernel
def _flag_hits_kernel(hits, flags):
    """Ray ``row`` (thread): flag its hit cell."""
    row = cuda.grid(1)
    if row < hits.shape[0] and hits[row] >= 0:
        flags[hits[row]] = 1


@kernel
def _apply_scan_kernel(log_odds, free, hit, n_rho, log_hit, log_miss, log_min, log_max):
    """Cell ``index`` (thread, column-major): OctoMap's update, a hit winning."""
    index = cuda.grid(1)
    if index < free.shape[0] and (free[index] != 0 or hit[index] != 0):
        n_columns = free.shape[0] // n_rho
        cell = (index % n_rho) * n_columns + index // n_rho
        _update._update(log_odds, cell, hit[index] != 0, free[index] != 0, log_hit, log_miss,
                        log_min, log_max)


@kernel
def _apply_radial_kernel(log_odds, free_extent, hit, log_hit, log_miss, log_min, log_max):
    """Cell ``cell`` (thread, map index): free below its column's extent; a hit wins."""
    cell = cuda.grid(1)
    if cell < log_odds.shape[0]:
        n_columns = free_extent.shape[0]
        free = cell // n_columns < free_extent[cell % n_columns]
        if free or hit[cell] != 0:
            _update._update(log_odds, cell, hit[cell] != 0, free, log_hit, log_miss, log_min,
                            log_max)


@kernel
def _scale_kernel(values, factor):
    """``values[t] *= factor``."""
    t = cuda.grid(1)
    if t < values.shape[0]:
        values[t] *= factor


def integrate(grid, log_odds, points, origin, max_range, update, want_hits=False):
    """Integrate a checked scan into the device map ``log_odds`` (flat float32).

    ``update``: the log-odds of a hit and a miss and the clamps. The same
    cells as the CPU's ``OccupancyGrid.integrate``, the same update. With
    ``want_hits``, return each ray's hit cell on the host, or -1, indexed as
    the CPU's kernels index it (the map's index from the centre, else
    column-major).
    """
    require()
    n_rays, n_cells = points.shape[0], log_odds.shape[0]
    if n_rays == 0:
        return np.empty(0, dtype=np.int64)
    args = _device_grid(grid)
    d_points = cuda.to_device(points)
    hits = cuda.device_array(n_rays, dtype=np.int64)
    hit = cuda.to_device(np.zeros(n_cells, dtype=np.uint8))
    if not np.any(origin):  # the egocentric case: every ray is radial
        free_extent = cuda.to_device(np.zeros(grid.n_theta * grid.n_phi, dtype=np.int64))
        per_log = locate.log_cells(grid.rho_edges) if grid.rho_kind == locate.LOG else 0.0
        _launch(_mark_radial_kernel, n_rays, d_points, max_range, args, per_log, free_extent,
                hits)
        _launch(_flag_hits_kernel, n_rays, hits, hit)
        _launch(_apply_radial_kernel, n_cells, log_odds, free_extent, hit, *update)
        return hits.copy_to_host() if want_hits else None
    zone = np.array([
        locate.rho_zone(*origin, grid.rho_edges, grid.rho_kind),
        locate.theta_zone(origin[0], origin[2], grid.theta_edges, grid.theta_kind),
        locate.phi_zone(*origin, grid.phi_edges, grid.phi_kind)], dtype=np.int64)
    free = cuda.to_device(np.zeros(n_cells, dtype=np.uint8))
    times, zones, lookups = _scratch(int(geometry.scratch_size(*grid.shape)), n_rays)
    d_origin, d_zone = cuda.to_device(origin), cuda.to_device(zone)
    in_flight = lookups.shape[0]
    for first_row in range(0, n_rays, in_flight):
        _launch(_mark_scan_kernel, in_flight, first_row, d_origin, d_points, max_range, args,
                d_zone, times, zones, lookups, free, hits)
    _launch(_flag_hits_kernel, n_rays, hits, hit)
    _launch(_apply_scan_kernel, n_cells, log_odds, free, hit, grid.n_rho, *update)
    return hits.copy_to_host() if want_hits else None


def decay(log_odds, factor):
    """``log_odds *= factor`` on the device (flat float32, factor a float32)."""
    _launch(_scale_kernel, log_odds.shape[0], log_odds, factor)


def values_at(values, index):
    """``values[index]`` (a flat device array, index (u,) int64) on the host."""
    out = cuda.device_array(max(index.shape[0], 1), dtype=values.dtype)
    if index.shape[0]:
        _launch(_gather_kernel, index.shape[0], values, cuda.to_device(index), out)
    return out.copy_to_host()[:index.shape[0]]
