"""Occupancy kernels (``@jit`` only): integrate a scan, first-occupied probabilities.

Parallel work never shares a write: each thread marks its own row of the
free/hit flag arrays, and a second ``prange`` over cells combines the rows.
"""

import math

import numba
import numpy as np
from numba import prange

from .._jit import jit
from .exact import (
    PHI,
    THETA,
    _sphere_time,
    grid_scratch_size,
    line_geometry,
    phi_plan,
    phi_times,
    theta_plan,
    theta_times,
)
from .locate import (
    BLOCK,
    LOG,
    locate_in,
    log_cells,
    norm3,
    phi_zone,
    rho_zone,
    theta_zone,
)

# Per-thread flag bits of a cell in one scan.
FREE = 1
HIT = 2


@jit(inline="always")
def _in_shell(r2, i, rho_sq):
    """Whether rho^2 = ``r2`` lies in zone ``i`` (-1: the gap; n_rho: beyond)."""
    above = i < 0 or r2 >= rho_sq[i]
    below = i >= rho_sq.shape[0] - 1 or r2 < rho_sq[i + 1]
    return above and below


@jit(inline="always")
def _left_within_snap(t_now, t_next, snap, t_closest, h2, i, rho_sq):
    """Whether the cell in shell ``i`` entered at ``t_now`` is left by ``t_now + snap``
    (a sliver the exact trace absorbs): the stretch ends or the shell changes."""
    if t_next - t_now <= snap:
        return True
    return not _in_shell((t_now + snap - t_closest) ** 2 + h2, i, rho_sq)


