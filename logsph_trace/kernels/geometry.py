"""A ray's set-up for the exact traversal: its line, and each family's plan (phase 1).

Per ray, before any crossing is timed: the line's closest point to the
centre (``line_geometry``), the rho zones at the start and at the closest
approach (``ray_start``), and for theta and phi the zone at each end of
every monotone branch, so the number of crossings of each family
(``theta_plan``, ``phi_plan``, ``angle_plan``). Those counts bound a ray's
segments (``segments_bound``, ``ray_bound``) and size its scratch
(``scratch_size``). The crossings themselves are timed in ``crossings``
and merged in ``exact``.
"""

import math
from typing import NamedTuple

import numpy as np

from .._jit import jit
from .locate import (
    CONE_BLOCK,
    TWO_PI,
    azimuth,
    locate_in,
    phi_zone_near,
    phi_zone_rough,
    theta_zone_rough,
)

# The spacing of float64 at 1 (2^-52).
EPSILON = 2.220446049250313e-16


# Each part of the cross product o x d (unit d) is off by at most about
# eps |o|, so h = |o x d| by ~1.7 eps |o|, and (o x d)_y written with c
# (``theta_plan``'s sweep sign) by ~3.9 eps |o| |d_h| at worst. A line within these
# of the centre or of the y axis passes through it as far as the inputs can
# tell; below them the closest point's direction, and so the sweep's sign,
# are rounding. Squared: h^2 against |o|^2 (``phi_plan``), the sweep sign's
# square against |o|^2 |d_h|^2.
THROUGH_CENTRE_SQ = (4.0 * EPSILON) ** 2
THROUGH_AXIS_SQ = (4.0 * EPSILON) ** 2


# An origin nearer the centre than this share of rho_max is traced from the
# centre itself (``ray_start``): everything it meets on its way out of that
# neighbourhood is a sliver, and below about 1e-154 the squares that tell
# where its line passes underflow.
AT_CENTRE = 1e-20


# Rows of the per-ray scratch: crossing times and the zone entered, per family.
RHO = 0
THETA = 1
PHI = 2


@jit
def scratch_size(n_rho, n_theta, n_phi):
    """Crossings one ray can have in any family (each loop below is bounded by it).

    rho: in and out through every sphere, 2 (n_rho + 1); theta: one sweep of
    fewer than n_theta + 1 zones plus a wrap, or one jump; phi: two monotone
    branches, 2 (n_phi + 1), plus one relocation at the origin. Two more slots:
    slot 0 holds the starting zone, and an ``inf`` sentinel ends each list.
    ``CONE_BLOCK - 1`` more take the lanes of a block of cones past the last
    crossing (``_branch_times``).
    """
    return max(2 * (n_rho + 1) + 1, n_theta + 2, 2 * (n_phi + 1) + 1) + 2 + CONE_BLOCK - 1


@jit
def grid_scratch_size(grid):
    """``scratch_size`` of a grid's ``GridArrays``."""
    return scratch_size(grid.rho_edges.shape[0] - 1, grid.theta_edges.shape[0] - 1,
                        grid.phi_edges.shape[0] - 1)


@jit(inline="always")
def line_geometry(ox, oy, oz, dx, dy, dz):
    """What the families share about the line o + t d (unit d).

    Returns ``t_closest``, the time of closest approach to the centre; ``h2``,
    the squared distance there, from the cross product o x d (exactly 0 for a
    line through the centre), so rho(t)^2 = (t - t_closest)^2 + h2; and the
    closest point itself, ``c = d x (o x d) = o + t_closest d``.

    The angular families are solved about ``c`` (times ``u = t - t_closest``),
    not about the origin. Their singular sets are the centre (phi and theta
    jump there) and the y axis (theta jumps), and near them the quantities
    that decide the plan -- phi's turning point, the sweep of theta, where the
    line meets the axis -- are small differences of large products when
    written with the origin, so rounding of eps |o| could move phi's turning
    point by eps |o|^2 / h, far past the cells it separates. Written with
    ``c`` (of size h) they are accurate to eps relative, and since ``c`` and
    the cross product are computed once, every family plans one and the same
    line, within eps |o| of the given one. Theta's crossing times alone are
    measured from the eye (``_plane_time``): a half-plane's time needs only
    the distance to its plane, which the eye's own coordinates give to
    eps |o_h|, and ``c`` only to eps |o|.
    """
    t_closest = -(ox * dx + oy * dy + oz * dz)
    cross_x = oy * dz - oz * dy
    cross_y = oz * dx - ox * dz
    cross_z = ox * dy - oy * dx
    h2 = cross_x * cross_x + cross_y * cross_y + cross_z * cross_z
    cx = dy * cross_z - dz * cross_y
    cy = dz * cross_x - dx * cross_z
    cz = dx * cross_y - dy * cross_x
    return t_closest, h2, cx, cy, cz


