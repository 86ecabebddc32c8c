"""Exact traversal of a bounded log-spherical grid: boundary stepping.

Amanatides & Woo step a ray from voxel to voxel by keeping, per axis, the
distance to the next boundary.  Here the three families of boundaries are
spheres (rho), azimuthal half-planes (theta) and elevation cones (phi), and the
same holds once one sees that along a line each coordinate is *piecewise
monotone with at most one turning point*:

* rho(t)^2 = (t - t_c)^2 + h^2: falls until the closest approach ``t_c``, then
  rises.
* theta(t) sweeps monotonically (less than half a turn in all), with the sign
  of ``o_z d_x - o_x d_z``; a line through the y axis jumps by pi there.
* tan phi(t) = y / sqrt(x^2 + z^2) has a derivative whose numerator is
  *linear* in t (``p t + q`` below), so phi rises then falls (or the reverse)
  with one turning point ``-q / p``; a line through the origin jumps there.

On each monotone branch the zone at both ends is the one the public ``cell_of``
gives (``theta_zone_rough`` and ``phi_zone_rough``: a cheap guess confirmed
against the edges, or that lookup), so the *number* of crossings of every family is fixed
before stepping.  Crossing *times* come from closed forms (Eq. 9a, 9c and the
exact cone quadratic of docs/geometry.md) and are clamped into the branch, so
rounding can move a crossing by an ulp or two but can never drop one or add
one: the indices cannot drift.

Each family's crossings form a sorted list, computed in a loop of independent
square roots and divisions (the CPU overlaps them); the traversal is then a
three-way merge of the lists, without a branch on which family crosses. Its
common step, a segment that starts where the last one ended, inside the grid,
writes that segment and nothing else; the rare ones (slivers to absorb, a
cell to extend, leaving or entering the grid) read the last segment back.
Every loop runs over a count fixed beforehand, at most ``scratch_size``.
"""

import numpy as np
from numba import prange

from .._jit import jit
from .crossings import phi_times, rho_times, theta_times
from .geometry import (
    PHI,
    RHO,
    THETA,
    angle_plan,
    grid_scratch_size,
    max_segments,
    ray_start,
    segments_bound,
)
from .locate import per_log_of
from .ordered import advance, buffer_of, chain, post, rows_of, take

# ``trace_span``'s ``bounds_only``: trace the rays, or only bound their segments.
# NumPy booleans, not Python's: a literal True or False would compile
# trace_span once more for each (a literal argument gets its own signature).
TRACE = np.bool_(False)
BOUND = np.bool_(True)


@jit(inline="always")
def _write_segment(cells, t_enter, t_exit, at, ir, jt, kp, t_from, t_to):
    """Write the segment of cell (ir, jt, kp) from ``t_from`` to ``t_to`` at row ``at``."""
    cells[at, 0] = ir
    cells[at, 1] = jt
    cells[at, 2] = kp
    t_enter[at] = t_from
    t_exit[at] = t_to


