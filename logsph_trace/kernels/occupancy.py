"""Occupancy kernels (``@jit`` only): integrate a scan, first-occupied probabilities.

Parallel work never shares a write: each thread marks its own row of the
free/hit flag arrays, and a second ``prange`` over cells combines the rows.
"""

import numba
import numpy as np
from numba import prange

from .._jit import jit
from .exact import FULL, max_segments, scratch_size, trace_ray
from .locate import BLOCK, locate, phi_zone, theta_zone


def _mark_rays(origins, directions, distances, is_hit, rho_edges, rho_sq, rho_kind, theta_edges,
               theta_sin, theta_cos, theta_kind, theta_full, phi_edges, phi_tan2, phi_nappe,
               phi_kind, free_flags, hit_flags):
    """Trace each sensor ray up to its distance; flag the cells it crosses as free and,
    for a hit, the cell holding its end point (its last segment) as hit.

    ``free_flags`` and ``hit_flags`` are (threads, n_cells) uint8, one row per thread.
    """
    n_rays = origins.shape[0]
    n_rho = rho_edges.shape[0] - 1
    n_theta = theta_edges.shape[0] - 1
    n_phi = phi_edges.shape[0] - 1
    worst = max_segments(n_rho, n_theta, n_phi)
    size = scratch_size(n_rho, n_theta, n_phi)
    for block in prange((n_rays + BLOCK - 1) // BLOCK):
        thread = numba.get_thread_id()
        times = np.empty((3, size), dtype=np.float64)
        zones = np.empty((3, size), dtype=np.int64)
        lookups = np.empty(8, dtype=np.int64)
        cells = np.empty((worst, 3), dtype=np.int32)
        t_enter = np.empty(worst, dtype=np.float64)
        t_exit = np.empty(worst, dtype=np.float64)
        for row in range(block * BLOCK, min(n_rays, (block + 1) * BLOCK)):
            count = trace_ray(
                origins[row, 0], origins[row, 1], origins[row, 2],
                directions[row, 0], directions[row, 1], directions[row, 2],
                rho_edges, rho_sq, rho_kind,
                theta_edges, theta_sin, theta_cos, theta_kind, theta_full,
                phi_edges, phi_tan2, phi_nappe, phi_kind,
                distances[row], times, zones, lookups, cells, t_enter, t_exit, 0, FULL,
            )
            # The end point lies in the last segment's cell when the trace
            # reaches it inside the region.
            ends_inside = count > 0 and is_hit[row] and t_exit[count - 1] >= distances[row]
            free_until = count - 1 if ends_inside else count
            for seg in range(free_until):
                flat = (cells[seg, 0] * n_theta + cells[seg, 1]) * n_phi + cells[seg, 2]
                free_flags[thread, flat] = 1
            if ends_inside:
                last = count - 1
                flat = (cells[last, 0] * n_theta + cells[last, 1]) * n_phi + cells[last, 2]
                hit_flags[thread, flat] = 1


@jit
def _update(log_odds, cell, hit, free, log_hit, log_miss, log_min, log_max):
    """OctoMap's update of one cell: a hit wins over a miss; clamped."""
    if hit:
        log_odds[cell] = min(log_odds[cell] + log_hit, log_max)
    elif free:
        log_odds[cell] = max(log_odds[cell] + log_miss, log_min)


def _apply_flags(log_odds, free_flags, hit_flags, log_hit, log_miss, log_min, log_max):
    """OctoMap's update, once per cell per scan: a hit wins over a miss; clamped."""
    threads = free_flags.shape[0]
    for cell in prange(log_odds.shape[0]):
        hit = False
        free = False
        for thread in range(threads):
            hit = hit or hit_flags[thread, cell] != 0
            free = free or free_flags[thread, cell] != 0
        _update(log_odds, cell, hit, free, log_hit, log_miss, log_min, log_max)


mark_rays = jit(_mark_rays, parallel=True)
apply_flags = jit(_apply_flags, parallel=True)


@jit
def first_occupied(offsets, cells, t_exit, log_odds, n_theta, n_phi, ray_weights,
                   min_distance, unknown, free_below):
    """Per segment: weight x P(its cell is the first occupied cell the ray meets).

    ``log_odds`` is the flat map; only the cells the rays cross are turned
    into probabilities: ``unknown`` for a never-observed cell (log-odds 0), 0
    below ``free_below``. Along a ray, P_first(c) = p_c times the product of
    (1 - p) over the distinct cells before c; a cell the ray re-enters adds
    nothing (had it been occupied, the ray would have stopped at the first
    entry). Segments ending within ``min_distance`` are skipped.
    """
    out = np.zeros(cells.shape[0])
    for ray in range(offsets.shape[0] - 1):
        clear = 1.0  # probability that nothing so far stopped the gaze
        for seg in range(offsets[ray], offsets[ray + 1]):
            if t_exit[seg] <= min_distance:
                continue
            seen = False
            for earlier in range(offsets[ray], seg):
                if (cells[earlier, 0] == cells[seg, 0] and cells[earlier, 1] == cells[seg, 1]
                        and cells[earlier, 2] == cells[seg, 2]):
                    seen = True
                    break
            if seen:
                continue
            flat = (cells[seg, 0] * n_theta + cells[seg, 1]) * n_phi + cells[seg, 2]
            if log_odds[flat] == 0:
                p = unknown
            else:
                p = 1.0 / (1.0 + np.exp(-np.float64(log_odds[flat])))
                if p < free_below:
                    p = 0.0
            out[seg] = ray_weights[ray] * p * clear
            clear *= 1.0 - p
    return out


def _mark_radial(points, distances, is_hit, rho_edges, rho_kind, theta_edges, theta_kind,
                 phi_edges, phi_kind, free_extent, hit_flags):
    """The sensor at the grid's origin: every ray is radial, so its cells are one
    (theta, phi) column, free up to the shell holding its end point.

    ``free_extent`` (threads, n_theta * n_phi) int64 records, per thread and
    column, how many shells from the centre are free; ``hit_flags`` as in
    ``_mark_rays``. Three lookups per ray instead of a traversal.
    """
    n_rays = points.shape[0]
    n_rho = rho_edges.shape[0] - 1
    n_theta = theta_edges.shape[0] - 1
    n_phi = phi_edges.shape[0] - 1
    for block in prange((n_rays + BLOCK - 1) // BLOCK):
        thread = numba.get_thread_id()
        for row in range(block * BLOCK, min(n_rays, (block + 1) * BLOCK)):
            x = points[row, 0]
            y = points[row, 1]
            z = points[row, 2]
            j = theta_zone(x, z, theta_edges, theta_kind)
            k = phi_zone(x, y, z, phi_edges, phi_kind)
            if j >= n_theta or k < 0 or k >= n_phi:
                continue  # outside the angular range: the ray never enters the region
            shell = locate(distances[row], rho_edges, rho_kind)  # -1: gap, n_rho: beyond
            column = j * n_phi + k
            hit = is_hit[row] and 0 <= shell < n_rho
            free = min(shell, n_rho) if hit else min(shell + 1, n_rho)
            if free > free_extent[thread, column]:
                free_extent[thread, column] = free
            if hit:
                hit_flags[thread, (shell * n_theta + j) * n_phi + k] = 1


def _apply_radial(log_odds, free_extent, hit_flags, n_theta, n_phi, log_hit, log_miss, log_min,
                  log_max):
    """``_apply_flags`` for the radial case: cell (i, j, k) is free if i is below a
    thread's free extent of its column. Loops over shells and columns (no division)."""
    threads = free_extent.shape[0]
    n_columns = n_theta * n_phi
    for shell in prange(log_odds.shape[0] // n_columns):
        for column in range(n_columns):
            cell = shell * n_columns + column
            hit = False
            free = False
            for thread in range(threads):
                hit = hit or hit_flags[thread, cell] != 0
                free = free or shell < free_extent[thread, column]
            _update(log_odds, cell, hit, free, log_hit, log_miss, log_min, log_max)


mark_radial = jit(_mark_radial, parallel=True)
apply_radial = jit(_apply_radial, parallel=True)
