"""Each family's crossing times along a ray, in order (phase 2 of the exact traversal).

Spheres (``_sphere_time``, Eq. 9a), azimuthal half-planes
(``theta_times``) and elevation cones (``phi_times``, the exact cone
quadratic of docs/geometry.md), each clamped into its monotone branch
(``_clamp``) so that rounding can move a crossing by an ulp or two but can
never drop one or add one. ``exact.trace_span`` merges the three lists.
"""

import math

import numpy as np

from .._jit import jit
from .geometry import EPSILON, PHI, RHO, THETA, _theta_edge_ahead
from .locate import CONE_BLOCK

# A direction lies on a cone, as far as rounding of a = d_y^2 - tan^2 d_h^2
# can tell, when |a| is at most this share of d_y^2 + tan^2 d_h^2
# (``_cone_times``).
PARALLEL = 16.0 * EPSILON


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


@jit(inline="always")
def rho_times(ir, ir_turn, n_rho, t_closest, h2, rho_sq, t_stop, times, zones):
    """Phase 2 for rho: the sphere crossings and zones entered, in order, into
    ``times[RHO, 1:]`` and ``zones[RHO, 1:]``; returns their number.

    From zone ``ir`` in to ``ir_turn`` (the closest approach), then out to
    ``n_rho``. A stop at ``t_stop`` before the last drops the crossings
    beyond it and leaves the region there (zone ``n_rho``), so the merge
    ends the last segment at ``t_stop``.
    """
    inf = np.inf
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
        t_run, t_prev = _clamp(_sphere_time(t_closest, h2, rho_sq[zone + 1], True), t_run, inf)
        zone += 1
        times[RHO, n_r + 1] = t_prev
        zones[RHO, n_r + 1] = zone
        n_r += 1
    if t_stop < times[RHO, n_r]:
        while n_r > 0 and times[RHO, n_r] >= t_stop:
            n_r -= 1
        times[RHO, n_r + 1] = t_stop
        zones[RHO, n_r + 1] = n_rho
        n_r += 1
    return n_r


@jit(inline="always")
def theta_times(ray, plan, t_start, grid, t_final, slack, times, zones):
    """Phase 2 for theta: the crossing times and zones entered, in order, from
    ``t_start`` up to ``t_final``, into ``times[THETA, 1:]`` and ``zones[THETA, 1:]``;
    returns their number. ``ray``: a ``geometry.Ray`` (its origin is the clock's,
    ``_plane_time``); ``plan``: a ``geometry.AnglePlan``."""
    eye_x, eye_z, dx, dz = ray.ox, ray.oz, ray.dx, ray.dz
    jt, jt_limit, th_sigma, th_steps, t_axis = plan[:5]
    theta_sin, theta_cos, theta_full = grid.theta_sin, grid.theta_cos, grid.theta_full
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
def _cone_times(low, count, cones, row, first, line, branch):
    """Crossings of the elevation cones ``low`` .. ``low + count - 1``, each on its own
    nappe and within the current branch, into ``row[first:first + count]``
    (a padding cone, of ``tan2`` and ``nappe`` 0, gives any number).

    ``cones``: the grid's (``phi_tan2``, ``phi_nappe``); ``line``: (t_closest,
    c_x, c_y, c_z, d_x, d_y, d_z, cab, ca2, b2); ``branch``: (whether it is the
    first branch, its start, the slack); see ``_branch_times``.

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
    phi_tan2, phi_nappe = cones
    t_closest, _, cy, _, _, dy, _, cab, ca2, b2 = line
    first_branch, branch_start, slack = branch
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
def _flat_cone_times(low, count, cones, row, first, line, branch):
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
    phi_tan2, phi_nappe = cones
    t_closest, cx, cy, cz, dx, dy, dz, cab, ca2, b2 = line
    first_branch, branch_start, slack = branch
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
    cones = (phi_tan2, phi_nappe)
    line = (t_closest, cx, cy, cz, dx, dy, dz, cab, ca2, b2)
    branch = (first_branch, branch_start, slack)
    row = times[PHI]
    step = 0
    t_run = t_prev
    t_low = t_prev
    t_candidate = t_prev
    while step < steps:
        count = min(CONE_BLOCK, steps - step)
        low = zone + 1 if sigma > 0 else zone - count + 1
        _cone_times(low, max(count, lanes), cones, row, n_p + 1, line, branch)
        if low < flat_to and flat_from < low + count:  # a cone all but flat in this block
            _flat_cone_times(low, count, cones, row, n_p + 1, line, branch)
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
def phi_times(ray, plan, t_start, grid, t_final, slack, times, zones):
    """Phase 2 for phi: as ``theta_times``, into row ``PHI``; returns their number.

    ``grid``: the grid's ``GridArrays``. Where its cone arrays are padded
    (the CPU's), every block of cones computes all ``CONE_BLOCK`` lanes: one
    vector pass, without the scalar loop LLVM adds for a partial block.
    The number comes from
    the arrays, not the constant: a loop of a fixed 8 LLVM unrolls into
    scalar code. Unpadded (the GPU's), a block times only the cones it needs.
    """
    dx, dy, dz, t_closest, _, cx, cy, cz = ray[3:11]
    kp_limit, kp, t_turn, ph1_steps, ph2_start, ph2_steps, ph_jump = plan[5:]
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