@jit(inline="always")
def _merge(ir, jt, kp, counts, snap, can_flow, grid, times, zones, out, used):
    """Phase 3: merge the three families' sorted crossings; emit a segment while inside.

    The ray starts in zones (``ir``, ``jt``, ``kp``); ``counts`` are the
    crossings of each family (``n_r``, ``n_t``, ``n_p``) in ``times`` and
    ``zones``; ``out`` the segment arrays (cells, t_enter, t_exit), written
    from row ``used`` on. Returns the new ``used``.

    Crossings that coincide (a corner where a sphere, a half-plane and a cone
    meet) come out a few ulps apart; the slivers between them (shorter than
    ``snap``) are cells the ray only touches. They are absorbed into the next
    segment, which starts where the last one ended, so coverage stays exact.
    """
    cells, t_enter, t_exit = out
    n_r, n_t, n_p = counts
    n_rho = grid.rho_edges.shape[0] - 1
    n_theta = grid.theta_edges.shape[0] - 1
    n_phi = grid.phi_edges.shape[0] - 1
    inf = np.inf
    zones[RHO, 0] = ir
    zones[THETA, 0] = jt
    zones[PHI, 0] = kp
    times[RHO, n_r + 1] = inf
    times[THETA, n_t + 1] = inf
    times[PHI, n_p + 1] = inf
    # Crossings consumed so far per family: the current zone is zones[f, done_f]
    # and the next crossing times[f, done_f + 1]. Picking the family is two
    # selects and advancing is a flag add, so the loop has no branch on which
    # family crosses -- the branch Amanatides & Woo mispredict on every voxel.
    done_r = 0
    done_t = 0
    done_p = 0
    t_now = 0.0
    start = used
    sliver_start = -1.0
    # ``flowing``: the last step wrote a segment that ends now, so this one, if
    # inside and no sliver, starts where it ended and is in another cell (a
    # crossing changes its family's zone; see ``can_flow``).
    flowing = False
    for _ in range(n_r + n_t + n_p):
        t_rho = times[RHO, done_r + 1]
        t_theta = times[THETA, done_t + 1]
        t_phi = times[PHI, done_p + 1]
        t_angle = min(t_theta, t_phi)
        t_next = max(min(t_rho, t_angle), t_now)
        ir = zones[RHO, done_r]
        jt = zones[THETA, done_t]
        kp = zones[PHI, done_p]
        inside = 0 <= ir < n_rho and jt < n_theta and 0 <= kp < n_phi
        if flowing and inside and t_next - t_now > snap:
            # The common step, with nothing to absorb or extend.
            _write_segment(cells, t_enter, t_exit, used, ir, jt, kp, t_now, t_next)
            used += 1
        elif inside:
            used, sliver_start, flowing = _rare_step(ir, jt, kp, t_now, t_next, snap, start,
                                                     sliver_start, can_flow, out, used)
        else:
            flowing = False
            sliver_start = -1.0
        t_now = t_next
        # Bitwise ``&`` on booleans, not ``and``: no short-circuit branch.
        rho_first = t_rho <= t_angle
        theta_first = t_theta <= t_phi
        done_r += rho_first
        done_t += (not rho_first) & theta_first
        done_p += (not rho_first) & (not theta_first)
        if done_r == n_r:
            break  # past rho_max and moving away for good
    return used


@jit(inline="always")
def _rare_step(ir, jt, kp, t_now, t_next, snap, start, sliver_start, can_flow, out, used):
    """A step of ``_merge`` inside the grid that is not the common one: a sliver to
    absorb, a cell to extend, or a segment after one. Returns (``used``,
    ``sliver_start``, ``flowing``)."""
    cells, t_enter, t_exit = out
    # The segment written last, read back: it ends at ``last_exit``.
    last_exit = t_exit[used - 1] if used > start else -np.inf
    touching = t_now - last_exit <= snap
    if t_next - t_now <= snap:
        if sliver_start < 0.0 and not touching:
            sliver_start = t_now
        return used, sliver_start, False
    if touching:
        t_from = last_exit
    elif sliver_start >= 0.0:
        t_from = sliver_start
    else:
        t_from = t_now
    if (touching and ir == cells[used - 1, 0] and jt == cells[used - 1, 1]
            and kp == cells[used - 1, 2]):
        # The same cell on both sides of a sliver or a zero-length detour
        # (tangency, the seam of a one-sector circle): extend, don't repeat.
        t_exit[used - 1] = t_next
    else:
        _write_segment(cells, t_enter, t_exit, used, ir, jt, kp, t_from, t_next)
        used += 1
    return used, -1.0, can_flow


