"""The paper's Algorithm 1 (bisection stepping), kept as a reproducible baseline.

Faithful to its steps: a fixed ``default_t`` first step; halve the step when
an index jumps by more than one; grow it by 1.5 when no index changes; take
the midpoint of the last two samples when the search oscillates (line 12-13,
"block"); accept when every index moves by at most one, then restart from
``default_t``; stop when a sample falls outside the region (line 4). The
azimuth index is compared cyclically on a full circle (the theta seam).

Known behaviour, measured rather than hidden (``bench/accuracy.py``): an
accepted step may move two indices at once and skip the cell between; the
trace ends at the first exit, so a ray that crosses the egocentric gap or
leaves a partial range and comes back loses the rest. ``t_enter`` and
``t_exit`` are the sample distances at which a cell was accepted and left,
not its boundaries. Every ray stops after ``max_iter`` samples at most, so
a ray grazing a boundary cannot loop forever.
"""

import numpy as np
from numba import prange

from ..._jit import jit, jit_twins
from ..locate import BLOCK, cell_of_point

_NONE = 0
_HALVED = 1
_GREW = 2


@jit
def _inside(ox, oy, oz, dx, dy, dz, t,
            rho_edges, rho_kind, theta_edges, theta_kind, phi_edges, phi_kind):
    i, _, _ = cell_of_point(ox + t * dx, oy + t * dy, oz + t * dz,
                            rho_edges, rho_kind, theta_edges, theta_kind, phi_edges, phi_kind)
    return i >= 0


@jit(runtime=True)
def entry_time(ox, oy, oz, dx, dy, dz, grid, candidates):
    """First t >= 0 at which the ray is inside the region (section 2.3), or -1.

    The candidates are t = 0 and the crossings of the region's own bounds with
    the corrected Eq. 9: the spheres rho_min and rho_max (9a), the half-planes
    theta_min and theta_max of a partial range (9c), the cones phi_min and
    phi_max (9b, both roots). The smallest candidate just after which the ray
    is inside is the entry ("overlapping the intervals"). ``candidates`` is
    scratch of length >= 11.
    """
    rho_edges, rho_kind = grid.rho_edges, grid.rho_kind
    theta_edges, theta_kind = grid.theta_edges, grid.theta_kind
    phi_edges, phi_kind = grid.phi_edges, grid.phi_kind
    n = 0
    candidates[n] = 0.0
    n += 1
    b = ox * dx + oy * dy + oz * dz
    c0 = ox * ox + oy * oy + oz * oz
    for radius in (rho_edges[0], rho_edges[-1]):
        disc = b * b - (c0 - radius * radius)
        if disc >= 0.0:
            root = np.sqrt(disc)
            candidates[n] = -b - root
            candidates[n + 1] = -b + root
            n += 2
    if theta_edges[-1] - theta_edges[0] < 2.0 * np.pi:
        for angle in (theta_edges[0], theta_edges[-1]):
            denom = dx * np.cos(angle) - dz * np.sin(angle)
            if denom != 0.0:
                candidates[n] = -(ox * np.cos(angle) - oz * np.sin(angle)) / denom
                n += 1
    for angle in (phi_edges[0], phi_edges[-1]):
        if abs(angle) >= 0.5 * np.pi:
            continue
        tan2 = np.tan(angle) ** 2
        a = dy * dy - tan2 * (dx * dx + dz * dz)
        half_b = oy * dy - tan2 * (ox * dx + oz * dz)
        c = oy * oy - tan2 * (ox * ox + oz * oz)
        disc = half_b * half_b - a * c
        if disc >= 0.0 and a != 0.0:
            root = np.sqrt(disc)
            candidates[n] = (-half_b - root) / a
            candidates[n + 1] = (-half_b + root) / a
            n += 2
        elif a == 0.0 and half_b != 0.0:
            candidates[n] = -c / (2.0 * half_b)
            n += 1
    ordered = candidates[:n]
    ordered.sort()  # in place: no allocation per ray
    nudge = 1e-9 * rho_edges[-1]
    for q in range(n):
        t = ordered[q]
        if t < 0.0:
            continue
        if _inside(ox, oy, oz, dx, dy, dz, t + nudge,
                   rho_edges, rho_kind, theta_edges, theta_kind, phi_edges, phi_kind):
            return t
    return -1.0


