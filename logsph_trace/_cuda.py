"""The exact traversal on a CUDA GPU (numba-cuda): ``device="cuda"``.

Imported only when a call asks for ``device="cuda"``, so ``import
logsph_trace`` never needs CUDA. The per-ray code is the CPU's own
(``kernels.exact.trace_span``, ``kernels.walk``, ``kernels.radial``),
compiled a second time by numba-cuda: there is no second copy of the
traversal.

Every call takes its scratch from a workspace kept between calls
(:class:`Workspace`, one per Python thread): after the first call of a
given size, a call allocates device memory only for the output it hands
to the caller. Kernels loop over their rays (a grid-stride loop), so a
batch of any size is one launch, and the host waits for the device once
per call where it can: a scan of the map is two launches and no wait (one
when the hits are wanted back), a batch of cones two launches and one
wait. ``tests/test_cuda.py`` counts them under the simulator.

``trace_many`` runs in five device steps, and two totals come back to the
host before the output is made:

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
neighbouring words, and is kept for at most ``RAYS_IN_FLIGHT`` rays,
fewer when it would not fit in ``MEMORY_SHARE`` of the free device memory.
Rays are taken in parts whose regions fit in that share too; each part's
output is exact, and the parts are joined at the end.
"""

import contextlib
import math
import threading
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
def _bound_kernel(origins, directions, grid, per_log, lookups, bounds):
    """Rays k, k + threads, ... (thread k): each one's bound on segments into ``bounds``.

    ``per_log``: the grid's ``locate.per_log_of``, taken once on the host.
    """
    k = cuda.grid(1)
    if k < lookups.shape[0]:
        for row in range(k, origins.shape[0], lookups.shape[0]):
            bounds[row] = geometry.ray_bound(origins, directions, row, grid, per_log, lookups[k])


@kernel
def _trace_kernel(origins, directions, t_max, grid, start, stop, times, zones, lookups, regions,
                  cells, t_enter, t_exit, ends, counts):
    """Trace rays ``start + k``, ``start + k + threads``, ... below ``stop`` (thread k).

    Each goes into its region (``regions[row] - regions[start]`` on), its
    count into ``counts``, and where its segments end into ``ends[row + 1]``
    (``trace_span``'s offsets).
    ``False`` is ``exact.TRACE``: a literal is fine here, where this kernel is
    the only one that compiles ``trace_span`` for the GPU.
    """
    k = cuda.grid(1)
    if k < lookups.shape[0]:
        base = regions[start]
        for row in range(start + k, stop, lookups.shape[0]):
            first = regions[row] - base
            end, _ = exact.trace_span(row, row + 1, origins, directions, t_max, grid,
                                      times[:, :, k], zones[:, :, k], lookups[k], False, cells,
                                      t_enter, t_exit, ends, first, BIG)
            counts[row] = end - first


@kernel
def _compact_kernel(regions, offsets, loose_cells, loose_enter, loose_exit, cells, t_enter,
                    t_exit):
    """Ray ``row``'s segments from its region to ``offsets[row] - offsets[0]`` on."""
    row = cuda.grid(1)
    if row < offsets.shape[0] - 1:
        source = regions[row] - regions[0]
        target = offsets[row] - offsets[0]
        for s in range(offsets[row + 1] - offsets[row]):
            cells[target + s, 0] = loose_cells[source + s, 0]
            cells[target + s, 1] = loose_cells[source + s, 1]
            cells[target + s, 2] = loose_cells[source + s, 2]
            t_enter[target + s] = loose_enter[source + s]
            t_exit[target + s] = loose_exit[source + s]


@kernel
def _fill_kernel(values, value):
    """``values[t] = value`` (1-D)."""
    t = cuda.grid(1)
    if t < values.shape[0]:
        values[t] = value


@kernel
def _chunk_sums(values, chunk, sums):
    """Thread t: the total of chunk t of ``values`` (``chunk`` values) into ``sums[t]``."""
    t = cuda.grid(1)
    low = t * chunk
    if low < values.shape[0]:
        total = 0
        for i in range(low, min(low + chunk, values.shape[0])):
            total += values[i]
        sums[t] = total