@jit
def trace_span(first, last, origins, directions, t_max, grid, times, zones, lookups, bounds_only,
               cells, t_enter, t_exit, offsets, used, limit):
    """One thread: trace rays first..last-1 (unit directions) in order, appending from
    segment ``used`` on; ray ``row`` up to distance ``t_max[row]`` (``inf``: to the end).

    Without threads a ray's final offset is known when it starts (the sum of
    the counts before it), so no bound pass or gather is needed. Writes
    ``offsets[row + 1]`` (absolute positions in the arrays). Stops before a ray
    that might not fit below ``limit`` (``max_segments`` per ray); returns
    (new ``used``, the first row not traced). ``grid`` is the grid's
    ``GridArrays``; ``times`` and ``zones`` are scratch of shape
    (3, scratch_size(...)), ``lookups`` 8 ints that carry guesses from one ray
    to the next.

    ``bounds_only`` (``TRACE`` or ``BOUND``): with ``BOUND``, each ray gets
    only its set-up, and ``offsets[row + 1]`` its bound on its segments
    (``segments_bound``); ``t_max``, the scratch and the segment arrays are
    not read or written, so they may be empty. The bound pass of the
    parallel paths (``trace_chunks``) runs this way, so the set-up is
    compiled once on the CPU, not again in a function of its own.

    Per ray, phases: (1) per family, the zone at each branch end and so the
    number of crossings (``ray_start``, ``angle_plan``); (2) per family, the
    crossing times in order -- independent square roots and divisions the CPU
    can overlap; (3) a three-way merge of the sorted lists, emitting a segment
    whenever the ray is inside. The rays' loop is here, not around a call per
    ray: a call passes every array field by field, and the set-up that does
    not depend on the ray is done once.
    """
    rho_edges = grid.rho_edges
    rho_sq = grid.rho_sq
    rho_kind = grid.rho_kind
    theta_full = grid.theta_full
    n_rho = rho_edges.shape[0] - 1
    n_theta = grid.theta_edges.shape[0] - 1
    n_phi = grid.phi_edges.shape[0] - 1
    worst = max_segments(n_rho, n_theta, n_phi)
    # ``flowing`` (below) may start a segment without reading the last one back,
    # except across the seam of a one-sector circle, where the cell stays the same.
    can_flow = not (theta_full and n_theta == 1)
    per_log = per_log_of(rho_edges, rho_kind)
    for row in range(first, last):
        if limit - used < worst:
            return used, row
        ray = ray_start(origins, directions, row, rho_edges, rho_kind, per_log)
        if ray.ir_turn == n_rho:
            # Beyond rho_max and moving away: never inside.
            offsets[row + 1] = 0 if bounds_only else used
            continue
        plan = angle_plan(ray, grid, lookups)
        if bounds_only:
            offsets[row + 1] = segments_bound(ray, plan, n_rho)
            continue
        ox, oy, oz, dx, dy, dz, t_closest, h2, cx, cy, cz, ir, ir_turn, radius = ray
        (jt, jt_limit, th_sigma, th_steps, t_axis, kp_limit, kp, t_turn, ph1_steps, ph2_start,
         ph2_steps, ph_jump) = plan
        # Rounding of a crossing time is ~1e-14 of the scene's size; a crossing found
        # further in the past than this is one at infinity (see _at_infinity).
        slack = 1e-9 * (rho_edges[n_rho] + radius)

        # ---- phase 2: each family's crossing times, in order, up to the final exit.
        n_r = rho_times(ir, ir_turn, n_rho, t_closest, h2, rho_sq, t_max[row], times, zones)
        # The last rho crossing leaves the region for good: nothing after it matters.
        t_final = times[RHO, n_r]

        n_t = theta_times(ray, plan, 0.0, grid, t_final, slack, times, zones)
        n_p = phi_times(ray, plan, 0.0, grid, t_final, slack, times, zones)

        # ---- phase 3: merge the three sorted lists; emit while inside.
        used = _merge(ir, jt, kp, (n_r, n_t, n_p), 1e-3 * slack, can_flow, grid, times, zones,
                      (cells, t_enter, t_exit), used)
        offsets[row + 1] = used
    return used, last


