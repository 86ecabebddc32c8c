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

import math

import numpy as np
from numba import prange

from .._jit import jit
from .locate import (
    CONE_BLOCK,
    TWO_PI,
    azimuth,
    locate_in,
    per_log_of,
    phi_zone_near,
    phi_zone_rough,
    theta_zone_rough,
)
from .ordered import advance, buffer_of, chain, post, rows_of, take

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
# A direction lies on a cone, as far as rounding of a = d_y^2 - tan^2 d_h^2
# can tell, when |a| is at most this share of d_y^2 + tan^2 d_h^2
# (``_cone_times``).
PARALLEL = 16.0 * EPSILON
# An origin nearer the centre than this share of rho_max is traced from the
# centre itself (``ray_start``): everything it meets on its way out of that
# neighbourhood is a sliver, and below about 1e-154 the squares that tell
# where its line passes underflow.
AT_CENTRE = 1e-20


@jit(inline="always")
def _sphere_time(t_closest, h2, radius2, outward):
    """Crossing of a sphere on the inward or outward half of the line (Eq. 9a, corrected)."""
    half_chord = math.sqrt(max(radius2 - h2, 0.0))
    if outward:
        return t_closest + half_chord
    return t_closest - half_chord


@jit
def _plane_time(eye_x, eye_z, dx, dz, edge_sin, edge_cos):
    """Crossing of the vertical plane holding the half-plane theta = edge (Eq. 9c),
    on the clock of the eye (``eye_x``, ``eye_z``) the line was given by.

    Measured from the eye, not from the closest point ``c``: the eye's x and z
    are inputs, so the numerator is rounded by eps |o_h|, its distance from
    the y axis, where ``c`` is itself rounded by eps |o|. Over a denominator
    near 0 (a line nearly in the plane) the difference is the trace's: an eye
    1.2e-16 from the axis at |o| = 2, on a half-plane and looking across the
    axis within that plane, crossed its own half-plane at t = 0.04 by ``c``,
    holding back the sweep past the axis, and at 1e-15 by the eye.
    """
    return -(eye_x * edge_cos - eye_z * edge_sin) / (dx * edge_cos - dz * edge_sin)


@jit(inline="always")
def _other_half_now(t_candidate, t_run, eye_x, eye_z, dx, dz, edge_sin, edge_cos, slack):
    """A half-plane's crossing ``t_candidate``, or ``t_run`` (now) where the line meets
    the half-plane's plane on the other half, beyond the y axis.

    A sweep counts the half-planes between its start zone and its limit's,
    and its line meets each one's plane once. Where that is on the other
    half, the half-plane itself lies within rounding of the sweep's start:
    the lookup put the start across an edge that the stored edge, rounded
    off the true angle (-pi/2 is 6.1e-17 rad off), leaves on the near side.
    A source on the half-plane looking along it across the y axis, 4e-17
    rad off it, meets the other half beyond the axis: a crossing there would
    hold every crossing after it back. Within the products' rounding of the
    axis the half is not told. A crossing scenes in the past is one at
    infinity (``_at_infinity``), left to the sweep's end.
    """
    along_eye = eye_x * edge_sin + eye_z * edge_cos
    along = t_candidate * (dx * edge_sin + dz * edge_cos)
    # A line parallel to the plane meets it at infinity (``t_candidate`` inf),
    # on the half its direction points along.
    beyond = along_eye + along < -4.0 * EPSILON * (abs(along_eye) + abs(along))
    other = beyond | (along == -np.inf)
    return t_run if other and t_candidate > t_run - 1e9 * slack else t_candidate


@jit
def _clamp(t_candidate, t_run, t_high):
    """Keep a counted crossing inside its branch: no earlier than the latest
    before it, at most ``t_high``.

    ``t_run`` is the latest candidate so far, or the branch's start (a
    running maximum: clamping each crossing to the one kept before it is
    clamping it to the latest before it). Returns the new ``t_run`` and the
    crossing kept. A crossing a hair before the one kept before it is a
    simultaneous one rounded the other way: it happens now. So is a NaN.
    Only ``t_run``, one ``maxsd``, carries from one crossing to the next.
    The compares are strict so that they are exactly ``maxsd`` and
    ``minsd`` (a NaN candidate keeps ``t_run`` either way). With ``>=`` and
    ``<=`` an equal candidate would be kept instead, which differs only for
    0.0 against -0.0, but LLVM must honour it: it compiled a compare and a
    masked move, a longer chain.
    """
    t_run = t_candidate if t_candidate > t_run else t_run  # also NaN -> now
    return t_run, (t_run if t_run < t_high else t_high)