@jit
def walk_ray(ox, oy, oz, dx, dy, dz, t_max, is_hit, ir, jt, kp, grid, times, zones, lookups,
             free):
    """Flag the cells one sensor ray (unit direction) crosses up to ``t_max`` in
    ``free`` (indexed column-major, see ``apply_scan``); return the index of its
    end cell when it is a hit that ends inside the region, else -1.

    The angular families are planned and timed by the exact kernel's phases 1
    and 2 (``theta_plan`` ... ``phi_times``). Between two angular crossings the
    ray stays in one (theta, phi) column and rho is monotone on each side of
    the closest approach, so the shells it passes are found by comparing
    rho^2 = (t - t_c)^2 + h^2 at the crossing with the squared edges: no
    sphere crossing times and no merge, as only the cells matter here.

    The cells are those of the exact trace: a cell is flagged when the ray
    leaves it, and only if it stayed longer than the trace's ``snap``. A cell
    entered or left at an angular crossing is tested by probing rho^2 ``snap``
    after (or before) the crossing; one entered and left through spheres is a
    whole shell, a sliver only when it is the dip at the closest approach
    (its chord is known). A ray through or near the y axis or the centre
    sweeps many columns within ~h there: those slivers are not flagged.
    ``ir``, ``jt``, ``kp``: the origin's zones, shared by the scan; ``grid``:
    the grid's ``GridArrays``.
    """
    rho_sq = grid.rho_sq
    theta_edges = grid.theta_edges
    theta_kind = grid.theta_kind
    theta_full = grid.theta_full
    phi_edges = grid.phi_edges
    phi_kind = grid.phi_kind
    n_rho = rho_sq.shape[0] - 1
    n_theta = theta_edges.shape[0] - 1
    n_phi = phi_edges.shape[0] - 1
    # The exact kernel's tolerances, from the sensor's own position.
    slack = 1e-9 * (math.sqrt(rho_sq[n_rho]) + math.sqrt(ox * ox + oy * oy + oz * oz))
    snap = 1e-3 * slack
    i = ir
    # The trace's own line geometry and stop, for the end of the ray (below).
    t_closest0, h2_0, _, _, _ = line_geometry(ox, oy, oz, dx, dy, dz)
    t_max0 = t_max
    if ir == -1:
        # In the egocentric gap: start where the ray leaves it, on the inner
        # sphere. Near the centre a ray sweeps through many angular zones (from
        # the origin's direction to its own) that hold no cell.
        t_in = t_closest0 + math.sqrt(max(rho_sq[0] - h2_0, 0.0))
        if t_in >= t_max:
            return -1  # ends in the gap
        ox += t_in * dx
        oy += t_in * dy
        oz += t_in * dz
        t_max -= t_in
        i = 0
        jt = theta_zone(ox, oz, theta_edges, theta_kind)
        kp = phi_zone(ox, oy, oz, phi_edges, phi_kind)
    t_closest, h2, cx, cy, cz = line_geometry(ox, oy, oz, dx, dy, dz)
    if h2 >= rho_sq[n_rho]:
        return -1  # the line misses the outer sphere (or only touches it)
    t_leave = t_closest + math.sqrt(rho_sq[n_rho] - h2)
    if t_leave <= 0.0:
        return -1  # beyond rho_max and moving away
    t_final = min(t_max, t_leave)

    jt_limit = theta_zone(dx, dz, theta_edges, theta_kind)
    kp_limit = phi_zone(dx, dy, dz, phi_edges, phi_kind)
    jt, th_sigma, th_steps, t_axis = theta_plan(
        ox, oz, cx, cz, dx, dz, t_closest, jt, jt_limit, theta_edges, theta_full, lookups, False
    )
    kp, t_turn, ph1_steps, ph2_start, ph2_steps, ph_jump = phi_plan(
        ox, oy, oz, cx, cy, cz, dx, dy, dz, h2, t_closest, kp, kp_limit, phi_edges, phi_kind,
        lookups, False,
    )
    n_t = theta_times(cx, cz, dx, dz, t_closest, jt, jt_limit, th_sigma, th_steps, t_axis,
                      grid.theta_sin, grid.theta_cos, theta_full, t_final, slack, times, zones)
    n_p = phi_times(cx, cy, cz, dx, dy, dz, t_closest, kp, kp_limit, t_turn, ph1_steps, ph2_start,
                    ph2_steps, ph_jump, grid.phi_tan2, grid.phi_nappe, t_final, slack, times, zones)
    zones[THETA, 0] = jt
    zones[PHI, 0] = kp
    times[THETA, n_t + 1] = np.inf
    times[PHI, n_p + 1] = np.inf

    column = jt * n_phi + kp
    column_in = jt < n_theta and 0 <= kp < n_phi
    falling = t_closest > 0.0
    done_t = 0
    done_p = 0
    t_now = 0.0  # when the current column was entered
    at_crossing = True  # the current cell was entered at t_now, not through a sphere
    inward = False  # ... or through a sphere inwards (then leaving outwards is the dip)
    # One pass per angular crossing, plus the last stretch to t_final. Each
    # shell walk moves i one way within [-1, n_rho], so n_rho + 1 steps bound it.
    for _ in range(n_t + n_p + 1):
        t_theta = times[THETA, done_t + 1]
        t_phi = times[PHI, done_p + 1]
        t_next = min(min(t_theta, t_phi), t_final)
        crossed = -1  # the last sphere crossed in this stretch, if any
        crossed_out = False  # ... outwards
        left_flagged = False  # ... and whether the cell it left was flagged
        if falling:
            # Inward until the closest approach (or the next crossing before it).
            r2 = h2 if t_next >= t_closest else (t_next - t_closest) ** 2 + h2
            for _ in range(n_rho + 1):
                if i >= 0 and r2 < rho_sq[i]:
                    # Left through the sphere below: a whole shell, unless it
                    # was entered at the crossing and left within snap.
                    left_flagged = column_in and i < n_rho and not (
                        at_crossing and _left_within_snap(t_now, t_next, snap, t_closest, h2, i,
                                                          rho_sq))
                    if left_flagged:
                        free[column * n_rho + i] = 1
                    crossed = i
                    crossed_out = False
                    i -= 1
                    at_crossing = False
                    inward = True
                else:
                    break
            falling = t_next < t_closest
        if not falling:
            r2 = (t_next - t_closest) ** 2 + h2
            for _ in range(n_rho + 1):
                if i < n_rho and r2 >= rho_sq[i + 1]:
                    if column_in and i >= 0:
                        if at_crossing:
                            sliver = _left_within_snap(t_now, t_next, snap, t_closest, h2, i,
                                                       rho_sq)
                        else:  # a whole shell, or the dip: its chord
                            sliver = inward and 4.0 * (rho_sq[i + 1] - h2) <= snap * snap
                        if not sliver:
                            free[column * n_rho + i] = 1
                    left_flagged = column_in and i >= 0 and not sliver
                    crossed = i + 1
                    crossed_out = True
                    i += 1
                    at_crossing = False
                    inward = False
                else:
                    break
            if i == n_rho and t_next < t_final:
                return -1  # past rho_max and moving away for good
        # The cell is left at t_next: by an angular crossing or the end of the ray.
        cell_in = column_in and 0 <= i < n_rho
        if cell_in:
            if at_crossing:
                stays = t_next - t_now > snap
            else:
                stays = _in_shell((t_next - snap - t_closest) ** 2 + h2, i, rho_sq)
            if stays:
                free[column * n_rho + i] = 1
        if t_next >= t_final:
            if not (is_hit and t_max0 <= _sphere_time(t_closest0, h2_0, rho_sq[n_rho], True)):
                return -1  # no hit, or the ray leaves the region before its end
            # The trace stops at t_max by comparing its sphere crossing times
            # (from the sensor, not the gap's exit) with it, which rho^2 at
            # t_max only approximates: on a sphere, follow the times. A sphere
            # the trace does not cross before t_max leaves it in the cell
            # before; one it does cross starts a sliver, which ends the trace
            # without a hit.
            if crossed >= 0 and _sphere_time(t_closest0, h2_0, rho_sq[crossed],
                                             crossed_out) >= t_max0:
                before = crossed - 1 if crossed_out else crossed
                if left_flagged and 0 <= before < n_rho:
                    return column * n_rho + before
                return -1
            outward = not falling
            ahead = i + 1 if outward else i
            if 0 <= ahead <= n_rho and _sphere_time(t_closest0, h2_0, rho_sq[ahead],
                                                    outward) < t_max0:
                return -1
            if cell_in and stays:
                return column * n_rho + i
            return -1
        # Flag adds, not a branch on which family crosses (a coin toss per crossing).
        theta_first = t_theta <= t_phi
        done_t += theta_first
        done_p += not theta_first
        column = zones[THETA, done_t] * n_phi + zones[PHI, done_p]
        column_in = zones[THETA, done_t] < n_theta and 0 <= zones[PHI, done_p] < n_phi
        t_now = t_next
        at_crossing = True
        inward = False
    return -1


