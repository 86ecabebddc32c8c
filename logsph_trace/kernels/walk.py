"""One sensor ray walked through the grid for the occupancy update.

``walk_ray`` follows the exact traversal's crossings (``crossings``) from
the sensor to the ray's end point and flags the cells it crosses free
(``FREE``) and the cell it ends in hit (``HIT``), in one array of bytes
that all threads share: a walk only ever stores ``FREE`` there, so threads
that store to one cell store the same byte, with relaxed atomic stores
(``atomic.store_relaxed``: a defined result). ``sensor_ray`` reads a ray
from a scan's points. The coherent scan (``coherent``) walks only some of
a scan's rays; the radial case (``radial``) none.
"""

import math

import numpy as np

from .._jit import jit
from .atomic import store_relaxed
from .crossings import _sphere_time, phi_times, theta_times
from .geometry import PHI, THETA, AnglePlan, Ray, line_geometry, phi_plan, theta_plan
from .locate import _last_at_or_below, norm3, phi_zone_near, theta_zone_near

# A cell's flag in one scan: a ray crossed it, or ended in it (the hit
# replaces the byte: it wins over a miss).
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


@jit(inline="always")
def _near_either_edge(a, b, sines, cosines, low, high, within):
    """Whether the point (a, b) of a half-plane through the axis lies within
    ``within`` of the line at angle ``low`` or ``high`` (their ``sines`` and
    ``cosines``): ``|a cos - b sin|``, its distance from each."""
    return (abs(a * cosines[low] - b * sines[low]) <= within
            or abs(a * cosines[high] - b * sines[high]) <= within)


@jit(inline="always")
def _near_theta_face(x, z, zone, within, grid):
    """Whether (x, ., z) lies within ``within`` of a half-plane's plane bounding
    azimuthal ``zone`` (``n_theta``: the rest of the turn of a partial range),
    where a lookup and a trace may round to different sides."""
    n = grid.theta_sin.shape[0] - 1
    return _near_either_edge(x, z, grid.theta_sin, grid.theta_cos, zone if zone < n else n,
                             zone + 1 if zone < n else 0, within)


@jit(inline="always")
def _near_phi_face(x, y, z, zone, within, grid):
    """Whether (x, y, z) lies within ``within`` of a cone bounding elevation
    ``zone`` (-1, ``n_phi``: below and above a partial range); see
    ``_near_theta_face``."""
    n = grid.phi_sin.shape[0] - 1
    return _near_either_edge(y, math.sqrt(x * x + z * z), grid.phi_sin, grid.phi_cos,
                             max(zone, 0), min(zone + 1, n), within)


@jit(inline="always")
def _leave_gap(t_max, t_closest, h2, skip, rho_sq):
    """Where a walk from the egocentric gap starts: (time, shell).

    Where the ray leaves the gap, on the inner sphere (near the centre a ray
    sweeps through many angular zones, from the origin's direction to its
    own, that hold no cell); with ``skip`` (see ``walk_ray``), on the last
    sphere up to ``skip`` crossed before the end. A time at or past
    ``t_max``: the ray ends in the gap.
    """
    t_start = t_closest + math.sqrt(max(rho_sq[0] - h2, 0.0))
    if t_start >= t_max or skip <= 0:
        return t_start, 0
    # Outside the gap rho only grows, so each sphere is crossed once.
    i = min(skip, _last_at_or_below((t_max - t_closest) ** 2 + h2, rho_sq))
    before_end = t_max * (1.0 - 1e-9)
    while i > 0:
        t_sphere = _sphere_time(t_closest, h2, rho_sq[i], True)
        if t_sphere < before_end:
            return t_sphere, i
        i -= 1
    return t_start, 0


@jit(inline="always")
def _shells_in(i, t_now, t_next, at_crossing, inward, base, line, rho_sq, free):
    """The spheres a falling stretch of ``walk_ray`` crosses inwards, up to ``t_next``.

    ``base``: the column's first flag (``column * n_rho``), or -1 outside the
    region's angles; ``line``: (t_closest, h2, snap). Each shell left through
    the sphere below is flagged, unless it was entered at the crossing and
    left within snap. Returns (shell, the last sphere crossed or -1, whether
    the cell it left was flagged, ``at_crossing``, ``inward``).
    """
    t_closest, h2, snap = line
    n_rho = rho_sq.shape[0] - 1
    r2 = h2 if t_next >= t_closest else (t_next - t_closest) ** 2 + h2
    crossed = -1
    left_flagged = False
    for _ in range(n_rho + 1):
        if not (i >= 0 and r2 < rho_sq[i]):
            break
        left_flagged = base >= 0 and i < n_rho and not (
            at_crossing and _left_within_snap(t_now, t_next, snap, t_closest, h2, i, rho_sq))
        if left_flagged:
            store_relaxed(free, base + i, FREE)
        crossed = i
        i -= 1
        at_crossing = False
        inward = True
    return i, crossed, left_flagged, at_crossing, inward