@jit
def _at_infinity(t_candidate, t_low, slack):
    """Whether a branch's last crossing, ``t_candidate``, is one at infinity.

    ``t_low`` is the crossing kept before it (or the branch's start). A
    crossing clearly in the past (by more than ``slack``) is one of two
    things. A crossing at infinity: the branch end was looked up exactly on
    a boundary the ray only approaches (a limit direction on a half-plane or
    cone), and the closed form divides by ~0, landing ~1e16 scenes away; it
    happens at the branch end, i.e. never for the last branch. Or a
    simultaneous one that rounding of a lookup, magnified by a ray nearly
    parallel to the boundary, put up to about a scene before ``t_low`` (an
    origin on a half-plane, left at 1e-14 rad, or a sensor on the y axis
    restarted at the gap's exit): ``_clamp`` makes it happen now.
    Crossings are counted in order, so only the last of a branch can be at
    infinity, and the loops test it once, after the branch: tested on every
    crossing, it costs the trace a few per cent (``python -m bench.ab``).
    """
    return t_candidate < t_low - 1e9 * slack  # slack is 1e-9 of the scene


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


@jit(inline="always")
def theta_times(eye_x, eye_z, dx, dz, t_start, jt, jt_limit, th_sigma, th_steps, t_axis,
                theta_sin, theta_cos, theta_full, t_final, slack, times, zones):
    """Phase 2 for theta: the crossing times and zones entered, in order, from
    ``t_start`` up to ``t_final``, into ``times[THETA, 1:]`` and ``zones[THETA, 1:]``;
    returns their number. ``eye_x``, ``eye_z``: the clock's origin (``_plane_time``)."""
    n_theta = theta_sin.shape[0] - 1
    n_zones_theta = n_theta if theta_full else n_theta + 1
    n_t = 0
    if t_axis <= t_final:
        times[THETA, 1] = t_axis
        zones[THETA, 1] = jt_limit
        n_t = 1
    zone = jt
    t_run = t_start
    t_low = t_start
    t_candidate = t_start
    for step in range(th_steps):
        edge = _theta_edge_ahead(zone, th_sigma, n_theta, theta_full)
        t_candidate = _plane_time(eye_x, eye_z, dx, dz, theta_sin[edge], theta_cos[edge])
        if step == 0:
            # Only the sweep's first half-plane can lie within rounding of its start.
            t_candidate = _other_half_now(t_candidate, t_run, eye_x, eye_z, dx, dz,
                                          theta_sin[edge], theta_cos[edge], slack)
        t_low = t_run
        t_run, _ = _clamp(t_candidate, t_run, np.inf)
        if t_run > t_final:
            return n_t
        zone += th_sigma
        if zone == n_zones_theta:
            zone = 0
        elif zone < 0:
            zone = n_zones_theta - 1
        times[THETA, n_t + 1] = t_run
        zones[THETA, n_t + 1] = zone
        n_t += 1
    if th_steps > 0 and _at_infinity(t_candidate, t_low, slack):
        # The last crossing is at infinity: it happens at the sweep's end,
        # which is at infinity too, so past t_final unless that is infinite.
        if np.inf > t_final:
            return n_t - 1
        times[THETA, n_t] = np.inf
    return n_t