@jit
def _comes_round(ox, oz, dx, dz, zone, sigma, theta_edges, theta_full):
    """Whether a sweep in direction ``sigma`` that starts and ends in azimuthal
    ``zone`` (one wider than half a turn) leaves it and comes round into it again.

    The sweep (less than pi) must cover the gap to the edge ahead and then the
    rest of the turn, outside the zone. Anything less is rounding of a start
    or limit on an edge, which puts them in one zone while the sweep leaves
    it. A sweep of pi or more is a sweep of ~0 against ``sigma``, rounded (the
    start's azimuth within an ulp of the limit's, ``sigma`` from a sweep sign
    of ~0), or one of pi past the y axis: the ray turns there at once, and
    leaves the zone for a sliver at most. Not inlined: most rays never ask,
    and its two ``atan2`` calls would crowd the plan's code.
    """
    n_theta = theta_edges.shape[0] - 1
    edge = _theta_edge_ahead(zone, sigma, n_theta, theta_full)
    theta_start = azimuth(ox, oz)
    theta_limit = azimuth(dx, dz)
    sweep = ((theta_limit - theta_start) * sigma) % TWO_PI
    gap = ((theta_edges[edge] - theta_start) * sigma) % TWO_PI
    span = theta_edges[n_theta] - theta_edges[0]
    width = theta_edges[zone + 1] - theta_edges[zone] if zone < n_theta else TWO_PI - span
    return gap + (TWO_PI - width) < sweep < math.pi


@jit
def _eye_sweep(eye_x, eye_z, dx, dz):
    """``(o x d)_y = o_z d_x - o_x d_z`` from the eye, and whether the line meets
    the y axis to within its rounding, its two products' few ulps."""
    across = eye_z * dx - eye_x * dz
    return across, abs(across) <= 4.0 * EPSILON * (abs(eye_z * dx) + abs(eye_x * dz))


