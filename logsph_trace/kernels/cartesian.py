"""Amanatides & Woo (1987) traversal of a Cartesian voxel box: the speed-of-light reference.

Written in the same style as the exact log-spherical kernel (scalar state,
count pass + fill pass, same segment output) so timings compare like for like.
"""

import numpy as np
from numba import prange

from .._jit import jit, jit_twins


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
    index = int(np.floor((origin + t_start * direction - low) / size))
    index = min(max(index, 0), n - 1)
    if direction > 0.0:
        return index, 1, (low + (index + 1) * size - origin) / direction, size / direction
    if direction < 0.0:
        return index, -1, (low + index * size - origin) / direction, -size / direction
    return index, 0, np.inf, np.inf


@jit
def trace_box_ray(origins, directions, row, low, size, shape, cells, t_enter, t_exit, start, write):
    """Trace ray ``row`` (unit direction) through the box; return its number of voxels.

    The loop moves one index by one each time and stops when any index leaves
    its range, so it runs at most ``shape[0] + shape[1] + shape[2]`` times.
    """
    ox, oy, oz = origins[row, 0], origins[row, 1], origins[row, 2]
    dx, dy, dz = directions[row, 0], directions[row, 1], directions[row, 2]
    near_x, far_x = _slab(ox, dx, low[0], low[0] + shape[0] * size[0])
    near_y, far_y = _slab(oy, dy, low[1], low[1] + shape[1] * size[1])
    near_z, far_z = _slab(oz, dz, low[2], low[2] + shape[2] * size[2])
    t_now = max(0.0, near_x, near_y, near_z)
    t_out = min(far_x, far_y, far_z)
    if not t_now < t_out:
        return 0
    ix, step_x, next_x, delta_x = _axis_start(ox, dx, t_now, low[0], size[0], shape[0])
    iy, step_y, next_y, delta_y = _axis_start(oy, dy, t_now, low[1], size[1], shape[1])
    iz, step_z, next_z, delta_z = _axis_start(oz, dz, t_now, low[2], size[2], shape[2])
    count = 0
    while True:
        t_next = min(next_x, next_y, next_z, t_out)
        if t_next > t_now:
            if write:
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


@jit_twins
def box_rows(origins, directions, low, size, shape, offsets, cells, t_enter, t_exit, write):
    """Count (``write`` False) or write (True) every ray's voxels; return the counts.

    One source for both CSR passes: counting passes empty output arrays, and
    writing puts ray ``row``'s voxels from ``offsets[row]`` on.
    """
    counts = np.empty(origins.shape[0], dtype=np.int64)
    for row in prange(origins.shape[0]):
        counts[row] = trace_box_ray(
            origins, directions, row, low, size, shape, cells, t_enter, t_exit,
            offsets[row] if write else 0, write,
        )
    return counts