@jit(inline="always")
def _cone_times(low, count, phi_tan2, phi_nappe, row, first, t_closest, cy, dy, cab, ca2, b2,
                first_branch, branch_start, slack):
    """Crossings of the elevation cones ``low`` .. ``low + count - 1``, each on its own
    nappe and within the current branch, into ``row[first:first + count]``
    (a padding cone, of ``tan2`` and ``nappe`` 0, gives any number).

    ``(c_y + u d_y)^2 = tan(phi)^2 ((c_x + u d_x)^2 + (c_z + u d_z)^2)``, with
    ``u = t - t_closest`` measured from the line's closest point ``c``, solved
    with the cancellation-free quadratic formula (a ray parallel to a
    generatrix has ``a ~ 0``); ``cab``, ``ca2``, ``b2`` are the x-z dot
    products C.B, |C|^2, |B|^2 of C = (c_x, c_z) and the direction B.
    Written about ``c`` rather than the origin, the coefficients keep their
    accuracy when the line passes near the centre: there ``c`` and every
    coefficient are small, where the origin's would be differences of large
    terms (rounding ``c`` by eps |o| moved crossings by sqrt(eps) |o|).
    On its own nappe, a cone a branch counts is met once on each side of
    phi's turning point, at most: before it the earlier root is the crossing,
    after it the later one.
    - Before the turning point the earlier root is taken wherever it falls.
      It cannot be behind the start, whose zone lies on the far side of the
      cone, except by rounding, and a root's rounding (a few eps of its terms
      over the quadratic's slope) grows as the line nears a generatrix: an
      eye on a cone, looking 5e-9 rad off it, crosses it at 6.5e-8, which
      the rounding of the cone's tan^2 alone puts at -3.5e-8, while the
      eye's lookup has it on the near side. ``_clamp`` makes it now.
    - After the turning point a root before ``branch_start`` can be the other
      branch's. When the direction lies on the cone to within rounding
      (``PARALLEL``), the crossing is then at infinity (``inf``); otherwise
      the later root is behind the start by rounding only, and the crossing
      is now (``earliest``).
    Dropping both roots behind the start would keep the ray in the eye's
    zone for good.

    The cone of phi = 0 (``nappe`` 0) is the plane y = 0. A discriminant
    rounded below zero is taken as zero, a tangency and its double root,
    except when the direction lies on the cone
    (``a`` ~ 0, its sign rounding): then with the closest point at the
    centre's height (``half_b`` ~ 0 too) the line only approaches the cone,
    at infinity, where the double root would put a crossing at the closest point.
    On the nappe the direction points into, that is ahead (``inf``); on the
    other, behind the ray, whose start the plan saw across it only by
    rounding: the crossing is then now (``earliest``).

    One loop over the cones in index order, with unit stride, no branches
    and slices that start at zero, so that LLVM vectorises it (four square
    roots or divisions per instruction). On the benchmark machine that took
    a crossing from 13.5 to 9.9 ns, although it also computes those past
    the ray's exit. ``phi_times`` reverses a descending branch in place.
    ``_branch_times`` passes a whole block as ``count`` where the arrays are
    padded for it, so that LLVM's scalar loop for a remainder never runs.
    """
    tan2s = phi_tan2[low:low + count]
    nappes = phi_nappe[low:low + count]
    out = row[first:first + count]
    earliest = branch_start - slack
    plane = t_closest - cy / dy
    for k in range(count):
        tan2 = tan2s[k]
        nappe = nappes[k]
        rise = dy * dy
        spread = tan2 * b2
        a = rise - spread
        half_b = cy * dy - tan2 * cab
        c = cy * cy - tan2 * ca2
        disc = half_b * half_b - a * c
        q = -(half_b + math.copysign(math.sqrt(max(disc, 0.0)), half_b))
        u1 = q / a
        # A tangency's double root is q / a. ``c / q`` is that root only when
        # c = half_b^2 / a exactly, and c cancels when the closest point lies
        # on the cone: over a q of ~0 its rounding puts the root scenes away.
        u2 = c / q if disc > 0.0 else u1
        crossing = _pick_crossing(t_closest + u1, t_closest + u2, cy + u1 * dy, cy + u2 * dy,
                                  nappe, disc, a, rise, spread, dy, first_branch, earliest)
        out[k] = plane if nappe == 0.0 else crossing


@jit(inline="always")
def _pick_crossing(t1, t2, y1, y2, nappe, disc, a, rise, spread, dy, first_branch, earliest):
    """A cone's crossing from its quadratic's roots ``t1``, ``t2``, where the line
    is at heights ``y1``, ``y2`` (see ``_cone_times``)."""
    inf = np.inf
    # No real root and the direction on the cone to within rounding: the
    # line meets the cone at infinity only (see ``_cone_times``).
    steep = abs(a) > PARALLEL * (rise + spread)
    real = (disc >= 0.0) | steep
    # Selects, not branches: ``t < inf`` also rejects NaN, and the nappe
    # test keeps the cone half whose sign of y matches phi.
    ok1 = (t1 < inf) & (nappe * y1 >= 0.0)
    ok2 = (t2 < inf) & (nappe * y2 >= 0.0)
    latest = max(t1 if ok1 else -inf, t2 if ok2 else -inf)
    crossing = (min(t1 if ok1 else inf, t2 if ok2 else inf) if first_branch
                else (latest if latest >= earliest
                      else (earliest if steep & (latest > -inf) else inf)))
    # Met only at infinity: ahead on the nappe the direction points into,
    # else behind, where the ray starts within rounding of it: now.
    return crossing if real else (inf if nappe * dy > 0.0 else earliest)