@jit(inline="always")
def sensor_ray(points, row, ox, oy, oz, max_range):
    """Ray ``row`` of a scan from (ox, oy, oz): its unit direction, its length cut
    at ``max_range`` and whether it ends in a hit; a zero length (a point at
    the sensor) is no ray. The direction is the offset over its ``norm3``, as
    ``trace_many`` normalises it."""
    x = points[row, 0] - ox
    y = points[row, 1] - oy
    z = points[row, 2] - oz
    length = norm3(x, y, z)
    if length == 0.0:
        return 0.0, 0.0, 0.0, 0.0, False, False
    return x / length, y / length, z / length, min(length, max_range), length <= max_range, True


@jit(parallel=True)
def mark_scan(origin, points, max_range, grid, free, hits):
    """Walk the ray from ``origin`` to every point of a scan (see ``walk_ray``).

    ``max_range``: rays are cut there and end in no hit (``inf``: none).
    ``grid`` is the grid's ``GridArrays``. ``free`` (threads, n_cells) uint8
    has one row per thread, so no two threads write the same place;
    ``hits[row]`` gets ray ``row``'s hit cell (column-major index) or -1.
    """
    n_rays = points.shape[0]
    ox = origin[0]
    oy = origin[1]
    oz = origin[2]
    ir = rho_zone(ox, oy, oz, grid.rho_edges, grid.rho_kind)
    jt = theta_zone(ox, oz, grid.theta_edges, grid.theta_kind)
    kp = phi_zone(ox, oy, oz, grid.phi_edges, grid.phi_kind)
    size = grid_scratch_size(grid)
    for block in prange((n_rays + BLOCK - 1) // BLOCK):
        row_free = free[numba.get_thread_id()]
        times = np.empty((3, size), dtype=np.float64)
        zones = np.empty((3, size), dtype=np.int64)
        lookups = np.empty(8, dtype=np.int64)
        for row in range(block * BLOCK, min(n_rays, (block + 1) * BLOCK)):
            dx, dy, dz, distance, is_hit, is_ray = sensor_ray(points, row, ox, oy, oz, max_range)
            hits[row] = -1
            if is_ray:
                hits[row] = walk_ray(ox, oy, oz, dx, dy, dz, distance, is_hit, ir, jt, kp, grid,
                                      times, zones, lookups, row_free)


@jit
def _update(log_odds, cell, hit, free, log_hit, log_miss, log_min, log_max):
    """OctoMap's update of one cell: a hit wins over a miss; clamped.

    Summed in float64 and rounded once to the map's float32, whatever the
    caller's promotion rules (numpy 2 would add a Python float to a float32
    scalar in float32).
    """
    if hit:
        log_odds[cell] = min(np.float64(log_odds[cell]) + log_hit, log_max)
    elif free:
        log_odds[cell] = max(np.float64(log_odds[cell]) + log_miss, log_min)


@jit(parallel=True)
def apply_scan(log_odds, free, words, hits, n_rho, log_hit, log_miss, log_min, log_max):
    """OctoMap's update, once per cell per scan: a hit wins over a miss; clamped.

    ``free`` is indexed column-major, ``(j * n_phi + k) * n_rho + i``, so that
    a ray's run of shells in one column is one cache line rather than a page
    apart each (the map is ``(i * n_theta + j) * n_phi + k``). The walk only
    stores to it: a load-test-store per cell to list the cells it met cost
    more than this pass. ``words`` is ``free`` seen as uint64 (rows padded to
    a multiple of 8 bytes): most of a scan's cells are untouched, and eight
    at a time are skipped with one test.
    """
    for ray in range(hits.shape[0]):
        if hits[ray] >= 0:
            free[0, hits[ray]] |= HIT
    threads = free.shape[0]
    n_cells = log_odds.shape[0]
    n_columns = n_cells // n_rho
    for word in prange(words.shape[1]):
        any_bits = words[0, word]
        for thread in range(1, threads):
            any_bits |= words[thread, word]
        if any_bits == 0:
            continue
        for index in range(word * 8, min(word * 8 + 8, n_cells)):
            bits = 0
            for thread in range(threads):
                bits |= free[thread, index]
            if bits != 0:
                i = index % n_rho
                _update(log_odds, i * n_columns + index // n_rho, (bits & HIT) != 0,
                        (bits & FREE) != 0, log_hit, log_miss, log_min, log_max)




@jit(inline="always")
def radial_ray(points, row, max_range, rho_edges, rho_kind, per_log, theta_edges, theta_kind,
               phi_edges, phi_kind):
    """Ray ``row`` of a scan from the grid's origin (see ``mark_radial``): its
    column (``j * n_phi + k``, or -1 when it misses the region), how many
    shells from the centre it frees, and its hit cell's map index or -1."""
    n_rho = rho_edges.shape[0] - 1
    n_theta = theta_edges.shape[0] - 1
    n_phi = phi_edges.shape[0] - 1
    x, y, z, distance, is_hit, is_ray = sensor_ray(points, row, 0.0, 0.0, 0.0, max_range)
    if not is_ray:
        return -1, 0, -1
    j = theta_zone(x, z, theta_edges, theta_kind)
    k = phi_zone(x, y, z, phi_edges, phi_kind)
    if j >= n_theta or k < 0 or k >= n_phi:
        return -1, 0, -1  # outside the angular range: the ray never enters the region
    shell = locate_in(distance, rho_edges, rho_kind, per_log)  # -1: gap, n_rho: beyond
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
def mark_radial(points, max_range, grid, free_extent, hits):
    """The sensor at the grid's origin: every ray is radial, so its cells are one
    (theta, phi) column, free up to the shell holding its end point.

    The column is that of the unit direction (``sensor_ray``), exactly as
    ``trace_many`` would trace it: a point on a cell's edge may round to
    either side, the direction decides. An end cell the ray enters less than
    the exact trace's ``snap`` before its (cut) length is a
    sliver, neither free nor hit; a ray ending exactly on a sphere ends in
    the cell below it, as the trace (whose crossing time ``sqrt(rho^2)`` is
    ``rho`` itself) stops before crossing. ``free_extent`` (threads, n_theta * n_phi)
    int64 records, per thread and column, how many shells from the centre are
    free; ``hits[row]`` gets the map index of ray ``row``'s hit cell, or -1.
    Three lookups per ray instead of a traversal (``radial_ray``).
    """
    n_rays = points.shape[0]
    rho_edges, rho_kind = grid.rho_edges, grid.rho_kind
    # Log shells' constant logarithm, taken once (it was a third of a ray's time).
    per_log = log_cells(rho_edges) if rho_kind == LOG else 0.0
    for block in prange((n_rays + BLOCK - 1) // BLOCK):
        thread = numba.get_thread_id()
        for row in range(block * BLOCK, min(n_rays, (block + 1) * BLOCK)):
            column, free, hits[row] = radial_ray(
                points, row, max_range, rho_edges, rho_kind, per_log, grid.theta_edges,
                grid.theta_kind, grid.phi_edges, grid.phi_kind)
            if column >= 0 and free > free_extent[thread, column]:
                free_extent[thread, column] = free


@jit(parallel=True)
def apply_radial(log_odds, free_extent, hits, hit_mask, n_theta, n_phi, log_hit, log_miss,
                  log_min, log_max):
    """``apply_scan`` for the radial case: cell (i, j, k) is free if i is below a
    thread's free extent of its column; ``hit_mask`` (n_cells,) uint8, zero,
    marks the hit cells so a hit wins and each is updated once. Only the
    columns' free runs and the hits are visited, not the whole map.
    """
    for ray in range(hits.shape[0]):
        if hits[ray] >= 0:
            hit_mask[hits[ray]] = 1
    threads = free_extent.shape[0]
    n_columns = n_theta * n_phi
    for column in prange(n_columns):
        extent = free_extent[0, column]
        for thread in range(1, threads):
            extent = max(extent, free_extent[thread, column])
        for shell in range(extent):
            cell = shell * n_columns + column
            if hit_mask[cell] == 0:
                _update(log_odds, cell, False, True, log_hit, log_miss, log_min, log_max)
    for ray in range(hits.shape[0]):
        cell = hits[ray]
        if cell >= 0 and hit_mask[cell] != 0:
            _update(log_odds, cell, True, False, log_hit, log_miss, log_min, log_max)
            hit_mask[cell] = 0