@jit(inline="always")
def theta_plan(ox, oz, cx, cz, dx, dz, h2, t_closest, t_start, eye_x, eye_z, jt, jt_limit,
               theta_edges, theta_full):
    """Phase 1 for theta: one monotone sweep, or a jump where the line meets the y axis.

    ``c`` is the line's closest point to the centre, ``h2`` its squared
    distance and ``t_closest`` its time (``line_geometry``), which sets the
    clock of every time here: the clock's origin lies ``t_closest^2 + h2``
    from the centre, squared. The ray starts at time ``t_start`` (0 for a
    trace), at the point whose x and z
    are ``ox``, ``oz``; ``jt`` and ``jt_limit`` are the zones of that point
    and of the direction (the limit as t -> inf). ``eye_x``, ``eye_z``: the
    clock's origin (the eye or sensor the line was given by). On the y axis
    the line meets the axis there, at t = 0, and every point after it has the
    direction's azimuth (written with ``c``, the sweep's sign would be
    rounding, and a line lying in a half-plane would be taken to sweep to it
    and never reach it). Returns the start zone, the sweep sign, the number
    of half-planes crossed and ``t_axis``, the time of the jump (inf when
    none).

    A line within rounding of the y axis meets it: below that the sweep's
    sign is noise, and a line lying in a half-plane's plane, as every line
    through the axis does, has that plane's crossing time 0 / 0. Swept, a
    sensor on a half-plane looking across the axis (or through the centre)
    had crossed its own half-plane at such a time; rounded into the future,
    every crossing after it waited for it, and the ray kept the sensor's
    zone past the axis. Where the sign written with ``c`` is under its
    bound (``THROUGH_AXIS_SQ``, for the worst case), the sign is taken from
    the eye instead, ``(o x d)_y``, whose rounding is that of its own two
    products: an eye near the axis, with a steep direction, tells its side
    to far below ``eps |o|``.
    """
    inf = np.inf
    n_theta = theta_edges.shape[0] - 1
    n_zones_theta = n_theta if theta_full else n_theta + 1
    # (o x d)_y, written with c (= o + t_c d): the sign of the sweep.
    sweep_sign = cz * dx - cx * dz
    b2 = dx * dx + dz * dz
    th_sigma = 0
    th_steps = 0
    t_axis = inf
    through = False
    if sweep_sign * sweep_sign <= THROUGH_AXIS_SQ * (t_closest * t_closest + h2) * b2:
        # The eye tells the side the line passes on, where c cannot (see above).
        sweep_sign, through = _eye_sweep(eye_x, eye_z, dx, dz)
    if dx == 0.0 and dz == 0.0:  # not b2 == 0: b2 underflows for |d_x|, |d_z| < 1e-154
        pass  # parallel to the y axis: theta never changes
    elif eye_x == 0.0 and eye_z == 0.0:
        jt = jt_limit
    elif through:
        # Through the y axis, exactly or to within rounding of the inputs.
        meets_axis = t_closest - (cx * dx + cz * dz) / b2
        if meets_axis > t_start:
            if jt != jt_limit:
                t_axis = meets_axis
        else:
            jt = jt_limit
    else:
        th_sigma = 1 if sweep_sign > 0.0 else -1
        th_steps = ((jt_limit - jt) * th_sigma) % n_zones_theta
        if th_steps == 0 and _comes_round(ox, oz, dx, dz, jt, th_sigma, theta_edges, theta_full):
            th_steps = n_zones_theta
    return jt, th_sigma, th_steps, t_axis


@jit(inline="always")
def phi_plan(ox, oy, oz, cx, cy, cz, dx, dy, dz, h2, t_closest, t_start, kp, kp_limit, grid,
             lookups):
    """Phase 1 for phi: up to two monotone branches split at the turning point,
    or piecewise constant with a jump at the centre.

    The clock and the start as in ``theta_plan`` (the start point is ``o``);
    ``kp`` and ``kp_limit`` are the zones of that point and of the direction;
    ``c`` is the line's closest point to the centre. Along c + u d, tan(phi)
    has a derivative whose numerator is ``slope * u + offset``, so phi turns
    at ``u = -offset / slope``; with c perpendicular to d these are ``-c_y``
    and ``d_y h^2``, sums of like-signed terms below, accurate however close
    the line comes to the centre. Returns the start zone, ``t_turn`` (end of
    the first branch, inf when none), the crossings on each branch, the zone
    the second branch starts in, and 1 when phi jumps at ``t_turn``. The zone
    at the turning point is kept in ``lookups[7]``, the next ray's guess there.
    """
    inf = np.inf
    b2 = dx * dx + dz * dz
    cab = cx * dx + cz * dz
    ca2 = cx * cx + cz * cz
    slope = dy * cab - cy * b2
    offset = dy * ca2 - cy * cab
    t_turn = inf
    ph1_steps = 0
    ph2_start = kp
    ph2_steps = 0
    # Through the centre to within rounding of the cross product o x d
    # (``THROUGH_CENTRE_SQ``): then the closest point c, of size h, points
    # anywhere, and so does the plane the line turns in. A line through the
    # centre lies on the cone of its elevation, and the time it crosses that
    # cone is 0 / 0: had it rounded into the future, every crossing after it
    # would have waited for it, and phi kept the start's zone past the
    # centre. So such a line jumps there.
    through = h2 <= THROUGH_CENTRE_SQ * (t_closest * t_closest + h2)
    if through or (slope == 0.0 and offset == 0.0):
        # Through the centre, or a line of constant phi: no turning point.
        if ox == 0.0 and oy == 0.0 and oz == 0.0:
            kp = kp_limit
            ph2_start = kp_limit
        elif t_closest > t_start and through and kp != kp_limit:
            t_turn = t_closest
            ph2_start = kp_limit
    else:
        turn = -offset / slope if slope != 0.0 else inf
        if t_start - t_closest < turn < inf:
            t_turn = t_closest + turn
            # lookups[7] holds the ray before's zone there: a guess.
            ph2_start = phi_zone_near(cx + turn * dx, cy + turn * dy, cz + turn * dz, lookups[7],
                                      grid)
            lookups[7] = ph2_start
            ph1_steps = abs(ph2_start - kp)
        ph2_steps = abs(kp_limit - ph2_start)
    # Only through the centre does the first branch end in another zone than
    # the second starts in: phi jumps between opposite directions there.
    ph_jump = 1 if ph1_steps == 0 and ph2_start != kp else 0
    return kp, t_turn, ph1_steps, ph2_start, ph2_steps, ph_jump