# The parallel batch kernels. One thread never needs them: it traces by
# appending (``trace_span``). Each ray writes only its own slice or region, so
# the output does not depend on the number of threads.
@jit(parallel=True)
def trace_chunks(starts, regions, origins, directions, t_max, grid, cells, t_enter, t_exit,
                 offsets, bounds_only):
    """Chunk c traces rays starts[c]..starts[c+1]-1 into its region, from regions[c] on.

    The regions must be sized by the rays' bounds: no ray writes past its
    bound, so none is checked. Returns per chunk the end of its segments;
    ``offsets[row + 1]`` gets the end of ray ``row``'s segments (positions in
    the regions). With ``bounds_only`` (``BOUND``) the same loop is the
    bound pass: ``offsets[row + 1]`` gets ray ``row``'s bound on its
    segments (``trace_span``), and nothing else is written -- one parallel
    kernel to compile for both passes, not two.
    """
    n_chunks = starts.shape[0] - 1
    size = grid_scratch_size(grid)
    ends = np.empty(n_chunks, dtype=np.int64)
    no_limit = np.iinfo(np.int64).max
    for chunk in prange(n_chunks):
        times = np.empty((3, size), dtype=np.float64)
        zones = np.empty((3, size), dtype=np.int64)
        lookups = np.empty(8, dtype=np.int64)
        ends[chunk], _ = trace_span(
            starts[chunk], starts[chunk + 1], origins, directions, t_max, grid, times, zones,
            lookups, bounds_only, cells, t_enter, t_exit, offsets, regions[chunk], no_limit,
        )
    return ends


@jit(parallel=True)
def trace_ordered(first_row, last_row, chunk_rays, workers, origins, directions, t_max, grid,
                  loose_cells, loose_enter, loose_exit, cells, t_enter, t_exit, offsets, used,
                  fresh_end, block_rows):
    """Rows ``first_row..last_row-1``, in chunks of ``chunk_rays``, taken in order by
    ``workers`` threads and placed in the output from segment ``used`` on
    (``kernels.ordered``).

    Worker w traces into rows ``(2 w + side) * room`` of the scratch arrays,
    ``room = chunk_rays * max_segments`` (two buffers per worker), so a chunk
    always fits. ``offsets[first_row]`` must be ``used``; every placed ray
    gets ``offsets[row + 1]``. Output rows ``used..fresh_end-1`` are fresh
    memory, faulted in by the workers ahead of the chunks, ``block_rows``
    rows at a time (``fresh_end`` at most ``used``: none is). Returns per
    chunk the first row not placed (the chunk's end when it was): a chunk
    that would end past the output and the chunks after it are not placed.
    """
    size = grid_scratch_size(grid)
    room = chunk_rays * max_segments(grid.rho_edges.shape[0] - 1, grid.theta_edges.shape[0] - 1,
                                     grid.phi_edges.shape[0] - 1)
    n_chunks, counts, starts, reached, counter, fresh = chain(first_row, last_row, chunk_rays,
                                                              used, fresh_end, block_rows)
    for worker in prange(workers):
        times = np.empty((3, size), dtype=np.float64)
        zones = np.empty((3, size), dtype=np.int64)
        lookups = np.empty(8, dtype=np.int64)
        waiting = -1  # the chunk in the other buffer, traced and not yet placed
        side = 0
        chunk = take(counter, n_chunks)
        while chunk >= 0 or waiting >= 0:
            if chunk >= 0:
                first, last = rows_of(chunk, first_row, chunk_rays, last_row)
                source = buffer_of(worker, side, room)
                end, _ = trace_span(first, last, origins, directions, t_max, grid, times, zones,
                                    lookups, TRACE, loose_cells, loose_enter, loose_exit, offsets,
                                    source, source + room)
                post(chunk, end - source, counts, starts)
            waiting, side, chunk = advance(
                chunk, waiting, worker, side, room, first_row, last_row, chunk_rays, workers,
                counter, counts, starts, reached, fresh, loose_cells, loose_enter, loose_exit,
                cells, t_enter, t_exit, offsets,
            )
    return reached