@jit(inline="always")
def _shells_out(i, t_now, t_next, at_crossing, inward, base, line, rho_sq, free, last):
    """The spheres a rising stretch of ``walk_ray`` crosses outwards, up to ``t_next``.

    As ``_shells_in``; a shell entered through a sphere is a whole shell, or
    the dip at the closest approach when entered inwards (a sliver when its
    chord is within snap). ``last``: (crossed, crossed_out, left_flagged) so
    far in the stretch, kept when no sphere is crossed here. Returns (shell,
    crossed, crossed_out, left_flagged, ``at_crossing``, ``inward``).
    """
    t_closest, h2, snap = line
    n_rho = rho_sq.shape[0] - 1
    crossed, crossed_out, left_flagged = last
    r2 = (t_next - t_closest) ** 2 + h2
    for _ in range(n_rho + 1):
        if not (i < n_rho and r2 >= rho_sq[i + 1]):
            break
        sliver = False
        if base >= 0 and i >= 0:
            if at_crossing:
                sliver = _left_within_snap(t_now, t_next, snap, t_closest, h2, i, rho_sq)
            else:  # a whole shell, or the dip: its chord
                sliver = inward and 4.0 * (rho_sq[i + 1] - h2) <= snap * snap
            if not sliver:
                store_relaxed(free, base + i, FREE)
        left_flagged = base >= 0 and i >= 0 and not sliver
        crossed = i + 1
        crossed_out = True
        i += 1
        at_crossing = False
        inward = False
    return i, crossed, crossed_out, left_flagged, at_crossing, inward


@jit(inline="always")
def _hit_cell(t_max, i, outward, flagged, column, last, line, rho_sq):
    """The map index of a hit ray's end cell, or -1 (the end of ``walk_ray``).

    ``i``: the shell at the end; ``flagged``: whether that cell stays inside
    the region and was flagged; ``last``: (crossed, crossed_out,
    left_flagged) of the last stretch; ``line``: (t_closest, h2).
    """
    t_closest, h2 = line
    n_rho = rho_sq.shape[0] - 1
    crossed, crossed_out, left_flagged = last
    if not t_max <= _sphere_time(t_closest, h2, rho_sq[n_rho], True):
        return -1  # the ray leaves the region before its end
    # The trace stops at t_max by comparing its sphere crossing times with
    # it, which rho^2 at t_max only approximates: on a sphere, follow the
    # times. A sphere the trace does not cross before t_max leaves it in the
    # cell before; one it does cross starts a sliver, which ends the trace
    # without a hit.
    if crossed >= 0 and _sphere_time(t_closest, h2, rho_sq[crossed], crossed_out) >= t_max:
        before = crossed - 1 if crossed_out else crossed
        if left_flagged and 0 <= before < n_rho:
            return column * n_rho + before
        return -1
    ahead = i + 1 if outward else i
    if 0 <= ahead <= n_rho and _sphere_time(t_closest, h2, rho_sq[ahead], outward) < t_max:
        return -1
    if flagged:
        return column * n_rho + i
    return -1


