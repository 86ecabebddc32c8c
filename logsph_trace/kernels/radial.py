"""A scan from the grid's origin: every ray radial, three lookups instead of a walk.

From the centre a ray's cells are one (theta, phi) column, free up to the
shell of its end point: ``mark_radial`` raises each column's free extent
(an atomic maximum, the same on any number of threads) and records each
ray's hit cell; ``apply_radial`` updates the free runs and the hits.
"""

import numpy as np
from numba import prange

from .._jit import jit
from .atomic import exchange, load_relaxed, raise_to, store_relaxed
from .locate import BLOCK, locate_in, per_log_of, phi_zone_near, theta_zone_near
from .ordered import in_turn, take
from .update import _update
from .walk import sensor_ray


@jit(inline="always")
def radial_ray(points, row, max_range, grid, per_log, guesses):
    """Ray ``row`` of a scan from the grid's origin (see ``mark_radial``): its
    column (``j * n_phi + k``, or -1 when it misses the region), how many
    shells from the centre it frees, and its hit cell's map index or -1.

    ``guesses``: the (theta, phi, rho) zones of the ray before, tried first
    (``theta_zone_near``); they are updated to this ray's.
    """
    rho_edges = grid.rho_edges
    n_rho = rho_edges.shape[0] - 1
    n_theta = grid.theta_edges.shape[0] - 1
    n_phi = grid.phi_edges.shape[0] - 1
    x, y, z, distance, is_hit, is_ray = sensor_ray(points, row, 0.0, 0.0, 0.0, max_range)
    if not is_ray:
        return -1, 0, -1
    j = theta_zone_near(x, z, guesses[0], grid)
    k = phi_zone_near(x, y, z, guesses[1], grid)
    guesses[0] = j
    guesses[1] = k
    if j >= n_theta or k < 0 or k >= n_phi:
        return -1, 0, -1  # outside the angular range: the ray never enters the region
    shell = guesses[2]  # -1: gap, n_rho: beyond
    if not (0 <= shell < n_rho and rho_edges[shell] <= distance < rho_edges[shell + 1]):
        shell = locate_in(distance, rho_edges, grid.rho_kind, per_log)
        guesses[2] = shell
    if 0 <= shell < n_rho and distance == rho_edges[shell]:
        # The ray stops on the sphere below its shell, which the trace
        # only crosses before t_max: it ends in the cell below.
        shell -= 1
        hit = is_hit and shell >= 0
        free = shell if hit else shell + 1
    elif 0 <= shell < n_rho and distance - rho_edges[shell] <= 1e-12 * rho_edges[n_rho]:
        shell -= 1  # the end cell is a sliver (shorter than the trace's snap): no hit
        hit = False
        free = shell + 1
    else:
        hit = is_hit and 0 <= shell < n_rho
        free = min(shell, n_rho) if hit else min(shell + 1, n_rho)
    return j * n_phi + k, free, (shell * n_theta + j) * n_phi + k if hit else -1


@jit(parallel=True)
def mark_radial(points, max_range, grid, free_extent, hits, workers):
    """The sensor at the grid's origin: every ray is radial, so its cells are one
    (theta, phi) column, free up to the shell holding its end point.

    The column is that of the unit direction (``sensor_ray``), exactly as
    ``trace_many`` would trace it: a point on a cell's edge may round to
    either side, the direction decides. An end cell the ray enters less than
    the exact trace's ``snap`` before its (cut) length is a
    sliver, neither free nor hit; a ray ending exactly on a sphere ends in
    the cell below it, as the trace (whose crossing time ``sqrt(rho^2)`` is
    ``rho`` itself) stops before crossing. ``free_extent`` (n_theta *
    n_phi,) int64 gets, per column, how many shells from the centre are
    free: raised by all threads (``raise_to``; a maximum, so the same on any
    number of them), once per run of rays in one column, since neighbouring
    pixels mostly share it. ``workers`` (a worker per thread) take blocks of
    rays in turn (``in_turn``); ``hits[row]`` gets the map index of ray
    ``row``'s hit cell, or -1. Three lookups per ray instead of a traversal
    (``radial_ray``).
    """
    n_rays = points.shape[0]
    rho_edges, rho_kind = grid.rho_edges, grid.rho_kind
    # Log shells' constant logarithm, taken once (it was a third of a ray's time).
    per_log = per_log_of(rho_edges, rho_kind)
    # Up to 2,048 rays a block: on few threads, longer runs of neighbouring
    # rays (blocks of 256 made the table scan 2-4% slower on 2 threads).
    step, n_blocks, counter = in_turn(n_rays, workers, 8 * BLOCK)
    for worker in prange(workers):
        guesses = np.empty(3, dtype=np.int64)
        _radial_blocks(points, max_range, grid, per_log, free_extent, hits, step, n_blocks,
                       counter, guesses)


