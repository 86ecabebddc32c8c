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

On each monotone branch the zone at both ends is found by the same lookup the
public ``cell_of`` uses, so the *number* of crossings of every family is fixed
before stepping.  Crossing *times* come from closed forms (Eq. 9a, 9c and the
exact cone quadratic of GEOMETRY.md) and are clamped into the branch, so
rounding can move a crossing by an ulp or two but can never drop one or add
one: the indices cannot drift.  Each loop iteration consumes one counted
crossing, which bounds the loop by 2 (n_rho + 1) + (n_theta + 2) +
2 (n_phi + 1) + 2 iterations.
"""

import numpy as np
from numba import prange

from .._jit import jit
from .locate import TWO_PI, azimuth, locate, phi_zone, rho_zone, theta_zone


@jit
def _sphere_time(t_closest, h2, radius2, outward):
    """Crossing of a sphere on the inward or outward half of the line (Eq. 9a, corrected)."""
    half_chord = np.sqrt(max(radius2 - h2, 0.0))
    if outward:
        return t_closest + half_chord
    return t_closest - half_chord


@jit
def _plane_time(ox, oz, dx, dz, edge_sin, edge_cos):
    """Crossing of the vertical plane holding the half-plane theta = edge (Eq. 9c)."""
    return -(ox * edge_cos - oz * edge_sin) / (dx * edge_cos - dz * edge_sin)


@jit
def _cone_time(oy, dy, ab, a2, b2, tan2, nappe, first_branch, branch_start, slack):
    """Crossing of the elevation cone phi = edge on its own nappe, within the current branch.

    ``(o_y + t d_y)^2 = tan(phi)^2 ((o_x + t d_x)^2 + (o_z + t d_z)^2)`` solved
    with the cancellation-free quadratic formula (a ray parallel to a generatrix
    has ``a ~ 0``); ``ab``, ``a2``, ``b2`` are the x-z dot products A.B, |A|^2,
    |B|^2 of origin A and direction B.  A root before ``branch_start`` belongs
    to the other branch.  On the branch before phi's turning point the earlier
    root is the crossing, after it the later one.  Returns ``inf`` when no root
    qualifies: the crossing is at infinity (a limit direction on the cone).
    """
    if nappe == 0.0:
        return -oy / dy
    a = dy * dy - tan2 * b2
    half_b = oy * dy - tan2 * ab
    c = oy * oy - tan2 * a2
    disc = half_b * half_b - a * c
    if disc < 0.0:
        disc = 0.0
    root = np.sqrt(disc)
    q = -(half_b + root) if half_b >= 0.0 else -(half_b - root)
    earliest = branch_start - slack
    best = np.inf
    found = False
    for t_root in (q / a, c / q):
        if not (np.isfinite(t_root) and t_root >= earliest and nappe * (oy + t_root * dy) >= 0.0):
            continue
        if not found or (t_root < best if first_branch else t_root > best):
            best = t_root
            found = True
    return best


@jit
def _clamp(t_candidate, t_low, t_high, slack):
    """Keep a counted crossing inside its branch ``[t_low, t_high]``.

    A crossing a hair before ``t_low`` is a simultaneous one rounded the other
    way: it happens now. One clearly in the past (by more than ``slack``) is a
    crossing at infinity: the branch end was looked up exactly on a boundary
    the ray only approaches (a limit direction on a half-plane or cone, where
    the closed form returns +-inf or a huge value of either sign); it happens
    at the branch end, i.e. never for the last branch. NaN happens now.
    """
    if t_candidate != t_candidate:
        return t_low
    if t_candidate < t_low - slack:
        return t_high
    if t_candidate < t_low:
        return t_low
    if t_candidate > t_high:
        return t_high
    return t_candidate


@jit
def _theta_edge_ahead(zone, sigma, n_theta):
    """Edge index met when leaving azimuthal ``zone`` in direction ``sigma``."""
    if sigma > 0:
        return zone + 1 if zone < n_theta else 0
    return zone if zone < n_theta else n_theta


@jit
def trace_ray(
    ox, oy, oz, dx, dy, dz,
    rho_edges, rho_sq, rho_kind,
    theta_edges, theta_sin, theta_cos, theta_kind, theta_full,
    phi_edges, phi_tan2, phi_nappe, phi_kind,
    cells, t_enter, t_exit, start, write,
):
    """Trace one ray (unit direction) and return its number of segments.

    With ``write`` the segments go to ``cells[start:]``, ``t_enter[start:]``,
    ``t_exit[start:]``; without it nothing is written (the count pass).
    """
    n_rho = rho_edges.shape[0] - 1
    n_theta = theta_edges.shape[0] - 1
    n_phi = phi_edges.shape[0] - 1
    inf = np.inf
    # Rounding of a crossing time is ~1e-14 of the scene's size; a crossing found
    # further in the past than this is one at infinity (see _clamp).
    slack = 1e-9 * (rho_edges[n_rho] + np.sqrt(ox * ox + oy * oy + oz * oz))

    # x-z projections shared by theta and phi: A = (ox, oz), B = (dx, dz).
    ab = ox * dx + oz * dz
    a2 = ox * ox + oz * oz
    b2 = dx * dx + dz * dz

    # ---- rho: two monotone branches split at the closest approach t_c.
    t_closest = -(ox * dx + oy * dy + oz * dz)
    cross_x = oy * dz - oz * dy
    cross_y = oz * dx - ox * dz
    cross_z = ox * dy - oy * dx
    h2 = cross_x * cross_x + cross_y * cross_y + cross_z * cross_z
    ir = rho_zone(ox, oy, oz, rho_edges, rho_kind)
    if t_closest > 0.0:
        ir_turn = locate(np.sqrt(h2), rho_edges, rho_kind)
        if ir_turn > ir:
            ir_turn = ir
        rho_outward = False
        rho_steps = ir - ir_turn
        rho_steps_out = n_rho - ir_turn
    else:
        rho_outward = True
        rho_steps = n_rho - ir
        rho_steps_out = 0
    if not rho_outward and rho_steps == 0:
        rho_outward = True
        rho_steps = rho_steps_out
    if rho_steps == 0:
        return 0  # beyond rho_max and moving away: never inside
    edge = ir + 1 if rho_outward else ir
    t_rho = _clamp(_sphere_time(t_closest, h2, rho_sq[edge], rho_outward), 0.0, inf, slack)

    # ---- theta: one monotone sweep, or a jump where the line meets the y axis.
    n_zones_theta = n_theta if theta_full else n_theta + 1
    sweep_sign = oz * dx - ox * dz
    th_sigma = 0
    th_steps = 0
    th_jump_zone = -1
    t_theta = inf
    if dx == 0.0 and dz == 0.0:  # not b2 == 0: b2 underflows for |d_x|, |d_z| < 1e-154
        jt = theta_zone(ox, oz, theta_edges, theta_kind)
    elif sweep_sign == 0.0:
        jt_after = theta_zone(dx, dz, theta_edges, theta_kind)
        t_axis = -ab / b2
        if t_axis > 0.0:
            jt = theta_zone(ox, oz, theta_edges, theta_kind)
            if jt != jt_after:
                th_jump_zone = jt_after
                t_theta = t_axis
        else:
            jt = jt_after
    else:
        th_sigma = 1 if sweep_sign > 0.0 else -1
        jt = theta_zone(ox, oz, theta_edges, theta_kind)
        jt_end = theta_zone(dx, dz, theta_edges, theta_kind)
        th_steps = ((jt_end - jt) * th_sigma) % n_zones_theta
        if th_steps == 0:
            # A zone wider than half a turn: the sweep (< pi) may still leave it
            # and come round into it again; compare the sweep with the gap.
            theta_start = azimuth(ox, oz)
            theta_limit = azimuth(dx, dz)
            edge = _theta_edge_ahead(jt, th_sigma, n_theta)
            sweep = ((theta_limit - theta_start) * th_sigma) % TWO_PI
            gap = ((theta_edges[edge] - theta_start) * th_sigma) % TWO_PI
            if gap < sweep:
                th_steps = n_zones_theta
        if th_steps > 0:
            edge = _theta_edge_ahead(jt, th_sigma, n_theta)
            t_theta = _clamp(
                _plane_time(ox, oz, dx, dz, theta_sin[edge], theta_cos[edge]), 0.0, inf, slack
            )

    # ---- phi: up to two monotone branches split at the turning point -q/p,
    # or piecewise constant with a jump at the origin when p == q == 0.
    slope = dy * ab - oy * b2
    offset = dy * a2 - oy * ab
    ph_first = False
    ph_sigma = 0
    ph_steps = 0
    ph_low = 0.0
    ph_high = inf
    ph2_start = -1
    ph2_sigma = 0
    ph2_steps = 0
    ph_relocate = False
    t_phi = inf
    kp_limit = phi_zone(dx, dy, dz, phi_edges, phi_kind)
    # h2 == 0 (the line meets the origin) is tested on the cross product, which
    # is exactly 0 for collinear o and d where ``slope`` may round to 1e-16.
    if h2 == 0.0 or (slope == 0.0 and offset == 0.0):
        if ox == 0.0 and oy == 0.0 and oz == 0.0:
            kp = kp_limit
        else:
            kp = phi_zone(ox, oy, oz, phi_edges, phi_kind)
            if t_closest > 0.0 and h2 == 0.0 and kp != kp_limit:
                ph_first = True
                ph_high = t_closest
                ph2_start = kp_limit
    else:
        kp = phi_zone(ox, oy, oz, phi_edges, phi_kind)
        t_turn = -offset / slope if slope != 0.0 else inf
        if 0.0 < t_turn < inf:
            kp_turn = phi_zone(
                ox + t_turn * dx, oy + t_turn * dy, oz + t_turn * dz, phi_edges, phi_kind
            )
            ph_first = True
            ph_high = t_turn
            ph_steps = abs(kp_turn - kp)
            ph_sigma = 1 if kp_turn > kp else -1
            ph2_start = kp_turn
            ph2_steps = abs(kp_limit - kp_turn)
            ph2_sigma = 1 if kp_limit > kp_turn else -1
        else:
            ph_steps = abs(kp_limit - kp)
            ph_sigma = 1 if kp_limit > kp else -1
    # Leave an exhausted first branch: at once if the zone carries over,
    # by a relocation event at its end if the zone jumps (origin crossing).
    if ph_first and ph_steps == 0:
        if ph2_start == kp:
            ph_first = False
            ph_steps = ph2_steps
            ph_sigma = ph2_sigma
            ph_low = ph_high
            ph_high = inf
        else:
            ph_relocate = True
            t_phi = _clamp(ph_high, 0.0, inf, slack)
    if ph_steps > 0:
        edge = kp + 1 if ph_sigma > 0 else kp
        t_phi = _clamp(
            _cone_time(oy, dy, ab, a2, b2, phi_tan2[edge], phi_nappe[edge], ph_first,
                       ph_low, slack),
            0.0,
            ph_high,
            slack,
        )

    # ---- event loop: step the family with the nearest crossing.
    # Crossings that coincide (a corner where a sphere, a half-plane and a cone
    # meet) come out a few ulps apart; the slivers between them (shorter than
    # ``snap``) are cells the ray only touches. They are absorbed into the next
    # segment, which starts where the last one ended, so coverage stays exact.
    snap = 1e-3 * slack
    t_now = 0.0
    count = 0
    last_i = -1
    last_j = -1
    last_k = -1
    last_exit = -inf
    sliver_start = -1.0
    while True:
        t_next = t_rho
        family = 0
        if t_theta < t_next:
            t_next = t_theta
            family = 1
        if t_phi < t_next:
            t_next = t_phi
            family = 2
        if t_next == inf:
            break
        inside = 0 <= ir < n_rho and jt < n_theta and 0 <= kp < n_phi
        touching = count > 0 and t_now - last_exit <= snap
        if not inside:
            sliver_start = -1.0
        elif t_next - t_now <= snap:
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
            if touching and ir == last_i and jt == last_j and kp == last_k:
                # The same cell on both sides of a sliver or a zero-length detour
                # (tangency, the seam of a one-sector circle): extend, don't repeat.
                if write:
                    t_exit[start + count - 1] = t_next
            else:
                if write:
                    cells[start + count, 0] = ir
                    cells[start + count, 1] = jt
                    cells[start + count, 2] = kp
                    t_enter[start + count] = t_from
                    t_exit[start + count] = t_next
                count += 1
                last_i = ir
                last_j = jt
                last_k = kp
            last_exit = t_next
        t_now = t_next

        if family == 0:
            ir += 1 if rho_outward else -1
            rho_steps -= 1
            if rho_steps == 0 and not rho_outward:
                rho_outward = True
                rho_steps = rho_steps_out
            if rho_steps == 0:
                break  # past rho_max and moving away for good
            edge = ir + 1 if rho_outward else ir
            t_rho = _clamp(_sphere_time(t_closest, h2, rho_sq[edge], rho_outward), t_now, inf, slack)
        elif family == 1:
            if th_jump_zone >= 0:
                jt = th_jump_zone
                th_jump_zone = -1
                t_theta = inf
            else:
                jt += th_sigma
                if jt == n_zones_theta:
                    jt = 0
                elif jt < 0:
                    jt = n_zones_theta - 1
                th_steps -= 1
                if th_steps > 0:
                    edge = _theta_edge_ahead(jt, th_sigma, n_theta)
                    t_theta = _clamp(
                        _plane_time(ox, oz, dx, dz, theta_sin[edge], theta_cos[edge]), t_now, inf,
                        slack,
                    )
                else:
                    t_theta = inf
        else:
            if ph_relocate:
                kp = ph2_start
                ph_relocate = False
                ph_first = False
                ph_steps = ph2_steps
                ph_sigma = ph2_sigma
                ph_low = ph_high
                ph_high = inf
            else:
                kp += ph_sigma
                ph_steps -= 1
                if ph_first and ph_steps == 0:
                    if ph2_start == kp:
                        ph_first = False
                        ph_steps = ph2_steps
                        ph_sigma = ph2_sigma
                        ph_low = ph_high
                        ph_high = inf
                    else:
                        ph_relocate = True
            if ph_relocate:
                t_phi = _clamp(ph_high, t_now, inf, slack)
            elif ph_steps > 0:
                edge = kp + 1 if ph_sigma > 0 else kp
                t_phi = _clamp(
                    _cone_time(oy, dy, ab, a2, b2, phi_tan2[edge], phi_nappe[edge], ph_first,
                               ph_low, slack),
                    t_now,
                    ph_high,
                    slack,
                )
            else:
                t_phi = inf
    return count


def _count_rows(origins, directions, rho_edges, rho_sq, rho_kind, theta_edges, theta_sin,
                theta_cos, theta_kind, theta_full, phi_edges, phi_tan2, phi_nappe, phi_kind):
    n_rays = origins.shape[0]
    counts = np.empty(n_rays, dtype=np.int64)
    no_cells = np.empty((0, 3), dtype=np.int32)
    no_times = np.empty(0, dtype=np.float64)
    for row in prange(n_rays):
        counts[row] = trace_ray(
            origins[row, 0], origins[row, 1], origins[row, 2],
            directions[row, 0], directions[row, 1], directions[row, 2],
            rho_edges, rho_sq, rho_kind,
            theta_edges, theta_sin, theta_cos, theta_kind, theta_full,
            phi_edges, phi_tan2, phi_nappe, phi_kind,
            no_cells, no_times, no_times, 0, False,
        )
    return counts


def _fill_rows(origins, directions, rho_edges, rho_sq, rho_kind, theta_edges, theta_sin,
               theta_cos, theta_kind, theta_full, phi_edges, phi_tan2, phi_nappe, phi_kind,
               offsets, cells, t_enter, t_exit):
    for row in prange(origins.shape[0]):
        trace_ray(
            origins[row, 0], origins[row, 1], origins[row, 2],
            directions[row, 0], directions[row, 1], directions[row, 2],
            rho_edges, rho_sq, rho_kind,
            theta_edges, theta_sin, theta_cos, theta_kind, theta_full,
            phi_edges, phi_tan2, phi_nappe, phi_kind,
            cells, t_enter, t_exit, offsets[row], True,
        )


# The same source compiled twice: ``prange`` is a plain ``range`` without
# ``parallel=True``, so serial and parallel runs execute identical per-ray code
# and write each ray's segments into its own slice [offsets[r], offsets[r+1]).
count_rows = jit(_count_rows)
fill_rows = jit(_fill_rows)
count_rows_parallel = jit(_count_rows, parallel=True)
fill_rows_parallel = jit(_fill_rows, parallel=True)