# It calls entry_time, which sorts: a kernel without the runtime cannot type that call.
@jit(runtime=True)
def bisect_ray(origins, directions, row, grid, default_t, max_iter, candidates,
               cells, t_enter, t_exit, start, write):
    """Algorithm 1 for ray ``row`` (unit direction); returns the number of cells reported."""
    ox, oy, oz = origins[row, 0], origins[row, 1], origins[row, 2]
    dx, dy, dz = directions[row, 0], directions[row, 1], directions[row, 2]
    rho_edges, rho_kind = grid.rho_edges, grid.rho_kind
    theta_edges, theta_kind = grid.theta_edges, grid.theta_kind
    phi_edges, phi_kind = grid.phi_edges, grid.phi_kind
    theta_full = grid.theta_full
    n_theta = theta_edges.shape[0] - 1
    t_first = entry_time(ox, oy, oz, dx, dy, dz, grid, candidates)
    if t_first < 0.0:
        return 0
    # The entry lies on a boundary; the first cell is read just inside it.
    t0 = t_first + 1e-9 * rho_edges[-1]
    i, j, k = cell_of_point(ox + t0 * dx, oy + t0 * dy, oz + t0 * dz,
                            rho_edges, rho_kind, theta_edges, theta_kind, phi_edges, phi_kind)
    if i < 0:
        return 0
    count = 0
    if write:
        cells[start, 0] = i
        cells[start, 1] = j
        cells[start, 2] = k
        t_enter[start] = t_first
        t_exit[start] = t0
    count = 1
    dt = default_t
    t_last = t0
    last_action = _NONE
    for _ in range(max_iter):
        t1 = t0 + dt
        i1, j1, k1 = cell_of_point(ox + t1 * dx, oy + t1 * dy, oz + t1 * dz,
                                   rho_edges, rho_kind, theta_edges, theta_kind,
                                   phi_edges, phi_kind)
        if i1 < 0:
            if write:
                t_exit[start + count - 1] = t1
            break  # line 4: the next point is out of bounds
        step_i = abs(i1 - i)
        step_j = abs(j1 - j)
        if theta_full:
            step_j = min(step_j, n_theta - step_j)  # the seam: cell n-1 neighbours cell 0
        step_k = abs(k1 - k)
        too_far = step_i > 1 or step_j > 1 or step_k > 1
        no_change = step_i == 0 and step_j == 0 and step_k == 0
        if (last_action == _HALVED and no_change) or (last_action == _GREW and too_far):
            dt = 0.5 * (t_last + t1) - t0  # lines 12-13: oscillation, take the midpoint
            last_action = _NONE
        elif too_far:
            dt = 0.5 * dt
            last_action = _HALVED
        elif no_change:
            dt = 1.5 * dt
            last_action = _GREW
        else:
            if write:
                t_exit[start + count - 1] = t1
                cells[start + count, 0] = i1
                cells[start + count, 1] = j1
                cells[start + count, 2] = k1
                t_enter[start + count] = t1
                t_exit[start + count] = t1
            count += 1
            i, j, k = i1, j1, k1
            t0 = t1
            dt = default_t
            last_action = _NONE
        t_last = t1
    return count


@jit_twins
def bisect_rows(origins, directions, grid, default_t, max_iter, offsets, cells, t_enter, t_exit,
                write):
    """Count (``write`` False) or write (True) every ray's cells; return the counts.

    One source for both CSR passes: counting passes empty output arrays,
    and writing puts ray ``row``'s cells from ``offsets[row]`` on.
    """
    n_rays = origins.shape[0]
    counts = np.empty(n_rays, dtype=np.int64)
    for block in prange((n_rays + BLOCK - 1) // BLOCK):
        candidates = np.empty(11)
        for row in range(block * BLOCK, min(n_rays, (block + 1) * BLOCK)):
            counts[row] = bisect_ray(
                origins, directions, row, grid, default_t, max_iter, candidates,
                cells, t_enter, t_exit, offsets[row] if write else 0, write,
            )
    return counts