class Ray(NamedTuple):
    """A ray's set-up (``ray_start``): its origin and unit direction, the line's
    closest point to the centre (``line_geometry``), its rho zones at the start
    and at the closest approach, and the origin's distance from the centre."""

    ox: float
    oy: float
    oz: float
    dx: float
    dy: float
    dz: float
    t_closest: float
    h2: float
    cx: float
    cy: float
    cz: float
    ir: int
    ir_turn: int
    radius: float


class AnglePlan(NamedTuple):
    """Phase 1 for theta and phi (``angle_plan``): the start theta zone and the
    direction's, ``theta_plan``'s sweep sign, crossing count and ``t_axis``,
    then the direction's phi zone and ``phi_plan``'s six values."""

    jt: int
    jt_limit: int
    th_sigma: int
    th_steps: int
    t_axis: float
    kp_limit: int
    kp: int
    t_turn: float
    ph1_steps: int
    ph2_start: int
    ph2_steps: int
    ph_jump: int


@jit(inline="always")
def ray_start(origins, directions, row, rho_edges, rho_kind, per_log):
    """Ray ``row``'s origin and unit direction, its ``line_geometry`` and phase 1 for rho.

    Returns a ``Ray``: the origin, the direction, ``line_geometry``'s five
    values, then the rho zones at the start, ``ir``, and at the closest
    approach, ``ir_turn`` (rho falls until then and rises after, Eq. 9a),
    and the origin's distance from the centre. ``ir_turn == n_rho``: beyond rho_max and moving away,
    never inside. ``per_log``: ``per_log_of(rho_edges, rho_kind)``, a constant
    of the grid (a logarithm, so a caller with many rays takes it once). An
    origin within ``AT_CENTRE`` rho_max of the centre is the centre.
    """
    ox = origins[row, 0]
    oy = origins[row, 1]
    oz = origins[row, 2]
    dx = directions[row, 0]
    dy = directions[row, 1]
    dz = directions[row, 2]
    t_closest, h2, cx, cy, cz = line_geometry(ox, oy, oz, dx, dy, dz)
    radius = math.sqrt(ox * ox + oy * oy + oz * oz)
    if radius < AT_CENTRE * rho_edges[rho_edges.shape[0] - 1]:
        # At the centre (``AT_CENTRE``). Taken after the common case's set-up,
        # not before it: waiting on the square root cost 2% (``bench.ab``).
        ox, oy, oz, radius = 0.0, 0.0, 0.0, 0.0
        t_closest, h2, cx, cy, cz = line_geometry(ox, oy, oz, dx, dy, dz)
    ir = locate_in(radius, rho_edges, rho_kind, per_log)
    ir_turn = ir
    if t_closest > 0.0:
        ir_turn = min(locate_in(math.sqrt(h2), rho_edges, rho_kind, per_log), ir)
    return Ray(ox, oy, oz, dx, dy, dz, t_closest, h2, cx, cy, cz, ir, ir_turn, radius)


