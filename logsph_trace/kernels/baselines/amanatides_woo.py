"""Amanatides & Woo (1987) traversal of a Cartesian voxel box: the speed-of-light reference.

Written in the same style as the exact log-spherical kernel (scalar state,
the same segment output, the same batching: one appending pass on one
thread, chunks placed in order on more) so timings compare like for like.
"""

import math

import numpy as np
from numba import prange

from ..._jit import jit
from ..ordered import advance, buffer_of, chain, post, rows_of, take


@jit
def _slab(origin, direction, low, high):
    """Interval of t where one coordinate lies in [low, high]."""
    if direction == 0.0:
        if low <= origin <= high:
            return -np.inf, np.inf
        return np.inf, -np.inf
    t_a = (low - origin) / direction
    t_b = (high - origin) / direction
    return min(t_a, t_b), max(t_a, t_b)


@jit
def _axis_start(origin, direction, t_start, low, size, n):
    """Voxel index at t_start, step sign, t of the next boundary, t between boundaries."""
    index = int(math.floor((origin + t_start * direction - low) / size))
    index = min(max(index, 0), n - 1)
    if direction > 0.0:
        return index, 1, (low + (index + 1) * size - origin) / direction, size / direction
    if direction < 0.0:
        return index, -1, (low + index * size - origin) / direction, -size / direction
    return index, 0, np.inf, np.inf


@jit(inline="always")
def _box_span_of(origins, directions, row, low, size, shape):
    """Ray ``row``'s origin and direction, and the t interval it spends in the box."""
    ox, oy, oz = origins[row, 0], origins[row, 1], origins[row, 2]
    dx, dy, dz = directions[row, 0], directions[row, 1], directions[row, 2]
    near_x, far_x = _slab(ox, dx, low[0], low[0] + shape[0] * size[0])
    near_y, far_y = _slab(oy, dy, low[1], low[1] + shape[1] * size[1])
    near_z, far_z = _slab(oz, dz, low[2], low[2] + shape[2] * size[2])
    return (ox, oy, oz, dx, dy, dz, max(0.0, near_x, near_y, near_z),
            min(far_x, far_y, far_z))


@jit(inline="always")
def box_max_segments(shape):
    """Most voxels one ray can cross in a box of ``shape`` (``trace_box_ray``'s loop bound)."""
    return shape[0] + shape[1] + shape[2]


@jit(inline="always")
def trace_box_ray(origins, directions, row, low, size, shape, cells, t_enter, t_exit, start):
    """Trace ray ``row`` (unit direction) through the box, writing its voxels from
    ``start`` on; return their number.

    The loop moves one index by one each time and stops when any index leaves
    its range, so it runs at most ``shape[0] + shape[1] + shape[2]`` times.
    """
    ox, oy, oz, dx, dy, dz, t_now, t_out = _box_span_of(origins, directions, row, low, size,
                                                        shape)
    if not t_now < t_out:
        return 0
    ix, step_x, next_x, delta_x = _axis_start(ox, dx, t_now, low[0], size[0], shape[0])
    iy, step_y, next_y, delta_y = _axis_start(oy, dy, t_now, low[1], size[1], shape[1])
    iz, step_z, next_z, delta_z = _axis_start(oz, dz, t_now, low[2], size[2], shape[2])
    count = 0
    while True:
        t_next = min(next_x, next_y, next_z, t_out)
        if t_next > t_now:
            cells[start + count, 0] = ix
            cells[start + count, 1] = iy
            cells[start + count, 2] = iz
            t_enter[start + count] = t_now
            t_exit[start + count] = t_next
            count += 1
        if t_next >= t_out:
            break
        t_now = t_next
        if next_x <= next_y and next_x <= next_z:
            ix += step_x
            next_x += delta_x
            if ix < 0 or ix >= shape[0]:
                break
        elif next_y <= next_z:
            iy += step_y
            next_y += delta_y
            if iy < 0 or iy >= shape[1]:
                break
        else:
            iz += step_z
            next_z += delta_z
            if iz < 0 or iz >= shape[2]:
                break
    return count


@jit
def box_bound(origins, directions, row, low, size, shape):
    """An upper bound on ``trace_box_ray``'s voxels for ray ``row``, in O(1).

    The index steps between the voxels of its entry and exit, one more per
    axis for rounding (the walk accumulates its boundary times), at most the
    walk's own limit ``shape[0] + shape[1] + shape[2]``. The GPU baseline of
    ``bench.gpu`` sizes each ray's region with it, as the exact kernel's
    ``BOUND`` mode does.
    """
    ox, oy, oz, dx, dy, dz, t_in, t_out = _box_span_of(origins, directions, row, low, size,
                                                       shape)
    if not t_in < t_out:
        return 0
    steps = (1 + _axis_steps(ox, dx, t_in, t_out, low[0], size[0], shape[0])
             + _axis_steps(oy, dy, t_in, t_out, low[1], size[1], shape[1])
             + _axis_steps(oz, dz, t_in, t_out, low[2], size[2], shape[2]))
    return min(steps, box_max_segments(shape))


@jit(inline="always")
def _axis_steps(origin, direction, t_in, t_out, low, width, n):
    """Index steps along one axis between t_in and t_out, plus one for rounding."""
    first = min(max(int(math.floor((origin + t_in * direction - low) / width)), 0), n - 1)
    last = min(max(int(math.floor((origin + t_out * direction - low) / width)), 0), n - 1)
    return abs(last - first) + 1


@jit
def box_span(first, last, origins, directions, low, size, shape, cells, t_enter, t_exit, offsets,
             used, limit):
    """One thread: rays first..last-1 in order, appending (``exact.trace_span``'s contract)."""
    worst = box_max_segments(shape)
    for row in range(first, last):
        if limit - used < worst:
            return used, row
        used += trace_box_ray(origins, directions, row, low, size, shape, cells, t_enter, t_exit,
                              used)
        offsets[row + 1] = used
    return used, last


@jit(parallel=True)
def box_bounds(origins, directions, low, size, shape, bounds):
    """``box_bound`` of every ray, into ``bounds`` (``exact.bound_counts``'s contract)."""
    for row in prange(origins.shape[0]):
        bounds[row] = box_bound(origins, directions, row, low, size, shape)


@jit(parallel=True)
def box_ordered(first_row, last_row, chunk_rays, workers, origins, directions, low, size, shape,
                loose_cells, loose_enter, loose_exit, cells, t_enter, t_exit, offsets, used,
                fresh_end, block_rows):
    """Chunks taken in order and placed by the threads that traced them
    (``exact.trace_ordered``'s contract)."""
    room = chunk_rays * box_max_segments(shape)
    n_chunks, counts, starts, reached, counter, fresh = chain(first_row, last_row, chunk_rays,
                                                              used, fresh_end, block_rows)
    for worker in prange(workers):
        waiting = -1
        side = 0
        chunk = take(counter, n_chunks)
        while chunk >= 0 or waiting >= 0:
            if chunk >= 0:
                first, last = rows_of(chunk, first_row, chunk_rays, last_row)
                source = buffer_of(worker, side, room)
                end, _ = box_span(first, last, origins, directions, low, size, shape, loose_cells,
                                  loose_enter, loose_exit, offsets, source, source + room)
                post(chunk, end - source, counts, starts)
            waiting, side, chunk = advance(
                chunk, waiting, worker, side, room, first_row, last_row, chunk_rays, workers,
                counter, counts, starts, reached, fresh, loose_cells, loose_enter, loose_exit,
                cells, t_enter, t_exit, offsets,
            )
    return reached