# A cone flatter than this (tan^2 of its elevation) is timed by
# ``_flat_cone_times``: at most 1e-5 rad from the plane y = 0.
FLAT_TAN2 = 1e-10


@jit(inline="always")
def _flat_cone_times(low, count, phi_tan2, phi_nappe, row, first, t_closest, cx, cy, cz, dx,
                     dy, dz, cab, ca2, b2, first_branch, branch_start, slack):
    """Time again, as ``_cone_times`` does, each cone of ``low`` .. ``low + count - 1``
    within ``FLAT_TAN2`` of the plane y = 0 (but not the plane itself).

    Near the plane the discriminant ``half_b^2 - a c`` is a difference of two
    terms of size (c_y d_y)^2 whose difference, the cone's own term, is
    tan^2 times as small: below tan ~ 1e-8 it was rounding, and with it which
    half of the cone the roots lie on, tested by the height ``c_y + u d_y``,
    a difference of two terms of size c_y. An edge of 1e-9 rad lost the
    crossing of 8 rays in 300 that rose through it, and with it every
    crossing after. Here both are
    written without the cancellation: the discriminant is
    tan^2 |d_y C - c_y B|^2 - tan^4 (C x B)^2 (C = (c_x, c_z), B = (d_x, d_z)),
    and the heights (tan^2 (C.B d_y - c_y |B|^2) - s d_y sqrt(disc)) / a and
    (tan^2 (c_y C.B - |C|^2 d_y) - s c_y sqrt(disc)) / q, with s the sign
    of ``half_b``: the same quantities, exactly, in real arithmetic.
    """
    across_x = dy * cx - cy * dx
    across_z = dy * cz - cy * dz
    wide = across_x * across_x + across_z * across_z
    turn = cx * dz - cz * dx
    rise = dy * dy
    earliest = branch_start - slack
    for k in range(count):
        tan2 = phi_tan2[low + k]
        if not 0.0 < tan2 < FLAT_TAN2:
            continue
        spread = tan2 * b2
        a = rise - spread
        half_b = cy * dy - tan2 * cab
        c = cy * cy - tan2 * ca2
        disc = tan2 * wide - tan2 * tan2 * (turn * turn)
        root = math.copysign(math.sqrt(max(disc, 0.0)), half_b)
        q = -(half_b + root)
        y1 = (tan2 * (cab * dy - cy * b2) - dy * root) / a
        y2 = (tan2 * (cy * cab - ca2 * dy) - cy * root) / q
        u1 = q / a
        u2 = c / q if disc > 0.0 else u1  # a tangency's double root (``_cone_times``)
        y2 = y2 if disc > 0.0 else y1
        row[first + k] = _pick_crossing(t_closest + u1, t_closest + u2, y1, y2,
                                        phi_nappe[low + k], disc, a, rise, spread, dy,
                                        first_branch, earliest)