@kernel
def _chunk_scan(values, chunk, sums, out):
    """Thread t: the chunks before t added up, then chunk t's running totals into ``out``."""
    t = cuda.grid(1)
    if t == 0:
        out[0] = 0
    low = t * chunk
    if low < values.shape[0]:
        running = 0
        for c in range(t):
            running += sums[c]
        for i in range(low, min(low + chunk, values.shape[0])):
            running += values[i]
            out[i + 1] = running


def exclusive_scan(values, out, workspace):
    """Fill ``out`` (n + 1,) int64 with 0, then the running totals of ``values`` (n,) int64.

    Two launches whatever n: each of about sqrt(n) threads adds up a chunk
    of about sqrt(n) values, then each adds up the chunk totals before its
    own and writes its chunk's running totals. No barriers and no shared
    memory, so it is cheap under Numba's CUDA simulator too, which runs each
    thread as Python; about 1.5 n reads in all.
    """
    n = values.shape[0]
    chunk = max(SCAN_CHUNK, math.isqrt(max(n - 1, 0)) + 1)
    chunks = max(1, -(-n // chunk))
    sums = workspace.take("scan sums", (chunks,), np.int64)
    _launch(_chunk_sums, chunks, values, chunk, sums)
    _launch(_chunk_scan, chunks, values, chunk, sums, out)
    return out


# ---- the workspace --------------------------------------------------------------------------

# Device memory a Python thread's workspace keeps between calls; a buffer that
# would take it past this is used for its call and freed.
KEEP_BYTES = 1 << 31


class Workspace:
    """Device buffers kept between calls, one per name, each grown to the largest asked.

    ``take`` hands out a view of the named buffer: after a call of some size,
    a call of that size or less allocates nothing. A buffer taken with a
    ``fill`` is filled once, when it is made, and the kernels that use it put
    the fill back as they go (a scan's flags are cleared by the kernel that
    applies them), so it is never refilled from the host. An exception in a
    call drops every buffer (:func:`working`): one left half-used is never
    handed out again.
    """

    def __init__(self):
        self._held = {}

    def take(self, name, shape, dtype, fill=None):
        """Return a device array of ``shape`` and ``dtype``: the named buffer's first elements."""
        shape = tuple(int(n) for n in shape)
        size = math.prod(shape)
        held = self._held.get(name)
        if held is None or held.dtype != np.dtype(dtype) or held.size < size:
            self._held.pop(name, None)  # the old one is freed before the new one is made
            held = cuda.device_array(max(size, 1), dtype=dtype)
            if fill is not None:
                _launch(_fill_kernel, held.size, held, fill)
            if self.nbytes + held.nbytes <= KEEP_BYTES:
                self._held[name] = held
        return held[:size].reshape(shape)

    @property
    def nbytes(self):
        """Bytes of device memory held."""
        return sum(held.nbytes for held in self._held.values())

    def clear(self):
        """Drop every buffer."""
        self._held.clear()


_threads = threading.local()


@contextlib.contextmanager
def working():
    """Yield this Python thread's :class:`Workspace`; an exception drops its buffers."""
    workspace = getattr(_threads, "workspace", None)
    if workspace is None:
        workspace = _threads.workspace = Workspace()
    try:
        yield workspace
    except BaseException:
        workspace.clear()
        raise


def _on_device(workspace, name, array):
    """Copy a host array into the named buffer (no allocation after the first call)."""
    held = workspace.take(name, array.shape, array.dtype)
    if array.size:
        held.copy_to_device(np.ascontiguousarray(array))
    return held


def _fetch(array):
    """Copy a device array back: where the host waits for the device."""
    return array.copy_to_host()


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
    with working() as workspace:
        return _trace(grid, _on_device(workspace, "origins", origins),
                      _on_device(workspace, "directions", directions),
                      _on_device(workspace, "t_max",
                                 np.ascontiguousarray(t_max, dtype=np.float64)), workspace)


def _scratch(size, per_ray_bytes, n_rays, workspace):
    """Return the traversal's per-ray scratch for the rays in flight.

    Crossing times and zones, ``(3, size)`` each, and the lookups, for
    ``RAYS_IN_FLIGHT`` rays at most, fewer where that and ``per_ray_bytes``
    more a ray would not fit in ``MEMORY_SHARE`` of the free memory.
    """
    per_ray = 2 * 3 * size * 8 + 8 * 8 + per_ray_bytes
    in_flight = max(1, min(RAYS_IN_FLIGHT, n_rays, int(_free_bytes() * MEMORY_SHARE) // per_ray))
    return (workspace.take("times", (3, size, in_flight), np.float64),
            workspace.take("zones", (3, size, in_flight), np.int64),
            workspace.take("lookups", (in_flight, 8), np.int64))


def _trace(grid, d_origins, d_directions, d_t_max, workspace):
    """``trace_many`` of rays already on the device."""
    n_rays = d_origins.shape[0]
    args = _device_grid(grid)
    size = int(geometry.scratch_size(*grid.shape))
    times, zones, lookups = _scratch(size, 0, n_rays, workspace)
    in_flight = lookups.shape[0]

    per_log = float(locate.per_log_of(grid.rho_edges, grid.rho_kind))
    bounds = workspace.take("bounds", (n_rays,), np.int64)
    if n_rays:
        _launch(_bound_kernel, in_flight, d_origins, d_directions, args, per_log, lookups,
                bounds)
    regions = exclusive_scan(bounds, workspace.take("regions", (n_rays + 1,), np.int64),
                             workspace)
    budget = max(int(_free_bytes() * MEMORY_SHARE) // SEGMENT_BYTES, 1)
    total = int(_fetch(regions[n_rays:])[0])
    if total <= budget:  # the usual case: one total comes back
        splits, host_regions = [0, n_rays], {0: 0, n_rays: total}
    else:  # split where the regions fill the budget, at least one ray a part
        host_regions = _fetch(regions)
        splits = [0]
        while splits[-1] < n_rays:
            start = splits[-1]
            stop = int(np.searchsorted(host_regions, host_regions[start] + budget,
                                       side="right")) - 1
            splits.append(min(max(stop, start + 1), n_rays))

    counts = workspace.take("counts", (n_rays,), np.int64)
    ends = workspace.take("ends", (n_rays + 1,), np.int64)
    parts = [_trace_part(args, d_origins, d_directions, d_t_max, regions, start, stop,
                         int(host_regions[stop] - host_regions[start]), times, zones, lookups,
                         ends, counts, workspace)
             for start, stop in zip(splits[:-1], splits[1:])]
    if len(parts) == 1:
        offsets, cells, t_enter, t_exit = parts[0]
    else:
        offsets, (cells, t_enter, t_exit) = _joined_offsets(parts), _join(parts)
    return Traces(offsets, cells, t_enter, t_exit)


def _trace_part(args, origins, directions, t_max, regions, start, stop, room, times, zones,
                lookups, ends, counts, workspace):
    """Trace rays ``start:stop`` into their regions, then copy them to exact-size arrays.

    ``room``: the segments their regions hold. Returns the part's offsets
    (from 0) and segments, new device arrays.
    """
    room = max(room, 1)
    loose_cells = workspace.take("loose cells", (room, 3), np.int32)
    loose_enter = workspace.take("loose enter", (room,), np.float64)
    loose_exit = workspace.take("loose exit", (room,), np.float64)
    if stop > start:
        _launch(_trace_kernel, min(lookups.shape[0], stop - start), origins, directions, t_max,
                args, start, stop, times, zones, lookups, regions, loose_cells, loose_enter,
                loose_exit, ends, counts)
    offsets = exclusive_scan(counts[start:stop], cuda.device_array(stop - start + 1,
                                                                  dtype=np.int64), workspace)
    total = int(_fetch(offsets[stop - start:])[0])  # one number back to the host
    cells = cuda.device_array((total, 3), dtype=np.int32)
    t_enter = cuda.device_array(total, dtype=np.float64)
    t_exit = cuda.device_array(total, dtype=np.float64)
    if stop > start:
        _launch(_compact_kernel, stop - start, regions[start:stop + 1], offsets, loose_cells,
                loose_enter, loose_exit, cells, t_enter, t_exit)
    return offsets, cells, t_enter, t_exit


def _joined_offsets(parts):
    """Return the parts' offsets, each from 0, as one array of offsets (on the device)."""
    host = [_fetch(part[0]) for part in parts]
    at = np.cumsum([0] + [h[-1] for h in host[:-1]])
    return cuda.to_device(np.concatenate([host[0]] + [h[1:] + a for h, a in
                                                      zip(host[1:], at[1:])]))


def _join(parts):
    """Concatenate the parts' segment arrays on the device."""
    total = sum(part[2].shape[0] for part in parts)
    cells = cuda.device_array((total, 3), dtype=np.int32)
    t_enter = cuda.device_array(total, dtype=np.float64)
    t_exit = cuda.device_array(total, dtype=np.float64)
    at = 0
    for _, part_cells, part_enter, part_exit in parts:
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
    with working() as workspace:
        return _trace(grid, origins, unit, d_t_max, workspace)


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
# A batch of cones is two launches and one wait. One thread per ray (in a
# grid-stride loop) traces the ray into a region of its own and adds its
# weight to each cell it reaches, in arrays of one value per cell of the
# grid and cone (atomic adds, so the weights' last bits depend on the order
# the GPU runs rays in; atomic min for the first reach). A cell a thread is
# first to touch goes on a list. One thread per listed cell then writes the
# reached ones out and resets their values, so the arrays are ready for the
# next batch without a pass over the grid. The host sorts the few cells that
# come back into the CPU's order (``aggregate_boxes``: cone, shell, azimuth
# from the cone's seam shift, elevation).
#
# A ray re-entering a cell adds nothing. Along a line the azimuth about the
# y axis is monotonic and sweeps less than a half turn, so a ray's segments
# in one azimuthal column are consecutive: a re-entry is found among the
# segments since the ray entered the column, with no per-ray set of cells.

TOUCHED = 1  # ``state``: a ray's first reach is in ``first``
REACHED = 2  # and a ray's weight is in ``weight``: the cell is an answer


@kernel
def _cone_kernel(ray_from, ray_to, cone_from, origins, directions, t_max, ray_weights, ray_cone,
                 grid, times, zones, lookups, cells, t_enter, t_exit, ends, room, fixation,
                 log_odds, min_distance, unknown, free_below, weight, first, state, listed,
                 counters):
    """Trace and weigh rays ``ray_from + k``, ``+ threads``, ... below ``ray_to`` (thread k).

    Each is traced into thread k's region (``room`` segments from ``k *
    room``), then its weight goes to each cell it reaches, in ``weight``
    (with ``fixation``, times the probability that the cell is the first
    occupied one it meets, as ``kernels.cone.fixation_boxes``).

    ``weight``, ``first`` and ``state`` hold a value per cell of each cone
    from ``cone_from`` on (cone, then the map's flat index); a slot first
    touched goes on ``listed`` (``counters[0]`` of them).
    """
    k = cuda.grid(1)
    if k < lookups.shape[0]:
        n_theta = grid.theta_edges.shape[0] - 1
        n_phi = grid.phi_edges.shape[0] - 1
        n_cells = (grid.rho_edges.shape[0] - 1) * n_theta * n_phi
        low = k * room
        for ray in range(ray_from + k, ray_to, lookups.shape[0]):
            high, _ = exact.trace_span(ray, ray + 1, origins, directions, t_max, grid,
                                       times[:, :, k], zones[:, :, k], lookups[k], False, cells,
                                       t_enter, t_exit, ends, low, BIG)
            cone_base = (ray_cone[ray] - cone_from) * n_cells
            clear = 1.0  # fixation: the probability that nothing so far stopped the gaze
            column_from = low  # the first segment in the current azimuthal column
            for seg in range(low, high):
                i, j, kk = cells[seg, 0], cells[seg, 1], cells[seg, 2]
                if seg > low and j != cells[seg - 1, 1]:
                    column_from = seg
                slot = cone_base + (i * n_theta + j) * n_phi + kk
                cuda.atomic.min(first, slot, t_enter[seg])
                if cuda.atomic.cas(state, slot, 0, TOUCHED) == 0:
                    listed[cuda.atomic.add(counters, 0, 1)] = slot
                if fixation and t_exit[seg] <= min_distance:
                    continue  # not counted, and not seen: met again beyond, it counts there
                again = False
                for back in range(column_from, seg):
                    if (cells[back, 0] == i and cells[back, 2] == kk
                            and not (fixation and t_exit[back] <= min_distance)):
                        again = True
                        break
                if again:
                    continue
                state[slot] = REACHED
                if fixation:
                    p = _cone.stop_probability(log_odds, cells, seg, n_theta, n_phi, unknown,
                                               free_below)
                    cuda.atomic.add(weight, slot, ray_weights[ray] * p * clear)
                    clear *= 1.0 - p
                else:
                    cuda.atomic.add(weight, slot, ray_weights[ray])


@kernel
def _cone_cells_kernel(listed, counters, cone_from, weight, first, state, out):
    """Write listed slot ``t`` (thread) out if reached; reset its values either way.

    Out at ``counters[1]``: (``cone_from``, the slot, its weight, its first reach).
    """
    t = cuda.grid(1)
    if t < counters[0]:
        slot = listed[t]
        if state[slot] == REACHED:
            at = cuda.atomic.add(counters, 1, 1)
            out[at, 0] = cone_from
            out[at, 1] = slot
            out[at, 2] = weight[slot]
            out[at, 3] = first[slot]
        weight[slot] = 0.0
        first[slot] = np.inf
        state[slot] = 0


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
    t_first) on the host, in the CPU's order (``aggregate_boxes``: shell by
    shell, then azimuth from the seam shift, then elevation).
    """
    require()
    n_cones, n_rays = len(counts), origins.shape[0]
    n_theta, n_phi = grid.n_theta, grid.n_phi
    n_cells = math.prod(grid.shape)
    ray_cone = np.repeat(np.arange(n_cones, dtype=np.int64), counts)
    cone_rays = np.concatenate(([0], np.cumsum(counts))).astype(np.int64)
    room = int(geometry.max_segments(*grid.shape))
    with working() as workspace:
        args = _device_grid(grid)
        times, zones, lookups = _scratch(int(geometry.scratch_size(*grid.shape)),
                                         room * SEGMENT_BYTES, n_rays, workspace)
        in_flight = lookups.shape[0]
        d_origins = _on_device(workspace, "origins", origins)
        d_directions = _on_device(workspace, "directions", directions)
        d_weights = _on_device(workspace, "ray weights",
                               np.ascontiguousarray(ray_weights, dtype=np.float64))
        d_ray_cone = _on_device(workspace, "ray cones", ray_cone)
        t_max = workspace.take("no end", (n_rays,), np.float64, fill=np.inf)
        cells = workspace.take("cone cells", (in_flight * room, 3), np.int32)
        t_enter = workspace.take("cone enter", (in_flight * room,), np.float64)
        t_exit = workspace.take("cone exit", (in_flight * room,), np.float64)
        ends = workspace.take("ends", (n_rays + 1,), np.int64)
        # Cones in groups whose per-cell values fit in the memory share.
        per_cone = n_cells * (8 + 8 + 4)
        group = max(1, min(n_cones, int(_free_bytes() * MEMORY_SHARE) // per_cone))
        weight = workspace.take("cone weight", (group * n_cells,), np.float64, fill=0.0)
        first = workspace.take("cone first", (group * n_cells,), np.float64, fill=np.inf)
        state = workspace.take("cone state", (group * n_cells,), np.int32, fill=0)
        capacity = max(1, min(group * n_cells, n_rays * room))
        listed = workspace.take("cone listed", (capacity,), np.int64)
        out = workspace.take("cone out", (max(1, min(n_cones * n_cells, n_rays * room)), 4),
                             np.float64)
        counters = _on_device(workspace, "cone counters", np.zeros(2, dtype=np.int64))
        weigh = ((False, workspace.take("no map", (1,), np.float32), 0.0, 0.0, 0.0)
                 if fixation is None else (True, *fixation))
        for cone_from in range(0, n_cones, group):
            cone_to = min(cone_from + group, n_cones)
            ray_from, ray_to = int(cone_rays[cone_from]), int(cone_rays[cone_to])
            if ray_to > ray_from:
                _launch(_cone_kernel, min(in_flight, ray_to - ray_from), ray_from, ray_to,
                        cone_from, d_origins, d_directions, t_max, d_weights, d_ray_cone, args,
                        times, zones, lookups, cells, t_enter, t_exit, ends, room, *weigh,
                        weight, first, state, listed, counters)
            _launch(_cone_cells_kernel, capacity, listed, counters, cone_from, weight, first,
                    state, out)
            if cone_to < n_cones:  # the list again from its start (the output count goes on)
                counters[:1].copy_to_device(np.zeros(1, dtype=np.int64))
        found = int(_fetch(counters)[1])  # where the host waits
        rows = _fetch(out[:found]) if found else np.empty((0, 4))
    cones = rows[:, 0].astype(np.int64) + (rows[:, 1].astype(np.int64) // n_cells)
    slots = rows[:, 1].astype(np.int64) % n_cells
    shell, column = np.divmod(slots, n_theta * n_phi)
    j, k = np.divmod(column, n_phi)
    shifted = (j + np.asarray(j_shifts, dtype=np.int64)[cones]) % n_theta
    order = np.lexsort((k, shifted, shell, cones))
    cells_out = np.stack([shell, j, k], axis=1).astype(np.int32)[order]
    values, t_first, cones = rows[order, 2], rows[order, 3], cones[order]
    bounds = np.searchsorted(cones, np.arange(n_cones + 1))
    return [(cells_out[lo:hi], values[lo:hi], t_first[lo:hi])
            for lo, hi in zip(bounds[:-1], bounds[1:])]


# ---- the occupancy map ----------------------------------------------------------------------
#
# The CPU's per-ray code (``kernels.walk``: ``sensor_ray`` and
# ``walk_ray``, or ``radial_ray`` for a sensor at the centre) marks the cells
# each ray frees, one thread per ray in a grid-stride loop, into flags shared
# by all threads: every write is a 1, so threads may write the same flag;
# the same thread flags its ray's hit. Then one thread per cell (per column
# from the centre) applies OctoMap's update once per cell, as ``apply_scan``
# does, and clears the flags it read: the next scan finds them zero.

@kernel
def _mark_scan_kernel(ox, oy, oz, zone_rho, zone_theta, zone_phi, points, max_range, grid,
                      times, zones, lookups, free, hit, hits):
    """Flag the free and hit cells of rays k, k + threads, ... (thread k) from (ox, oy, oz).

    Flags are column-major, as ``apply_scan``'s; ``hits[row]``: each ray's hit there, or -1.
    """
    k = cuda.grid(1)
    if k < lookups.shape[0]:
        for row in range(k, points.shape[0], lookups.shape[0]):
            dx, dy, dz, distance, is_hit, is_ray = _walk.sensor_ray(points, row, ox, oy, oz,
                                                                    max_range)
            cell = -1
            if is_ray:
                cell = _walk.walk_ray(ox, oy, oz, dx, dy, dz, distance, is_hit, zone_rho,
                                      zone_theta, zone_phi, grid, times[:, :, k],
                                      zones[:, :, k], lookups[k], free, 0)
            hits[row] = cell
            if cell >= 0:
                hit[cell] = 1


@kernel
def _mark_radial_kernel(points, max_range, grid, per_log, free_extent, hit, hits):
    """Ray ``row`` (thread) from the grid's origin: widen its column's free extent.

    It flags its hit cell (the map's index); ``hits[row]``: that cell, or -1.
    """
    row = cuda.grid(1)
    if row < points.shape[0]:
        guesses = cuda.local.array(3, np.int64)
        for zone in range(3):
            guesses[zone] = -1
        column, free, cell = _radial.radial_ray(points, row, max_range, grid, per_log, guesses)
        hits[row] = cell
        if cell >= 0:
            hit[cell] = 1
        if column >= 0 and free > 0:
            cuda.atomic.max(free_extent, column, free)


@kernel
def _apply_scan_kernel(log_odds, free, hit, n_rho, log_hit, log_miss, log_min, log_max):
    """Cell ``index`` (thread, column-major): OctoMap's update, a hit winning; flags cleared."""
    index = cuda.grid(1)
    if index < free.shape[0] and (free[index] != 0 or hit[index] != 0):
        n_columns = free.shape[0] // n_rho
        cell = (index % n_rho) * n_columns + index // n_rho
        _update._update(log_odds, cell, hit[index] != 0, free[index] != 0, log_hit, log_miss,
                        log_min, log_max)
        free[index] = 0
        hit[index] = 0


@kernel
def _apply_radial_kernel(log_odds, free_extent, hit, log_hit, log_miss, log_min, log_max):
    """Column ``column`` (thread): its shells free below its extent, a hit winning.

    In the map's index (neighbouring threads, neighbouring cells); its
    extent and flags cleared.
    """
    column = cuda.grid(1)
    n_columns = free_extent.shape[0]
    if column < n_columns:
        extent = free_extent[column]
        for cell in range(column, log_odds.shape[0], n_columns):
            free = cell // n_columns < extent
            if free or hit[cell] != 0:
                _update._update(log_odds, cell, hit[cell] != 0, free, log_hit, log_miss,
                                log_min, log_max)
                hit[cell] = 0
        free_extent[column] = 0


@kernel
def _scale_kernel(values, factor):
    """``values[t] *= factor``."""
    t = cuda.grid(1)
    if t < values.shape[0]:
        values[t] *= factor


def integrate(grid, log_odds, points, origin, max_range, update, want_hits=False):
    """Integrate a checked scan into the device map ``log_odds`` (flat float32).

    ``update``: the log-odds of a hit and a miss and the clamps. The same
    cells as the CPU's ``OccupancyGrid.integrate``, the same update. Two
    launches; the host waits only when ``want_hits``: then it returns each
    ray's hit cell on the host, or -1, indexed as the CPU's kernels index it
    (the map's index from the centre, else column-major).
    """
    require()
    n_rays, n_cells = points.shape[0], log_odds.shape[0]
    if n_rays == 0:
        return np.empty(0, dtype=np.int64)
    args = _device_grid(grid)
    with working() as workspace:
        d_points = _on_device(workspace, "points", points)
        hits = workspace.take("hits", (n_rays,), np.int64)
        hit = workspace.take("hit flags", (n_cells,), np.uint8, fill=0)
        if not np.any(origin):  # the egocentric case: every ray is radial
            n_columns = grid.n_theta * grid.n_phi
            free_extent = workspace.take("free extents", (n_columns,), np.int64, fill=0)
            per_log = locate.log_cells(grid.rho_edges) if grid.rho_kind == locate.LOG else 0.0
            _launch(_mark_radial_kernel, n_rays, d_points, max_range, args, per_log,
                    free_extent, hit, hits)
            _launch(_apply_radial_kernel, n_columns, log_odds, free_extent, hit, *update)
        else:
            zone = (locate.rho_zone(*origin, grid.rho_edges, grid.rho_kind),
                    locate.theta_zone(origin[0], origin[2], grid.theta_edges, grid.theta_kind),
                    locate.phi_zone(*origin, grid.phi_edges, grid.phi_kind))
            free = workspace.take("free flags", (n_cells,), np.uint8, fill=0)
            times, zones, lookups = _scratch(int(geometry.scratch_size(*grid.shape)), 0, n_rays,
                                             workspace)
            _launch(_mark_scan_kernel, lookups.shape[0], *(float(v) for v in origin),
                    *(int(z) for z in zone), d_points, max_range, args, times, zones, lookups,
                    free, hit, hits)
            _launch(_apply_scan_kernel, n_cells, log_odds, free, hit, grid.n_rho, *update)
        return _fetch(hits) if want_hits else None


def decay(log_odds, factor):
    """``log_odds *= factor`` on the device (flat float32, factor a float32)."""
    _launch(_scale_kernel, log_odds.shape[0], log_odds, factor)


def values_at(values, index):
    """``values[index]`` (a flat device array, index (u,) int64) on the host."""
    if not index.shape[0]:
        return np.empty(0, dtype=values.dtype)
    with working() as workspace:
        out = workspace.take("gathered", index.shape, values.dtype)
        _launch(_gather_kernel, index.shape[0], values, _on_device(workspace, "index", index),
                out)
        return _fetch(out)