@jit(inline="always")
def _angle_crossings(sensor, direction, start, t_start, start_zones, sensor_zones, line, limits,
                     grid, scratch):
    """Plan and time the angular families of ``walk_ray`` from its start point.

    Each family is planned from the start point, unless that point lies
    within rounding of a face of its zone (``sensor_zones``: whether the
    walk starts from the gap, and the sensor's zones): there a lookup may round
    the other way from the trace, which reaches the point by its crossings
    from the sensor (a line through or within ~1e-16 of the centre whose
    direction lies on a cone, or one through the y axis on a half-plane).
    Such a family is planned from the sensor, as the trace plans it, and the
    walk starts after its crossings up to ``t_start``. ``line``: (t_closest,
    h2, cx, cy, cz); ``limits``: (t_final, slack, snap); ``scratch``:
    (times, zones, lookups). Returns the crossings of theta and phi and how
    many of each lie before the start; the zones entered are in ``zones``.
    """
    ox, oy, oz = sensor
    dx, dy, dz = direction
    sx, sy, sz = start
    jt, kp = start_zones
    from_gap, jt_sensor, kp_sensor = sensor_zones
    t_closest, h2, cx, cy, cz = line
    t_final, slack, snap = limits
    times, zones, lookups = scratch
    jt_limit = theta_zone_near(dx, dz, lookups[2], grid)
    kp_limit = phi_zone_near(dx, dy, dz, lookups[3], grid)
    lookups[2] = jt_limit
    lookups[3] = kp_limit
    theta_from_sensor = from_gap and _near_theta_face(sx, sz, jt, snap, grid)
    phi_from_sensor = from_gap and _near_phi_face(sx, sy, sz, kp, snap, grid)
    t_theta = 0.0 if theta_from_sensor else t_start
    t_phi = 0.0 if phi_from_sensor else t_start
    jt, th_sigma, th_steps, t_axis = theta_plan(
        ox if theta_from_sensor else sx, oz if theta_from_sensor else sz, cx, cz, dx, dz, h2,
        t_closest, t_theta, ox, oz, jt_sensor if theta_from_sensor else jt, jt_limit,
        grid.theta_edges, grid.theta_full,
    )
    kp, t_turn, ph1_steps, ph2_start, ph2_steps, ph_jump = phi_plan(
        ox if phi_from_sensor else sx, oy if phi_from_sensor else sy,
        oz if phi_from_sensor else sz, cx, cy, cz, dx, dy, dz, h2, t_closest, t_phi,
        kp_sensor if phi_from_sensor else kp, kp_limit, grid, lookups,
    )
    ray = Ray(ox, oy, oz, dx, dy, dz, t_closest, h2, cx, cy, cz, -1, -1, 0.0)
    plan = AnglePlan(jt, jt_limit, th_sigma, th_steps, t_axis, kp_limit, kp, t_turn, ph1_steps,
                     ph2_start, ph2_steps, ph_jump)
    n_t = theta_times(ray, plan, t_theta, grid, t_final, slack, times, zones)
    n_p = phi_times(ray, plan, t_phi, grid, t_final, slack, times, zones)
    zones[THETA, 0] = jt
    zones[PHI, 0] = kp
    times[THETA, n_t + 1] = np.inf
    times[PHI, n_p + 1] = np.inf
    # Crossings before the start (a plan from the sensor has some: the trace
    # crosses them in the gap, or below the start sphere, where they bound no
    # cell of the walk's).
    done_t = 0
    done_p = 0
    while t_theta < t_start and times[THETA, done_t + 1] <= t_start:
        done_t += 1
    while t_phi < t_start and times[PHI, done_p + 1] <= t_start:
        done_p += 1
    return n_t, n_p, done_t, done_p