@jit(inline="always")
def angle_plan(ray, grid, lookups):
    """Phase 1 for theta and phi of a ``Ray``: the zones at the branch ends, so the
    crossing counts; an ``AnglePlan``.
    """
    ox, oy, oz, dx, dy, dz, t_closest, h2, cx, cy, cz = ray[:11]
    theta_edges = grid.theta_edges
    jt = theta_zone_rough(ox, oz, theta_edges, grid.theta_sin, grid.theta_cos, grid.theta_kind)
    jt_limit = theta_zone_rough(dx, dz, theta_edges, grid.theta_sin, grid.theta_cos,
                                grid.theta_kind)
    jt, th_sigma, th_steps, t_axis = theta_plan(
        ox, oz, cx, cz, dx, dz, h2, t_closest, 0.0, ox, oz, jt, jt_limit, theta_edges,
        grid.theta_full,
    )
    phi_edges = grid.phi_edges
    kp_limit = phi_zone_rough(dx, dy, dz, phi_edges, grid.phi_sin, grid.phi_cos, grid.phi_kind)
    kp = phi_zone_rough(ox, oy, oz, phi_edges, grid.phi_sin, grid.phi_cos, grid.phi_kind)
    kp, t_turn, ph1_steps, ph2_start, ph2_steps, ph_jump = phi_plan(
        ox, oy, oz, cx, cy, cz, dx, dy, dz, h2, t_closest, 0.0, kp, kp_limit, grid, lookups,
    )
    return AnglePlan(jt, jt_limit, th_sigma, th_steps, t_axis, kp_limit, kp, t_turn, ph1_steps,
                     ph2_start, ph2_steps, ph_jump)


@jit(inline="always")
def segments_bound(ray, plan, n_rho):
    """A ray's bound on its segments from its set-up (``Ray``, ``AnglePlan``): its
    crossings, plus one for a stop at ``t_max`` (each merge step emits at most one
    segment)."""
    jumps = (1 if plan.t_axis < np.inf else 0) + plan.ph_jump
    return ((ray.ir - ray.ir_turn) + (n_rho - ray.ir_turn) + plan.th_steps + plan.ph1_steps
            + plan.ph2_steps + jumps + 1)


@jit
def ray_bound(origins, directions, row, grid, per_log, lookups):
    """An upper bound on ray ``row``'s segments: its set-up only, no stepping.

    ``segments_bound`` of one ray, for a GPU thread: the GPU's bound kernel
    runs this light function rather than all of ``trace_span`` (the CPU's
    bound pass does the opposite, to compile the set-up once).
    ``per_log`` as in ``ray_start``, ``lookups`` as in ``trace_span``.
    """
    n_rho = grid.rho_edges.shape[0] - 1
    ray = ray_start(origins, directions, row, grid.rho_edges, grid.rho_kind, per_log)
    if ray.ir_turn == n_rho:
        return 0
    return segments_bound(ray, angle_plan(ray, grid, lookups), n_rho)


@jit
def max_segments(n_rho, n_theta, n_phi):
    """Most segments one ray can have: one per crossing (see ``scratch_size``)."""
    return 2 * (n_rho + 1) + (n_theta + 2) + 2 * (n_phi + 1) + 2


@jit
def _theta_edge_ahead(zone, sigma, n_theta, full):
    """Edge index met when leaving azimuthal ``zone`` in direction ``sigma``.

    On a full circle the seam is the last edge both ways: the lookup wraps an
    azimuth at or above ``theta_edges[-1]`` into zone 0, and ``theta_edges[0]``
    + 2 pi rounds to another plane a few 1e-16 rad away.
    """
    if sigma > 0:
        return zone + 1 if zone < n_theta else 0
    if zone == 0 and full:
        return n_theta
    return zone if zone < n_theta else n_theta