@jit
def _radial_blocks(points, max_range, grid, per_log, free_extent, hits, step, n_blocks, counter,
                   guesses):
    """One worker of ``mark_radial``: blocks of ``step`` rays, taken in turn until none is left.

    A function of its own, called by the parallel loop rather than written
    in it: Numba compiles a parallel loop's body twice, and this one took
    1.4 s more to compile inside it. ``guesses``: the worker's scratch of 3.
    """
    n_rays = points.shape[0]
    block = take(counter, n_blocks)
    while block >= 0:
        guesses[:] = -1
        run_column = -1  # the run's column (-1: none) and its largest extent
        run_free = 0
        for row in range(block * step, min(n_rays, (block + 1) * step)):
            column, free, hits[row] = radial_ray(points, row, max_range, grid, per_log,
                                                 guesses)
            if column != run_column:
                if run_column >= 0:
                    raise_to(free_extent, run_column, run_free)
                run_column = column
                run_free = free
            elif free > run_free:
                run_free = free
        if run_column >= 0:
            raise_to(free_extent, run_column, run_free)
        block = take(counter, n_blocks)


@jit(parallel=True)
def apply_radial(log_odds, free_extent, hits, hit_mask, n_theta, n_phi, log_hit, log_miss,
                  log_min, log_max, workers):
    """``apply_scan`` for the radial case: cell (i, j, k) is free if i is below its
    column's free extent (``mark_radial``); ``hit_mask`` (n_cells,) uint8,
    zero, marks the hit cells so a hit wins and each is updated once. Only
    the columns' free runs and the hits are visited, not the whole map.

    All three passes run on all threads; the columns, whose free runs lie
    together where the scan looks, in blocks that the ``workers`` take in
    turn (``in_turn``). Rays that end in one cell store the same mark
    (``atomic.store_relaxed``); in the last pass exactly one of them takes it
    back (``atomic.exchange``) and updates the cell, so the map does not
    depend on the thread count. ``free_extent`` and ``hit_mask`` are left
    zero, ready for the next scan.
    """
    n_rays = hits.shape[0]
    n_blocks = (n_rays + BLOCK - 1) // BLOCK
    n_cells = log_odds.shape[0]
    for block in prange(n_blocks):
        for ray in range(block * BLOCK, min(n_rays, (block + 1) * BLOCK)):
            if 0 <= hits[ray] < n_cells:  # -1: no hit (the bound: no store outside the map)
                store_relaxed(hit_mask, hits[ray], 1)
    n_columns = n_theta * n_phi
    step, n_column_blocks, counter = in_turn(n_columns, workers, BLOCK)
    for worker in prange(workers):  # the columns in view lie together: blocks in turn
        column_block = take(counter, n_column_blocks)
        while column_block >= 0:
            for column in range(column_block * step, min(n_columns, (column_block + 1) * step)):
                extent = free_extent[column]
                if extent > 0:
                    free_extent[column] = 0
                for shell in range(extent):
                    cell = shell * n_columns + column
                    if hit_mask[cell] == 0:
                        _update(log_odds, cell, False, True, log_hit, log_miss, log_min,
                                log_max)
            column_block = take(counter, n_column_blocks)
    for block in prange(n_blocks):
        for ray in range(block * BLOCK, min(n_rays, (block + 1) * BLOCK)):
            cell = hits[ray]
            # The load skips the locked exchange for a cell already taken.
            if (0 <= cell < n_cells and load_relaxed(hit_mask, cell) != 0
                    and exchange(hit_mask, cell, 0) != 0):
                _update(log_odds, cell, True, False, log_hit, log_miss, log_min, log_max)