@jit(inline="always")
def _reverse(row, first, count):
    """Reverse ``row[first:first + count]`` in place."""
    for k in range(count // 2):
        a = row[first + k]
        row[first + k] = row[first + count - 1 - k]
        row[first + count - 1 - k] = a


# ``_branch_times``'s ``first_branch`` and its first ``n_p``: NumPy scalars,
# not literals, so that both calls of each ray share one compiled function (a
# literal argument gets a signature of its own: about 1.3 s more, cold).
FIRST_BRANCH = np.bool_(True)
SECOND_BRANCH = np.bool_(False)
NO_CROSSINGS = np.int64(0)


@jit
def _branch_times(zone, sigma, steps, t_prev, t_high, n_p, first_branch, branch_start, phi_tan2,
                  phi_nappe, lanes, flat_from, flat_to, t_closest, cx, cy, cz, dx, dy, dz, cab,
                  ca2, b2, t_final, slack, times, zones):
    """The ``steps`` cone crossings of one monotone branch of phi, from ``zone`` in
    direction ``sigma``, clamped into ``[t_prev, t_high]``, appended to row
    ``PHI`` after its first ``n_p``; stops at the first past ``t_final``.

    A function of its own, not inlined: each ray calls it twice, and
    inlining both calls cost 3.2 s more to compile ``trace_span``. As a call
    (``python -m bench.ab REV --threads 1`` against the inlined commit), the
    trace took 1.005x and 1.026x in two runs. With its arguments bundled
    into named tuples (the line, the cones) it took 1.040x, so they stay
    apart.

    A branch's crossings past the ray's exit are never used, so
    ``_cone_times`` times the cones ``CONE_BLOCK`` at a time, in the order
    the ray meets them (a descending block is reversed in place). Clamped
    crossings never decrease, so none after the first one past ``t_final``
    is used, and the blocks after it are not computed. Each block computes
    at least ``lanes`` cones (see ``phi_times``). Returns (``n_p``,
    ``t_prev``, ``zone``, whether a crossing past ``t_final`` ended the list).
    """
    row = times[PHI]
    step = 0
    t_run = t_prev
    t_low = t_prev
    t_candidate = t_prev
    while step < steps:
        count = min(CONE_BLOCK, steps - step)
        low = zone + 1 if sigma > 0 else zone - count + 1
        _cone_times(low, max(count, lanes), phi_tan2, phi_nappe, row, n_p + 1, t_closest, cy, dy,
                    cab, ca2, b2, first_branch, branch_start, slack)
        if low < flat_to and flat_from < low + count:  # a cone all but flat in this block
            _flat_cone_times(low, count, phi_tan2, phi_nappe, row, n_p + 1, t_closest, cx, cy,
                             cz, dx, dy, dz, cab, ca2, b2, first_branch, branch_start, slack)
        if sigma < 0:
            _reverse(row, n_p + 1, count)
        for _ in range(count):
            t_candidate = row[n_p + 1]
            t_low = t_prev
            t_run, t_prev = _clamp(t_candidate, t_run, t_high)
            if t_prev > t_final:
                return n_p, t_prev, zone, True
            zone += sigma
            times[PHI, n_p + 1] = t_prev
            zones[PHI, n_p + 1] = zone
            n_p += 1
            step += 1
    if steps > 0 and _at_infinity(t_candidate, t_low, slack):
        # The last crossing is at infinity: it happens at the branch's end.
        t_prev = t_high
        if t_prev > t_final:
            return n_p - 1, t_prev, zone - sigma, True
        times[PHI, n_p] = t_prev
    return n_p, t_prev, zone, False


@jit(inline="always")
def phi_times(cx, cy, cz, dx, dy, dz, t_closest, t_start, kp, kp_limit, t_turn, ph1_steps,
              ph2_start, ph2_steps, ph_jump, grid, t_final, slack, times, zones):
    """Phase 2 for phi: as ``theta_times``, into row ``PHI``; returns their number.

    ``grid``: the grid's ``GridArrays``. Where its cone arrays are padded
    (the CPU's), every block of cones computes all ``CONE_BLOCK`` lanes: one
    vector pass, without the scalar loop LLVM adds for a partial block.
    The number comes from
    the arrays, not the constant: a loop of a fixed 8 LLVM unrolls into
    scalar code. Unpadded (the GPU's), a block times only the cones it needs.
    """
    inf = np.inf
    phi_tan2 = grid.phi_tan2
    phi_nappe = grid.phi_nappe
    lanes = phi_tan2.shape[0] - grid.phi_edges.shape[0] + 1
    b2 = dx * dx + dz * dz
    cab = cx * dx + cz * dz
    ca2 = cx * cx + cz * cz
    n_p, t_prev, zone, done = _branch_times(
        kp, 1 if ph2_start > kp else -1, ph1_steps, t_start, t_turn, NO_CROSSINGS, FIRST_BRANCH,
        t_start, phi_tan2, phi_nappe, lanes, grid.phi_flat_from, grid.phi_flat_to, t_closest, cx,
        cy, cz, dx, dy, dz, cab, ca2, b2, t_final, slack, times, zones,
    )
    if ph_jump == 1:
        _, t_prev = _clamp(t_turn, t_prev, inf)
        if t_prev > t_final:
            done = True
        else:
            zone = ph2_start
            times[PHI, n_p + 1] = t_prev
            zones[PHI, n_p + 1] = zone
            n_p += 1
    if not done:
        n_p, _, _, _ = _branch_times(
            zone, 1 if kp_limit > zone else -1, ph2_steps, t_prev, inf, n_p, SECOND_BRANCH,
            t_turn if t_turn < inf else t_start, phi_tan2, phi_nappe, lanes, grid.phi_flat_from,
            grid.phi_flat_to, t_closest, cx, cy, cz, dx, dy, dz, cab, ca2, b2, t_final, slack,
            times, zones,
        )
    return n_p


@jit(inline="always")
def ray_start(origins, directions, row, rho_edges, rho_kind, per_log):
    """Ray ``row``'s origin and unit direction, its ``line_geometry`` and phase 1 for rho.

    Returns the origin, the direction, ``line_geometry``'s five values, then
    the rho zones at the start, ``ir``, and at the closest approach, ``ir_turn``
    (rho falls until then and rises after, Eq. 9a), and the origin's distance
    from the centre. ``ir_turn == n_rho``: beyond rho_max and moving away,
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
    return ox, oy, oz, dx, dy, dz, t_closest, h2, cx, cy, cz, ir, ir_turn, radius


@jit(inline="always")
def angle_plan(ox, oy, oz, dx, dy, dz, t_closest, h2, cx, cy, cz, grid, lookups):
    """Phase 1 for theta and phi: the zones at the branch ends, so the crossing counts.

    Returns the start theta zone and the direction's, ``theta_plan``'s sweep
    sign, crossing count and ``t_axis``, then the direction's phi zone and
    ``phi_plan``'s six values.
    """
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
    return (jt, jt_limit, th_sigma, th_steps, t_axis, kp_limit, kp, t_turn, ph1_steps, ph2_start,
            ph2_steps, ph_jump)


# ``trace_span``'s ``bounds_only``: trace the rays, or only bound their segments.
# NumPy booleans, not Python's: a literal True or False would compile
# trace_span once more for each (a literal argument gets its own signature).
TRACE = np.bool_(False)
BOUND = np.bool_(True)


@jit(inline="always")
def segments_bound(ir, ir_turn, n_rho, th_steps, t_axis, ph1_steps, ph2_steps, ph_jump):
    """A ray's bound on its segments from its set-up: its crossings, plus one
    for a stop at ``t_max`` (each merge step emits at most one segment)."""
    jumps = (1 if t_axis < np.inf else 0) + ph_jump
    return (ir - ir_turn) + (n_rho - ir_turn) + th_steps + ph1_steps + ph2_steps + jumps + 1


@jit
def ray_bound(origins, directions, row, grid, per_log, lookups):
    """An upper bound on ray ``row``'s segments: its set-up only, no stepping.

    ``segments_bound`` of one ray, for a GPU thread: the GPU's bound kernel
    runs this light function rather than all of ``trace_span`` (the CPU's
    bound pass does the opposite, to compile the set-up once).
    ``per_log`` as in ``ray_start``, ``lookups`` as in ``trace_span``.
    """
    n_rho = grid.rho_edges.shape[0] - 1
    ox, oy, oz, dx, dy, dz, t_closest, h2, cx, cy, cz, ir, ir_turn, _ = ray_start(
        origins, directions, row, grid.rho_edges, grid.rho_kind, per_log)
    if ir_turn == n_rho:
        return 0
    (_, _, _, th_steps, t_axis, _, _, _, ph1_steps, _, ph2_steps,
     ph_jump) = angle_plan(ox, oy, oz, dx, dy, dz, t_closest, h2, cx, cy, cz, grid, lookups)
    return segments_bound(ir, ir_turn, n_rho, th_steps, t_axis, ph1_steps, ph2_steps, ph_jump)


@jit(inline="always")
def _write_segment(cells, t_enter, t_exit, at, ir, jt, kp, t_from, t_to):
    """Write the segment of cell (ir, jt, kp) from ``t_from`` to ``t_to`` at row ``at``."""
    cells[at, 0] = ir
    cells[at, 1] = jt
    cells[at, 2] = kp
    t_enter[at] = t_from
    t_exit[at] = t_to


@jit
def max_segments(n_rho, n_theta, n_phi):
    """Most segments one ray can have: one per crossing (see ``scratch_size``)."""
    return 2 * (n_rho + 1) + (n_theta + 2) + 2 * (n_phi + 1) + 2


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
    inf = np.inf
    # ``flowing`` (below) may start a segment without reading the last one back,
    # except across the seam of a one-sector circle, where the cell stays the same.
    can_flow = not (theta_full and n_theta == 1)
    per_log = per_log_of(rho_edges, rho_kind)
    for row in range(first, last):
        if limit - used < worst:
            return used, row
        ox, oy, oz, dx, dy, dz, t_closest, h2, cx, cy, cz, ir, ir_turn, radius = ray_start(
            origins, directions, row, rho_edges, rho_kind, per_log)
        if ir_turn == n_rho:
            # Beyond rho_max and moving away: never inside.
            offsets[row + 1] = 0 if bounds_only else used
            continue
        (jt, jt_limit, th_sigma, th_steps, t_axis, kp_limit, kp, t_turn, ph1_steps, ph2_start,
         ph2_steps, ph_jump) = angle_plan(ox, oy, oz, dx, dy, dz, t_closest, h2, cx, cy, cz, grid,
                                          lookups)
        if bounds_only:
            offsets[row + 1] = segments_bound(ir, ir_turn, n_rho, th_steps, t_axis, ph1_steps,
                                              ph2_steps, ph_jump)
            continue
        # Rounding of a crossing time is ~1e-14 of the scene's size; a crossing found
        # further in the past than this is one at infinity (see _at_infinity).
        slack = 1e-9 * (rho_edges[n_rho] + radius)
        t_stop = t_max[row]

        # ---- phase 2: each family's crossing times, in order, up to the final exit.
        n_r = 0
        zone = ir
        t_run = 0.0
        for _ in range(ir - ir_turn):
            t_run, t_prev = _clamp(_sphere_time(t_closest, h2, rho_sq[zone], False), t_run, inf)
            zone -= 1
            times[RHO, n_r + 1] = t_prev
            zones[RHO, n_r + 1] = zone
            n_r += 1
        for _ in range(n_rho - ir_turn):
            t_run, t_prev = _clamp(_sphere_time(t_closest, h2, rho_sq[zone + 1], True), t_run,
                                   inf)
            zone += 1
            times[RHO, n_r + 1] = t_prev
            zones[RHO, n_r + 1] = zone
            n_r += 1
        if t_stop < times[RHO, n_r]:
            # Stop at t_max: drop the rho crossings beyond it and leave the region
            # there (zone n_rho), so the merge ends the last segment at t_max.
            while n_r > 0 and times[RHO, n_r] >= t_stop:
                n_r -= 1
            times[RHO, n_r + 1] = t_stop
            zones[RHO, n_r + 1] = n_rho
            n_r += 1
        # The last rho crossing leaves the region for good: nothing after it matters.
        t_final = times[RHO, n_r]

        n_t = theta_times(ox, oz, dx, dz, 0.0, jt, jt_limit, th_sigma, th_steps, t_axis,
                          grid.theta_sin, grid.theta_cos, theta_full, t_final, slack, times,
                          zones)
        n_p = phi_times(cx, cy, cz, dx, dy, dz, t_closest, 0.0, kp, kp_limit, t_turn, ph1_steps,
                        ph2_start, ph2_steps, ph_jump, grid, t_final, slack, times, zones)

        # ---- phase 3: merge the three sorted lists; emit while inside.
        # Crossings that coincide (a corner where a sphere, a half-plane and a cone
        # meet) come out a few ulps apart; the slivers between them (shorter than
        # ``snap``) are cells the ray only touches. They are absorbed into the next
        # segment, which starts where the last one ended, so coverage stays exact.
        snap = 1e-3 * slack
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
                flowing = False
                # The segment written last, read back: it ends at ``last_exit``.
                last_exit = t_exit[used - 1] if used > start else -inf
                touching = t_now - last_exit <= snap
                if t_next - t_now <= snap:
                    if sliver_start < 0.0 and not touching:
                        sliver_start = t_now
                else:
                    if touching:
                        t_from = last_exit
                    elif sliver_start >= 0.0:
                        t_from = sliver_start
                    else:
                        t_from = t_now
                    sliver_start = -1.0
                    if (touching and ir == cells[used - 1, 0] and jt == cells[used - 1, 1]
                            and kp == cells[used - 1, 2]):
                        # The same cell on both sides of a sliver or a zero-length detour
                        # (tangency, the seam of a one-sector circle): extend, don't repeat.
                        t_exit[used - 1] = t_next
                    else:
                        _write_segment(cells, t_enter, t_exit, used, ir, jt, kp, t_from, t_next)
                        used += 1
                    flowing = can_flow
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