@jit
def walk_ray(ox, oy, oz, dx, dy, dz, t_max, is_hit, ir, jt, kp, grid, times, zones, lookups,
             free, skip):
    """Flag the cells one sensor ray (unit direction) crosses up to ``t_max`` in
    ``free`` (indexed column-major, see ``apply_scan``; ``FREE``, stored
    relaxed, since other rays may flag the same cell at once); return the
    index of its end cell when it is a hit that ends inside the region, else
    -1.

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
    the grid's ``GridArrays``. ``skip``: for a ray from the egocentric gap,
    the shell whose inner sphere the walk may start on (0: where the ray
    leaves the gap), when the cells below it are known to be flagged by
    other rays (``occupancy._mark_off_centre``); a ray that ends before it
    (or within 1e-9 of it) starts on the last sphere it crosses before.
    Wherever the walk starts, its times are the trace's, from the sensor,
    and where its start point lies within ``snap`` of a face of its zone, a
    family is planned from the sensor too (see the comment at the plans).
    """
    rho_sq = grid.rho_sq
    theta_edges = grid.theta_edges
    phi_edges = grid.phi_edges
    n_rho = rho_sq.shape[0] - 1
    n_theta = theta_edges.shape[0] - 1
    n_phi = phi_edges.shape[0] - 1
    # The exact kernel's tolerances, from the sensor's own position.
    slack = 1e-9 * (math.sqrt(rho_sq[n_rho]) + math.sqrt(ox * ox + oy * oy + oz * oz))
    snap = 1e-3 * slack
    i = ir
    jt_sensor = jt
    kp_sensor = kp
    # Every time is on the trace's clock, from the sensor: a crossing is then
    # the very number the trace computes (the same closed form of the same
    # line), so a ray ending on a face ends where the trace ends it.
    t_closest, h2, cx, cy, cz = line_geometry(ox, oy, oz, dx, dy, dz)
    t_start = 0.0  # where the walk starts: (sx, sy, sz)
    sx = ox
    sy = oy
    sz = oz
    if ir == -1:
        t_start, i = _leave_gap(t_max, t_closest, h2, skip, rho_sq)
        if t_start >= t_max:
            return -1  # ends in the gap
        sx += t_start * dx
        sy += t_start * dy
        sz += t_start * dz
        # The zones of the last ray walked with these ``lookups`` are guesses.
        jt = theta_zone_near(sx, sz, lookups[0], grid)
        kp = phi_zone_near(sx, sy, sz, lookups[1], grid)
        lookups[0] = jt
        lookups[1] = kp
    if h2 >= rho_sq[n_rho]:
        return -1  # the line misses the outer sphere (or only touches it)
    t_leave = t_closest + math.sqrt(rho_sq[n_rho] - h2)
    if t_leave <= t_start:
        return -1  # beyond rho_max and moving away
    t_final = min(t_max, t_leave)

    n_t, n_p, done_t, done_p = _angle_crossings(
        (ox, oy, oz), (dx, dy, dz), (sx, sy, sz), t_start, (jt, kp),
        (ir == -1, jt_sensor, kp_sensor), (t_closest, h2, cx, cy, cz),
        (t_final, slack, snap), grid, (times, zones, lookups))
    jt = zones[THETA, done_t]
    kp = zones[PHI, done_p]

    column = jt * n_phi + kp
    column_in = jt < n_theta and 0 <= kp < n_phi
    falling = t_closest > t_start
    t_now = t_start  # when the current column was entered
    at_crossing = True  # the current cell was entered at t_now, not through a sphere
    inward = False  # ... or through a sphere inwards (then leaving outwards is the dip)
    # One pass per angular crossing, plus the last stretch to t_final. Each
    # shell walk moves i one way within [-1, n_rho], so n_rho + 1 steps bound it.
    for _ in range(n_t + n_p + 1):
        t_theta = times[THETA, done_t + 1]
        t_phi = times[PHI, done_p + 1]
        t_next = min(min(t_theta, t_phi), t_final)
        # The spheres crossed in this stretch: the last one (or -1), whether
        # outwards, and whether the cell it left was flagged.
        crossed, crossed_out, left_flagged = -1, False, False
        line = (t_closest, h2, snap)
        if falling:
            # Inward until the closest approach (or the next crossing before it).
            i, crossed, left_flagged, at_crossing, inward = _shells_in(
                i, t_now, t_next, at_crossing, inward, column * n_rho if column_in else -1,
                line, rho_sq, free)
            falling = t_next < t_closest
        if not falling:
            i, crossed, crossed_out, left_flagged, at_crossing, inward = _shells_out(
                i, t_now, t_next, at_crossing, inward, column * n_rho if column_in else -1,
                line, rho_sq, free, (crossed, crossed_out, left_flagged))
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
                store_relaxed(free, column * n_rho + i, FREE)
        if t_next >= t_final:
            if not is_hit:
                return -1
            return _hit_cell(t_max, i, not falling, cell_in and stays, column,
                             (crossed, crossed_out, left_flagged), (t_closest, h2), rho_sq)
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
    length, distance, is_hit = _ray_length(points, row, ox, oy, oz, max_range)
    if length == 0.0:
        return 0.0, 0.0, 0.0, 0.0, False, False
    dx, dy, dz = _direction(points, row, ox, oy, oz, length)
    return dx, dy, dz, distance, is_hit, True


@jit(inline="always")
def _ray_length(points, row, ox, oy, oz, max_range):
    """Ray ``row``'s offset length (0: no ray), that length cut at ``max_range``,
    and whether the ray ends in a hit (``sensor_ray``)."""
    length = norm3(points[row, 0] - ox, points[row, 1] - oy, points[row, 2] - oz)
    return length, min(length, max_range), length <= max_range


@jit(inline="always")
def _direction(points, row, ox, oy, oz, length):
    """The unit direction of ray ``row`` of ``sensor_ray``, its offset's ``length`` given."""
    return ((points[row, 0] - ox) / length, (points[row, 1] - oy) / length,
            (points[row, 2] - oz) / length)
