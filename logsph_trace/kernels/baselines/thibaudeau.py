"""Thibaudeau-style traversal: every crossing with every boundary, sorted, classified.

Thibaudeau et al. (2013) trace rays through polar grids by computing the
intersections with each family of boundaries separately, sorting them and
removing repetitions. This kernel does that for spheres, half-planes and cones
(the corrected Eq. 9): O(n log n) per ray in the number of boundaries, with a
full Cartesian-to-cell lookup per interval. It is exact, like the oracle, and
serves as the sort-based baseline of the timing study (Fig. 4).
"""

import math

import numpy as np
from numba import prange

from ..._jit import jit, jit_twins
from ..geometry import line_geometry
from ..locate import BLOCK, phi_zone, rho_zone, theta_zone


@jit
def scratch_length(n_rho, n_theta, n_phi):
    """Most break points one ray can have: every root of every boundary, plus 0, the
    closest approach and the end."""
    return 2 * (n_rho + 1) + (n_theta + 1) + 2 * (n_phi + 1) + 4


@jit(runtime=True)
def thibaudeau_ray(origins, directions, row, grid, breaks, cells, t_enter, t_exit, start, write):
    """Ray ``row`` (unit direction); ``breaks`` is scratch of length ``scratch_length``."""
    ox, oy, oz = origins[row, 0], origins[row, 1], origins[row, 2]
    dx, dy, dz = directions[row, 0], directions[row, 1], directions[row, 2]
    rho_edges, rho_kind = grid.rho_edges, grid.rho_kind
    theta_edges, theta_kind = grid.theta_edges, grid.theta_kind
    phi_edges, phi_kind = grid.phi_edges, grid.phi_kind
    n_rho = rho_edges.shape[0] - 1
    n_theta = theta_edges.shape[0] - 1
    n_phi = phi_edges.shape[0] - 1
    # Every equation is solved about the line's closest point c to the centre
    # (u = t - t_c), which keeps the roots accurate for lines through or near
    # the centre (see ``geometry.line_geometry``).
    t_c, h2, cx, cy, cz = line_geometry(ox, oy, oz, dx, dy, dz)
    outer = rho_edges[n_rho] ** 2 - h2
    if outer < 0.0 or t_c + math.sqrt(outer) <= 0.0:
        return 0  # never inside the outer sphere
    t_final = t_c + math.sqrt(outer)
    n = 0
    breaks[n] = 0.0
    n += 1
    if 0.0 < t_c < t_final:  # phi and theta may jump at the centre
        breaks[n] = t_c
        n += 1
    for radius in rho_edges:  # Eq. 9a, both roots
        disc = radius * radius - h2
        if disc >= 0.0:
            root = math.sqrt(disc)
            for t in (t_c - root, t_c + root):
                if 0.0 < t < t_final:
                    breaks[n] = t
                    n += 1
    for angle in theta_edges:  # Eq. 9c: the whole plane; extra breaks are harmless
        denom = dx * math.cos(angle) - dz * math.sin(angle)
        if denom != 0.0:
            t = t_c - (cx * math.cos(angle) - cz * math.sin(angle)) / denom
            if 0.0 < t < t_final:
                breaks[n] = t
                n += 1
    b2 = dx * dx + dz * dz
    cab = cx * dx + cz * dz
    ca2 = cx * cx + cz * cz
    for angle in phi_edges:  # Eq. 9b, both nappes
        if abs(angle) >= 0.5 * np.pi:
            continue
        if angle == 0.0:  # the plane y = 0; its quadratic's discriminant rounds below 0
            t = t_c - cy / dy
            if 0.0 < t < t_final:
                breaks[n] = t
                n += 1
            continue
        tan2 = math.tan(angle) ** 2
        a = dy * dy - tan2 * b2
        half_b = cy * dy - tan2 * cab
        c = cy * cy - tan2 * ca2
        disc = half_b * half_b - a * c
        if disc < 0.0:
            continue
        q = -(half_b + math.sqrt(disc)) if half_b >= 0.0 else -(half_b - math.sqrt(disc))
        for u in (q / a, c / q):
            t = t_c + u
            if 0.0 < t < t_final:
                breaks[n] = t
                n += 1
    breaks[n] = t_final
    n += 1
    ordered = breaks[:n]
    ordered.sort()  # in place: no allocation per ray
    snap = 1e-12 * (rho_edges[n_rho] + math.sqrt(ox * ox + oy * oy + oz * oz))
    count = 0
    last_i = -1
    last_j = -1
    last_k = -1
    last_exit = -1.0
    for q in range(n - 1):
        t_from = ordered[q]
        t_to = ordered[q + 1]
        if t_to - t_from <= snap:
            continue
        t_mid = 0.5 * (t_from + t_to)
        x = ox + t_mid * dx
        y = oy + t_mid * dy
        z = oz + t_mid * dz
        i = rho_zone(x, y, z, rho_edges, rho_kind)
        j = theta_zone(x, z, theta_edges, theta_kind)
        k = phi_zone(x, y, z, phi_edges, phi_kind)
        if not (0 <= i < n_rho and j < n_theta and 0 <= k < n_phi):
            continue
        if count > 0 and i == last_i and j == last_j and k == last_k and t_from - last_exit <= snap:
            if write:
                t_exit[start + count - 1] = t_to  # repetition removed
        else:
            if write:
                cells[start + count, 0] = i
                cells[start + count, 1] = j
                cells[start + count, 2] = k
                t_enter[start + count] = t_from if t_from - last_exit > snap else last_exit
                t_exit[start + count] = t_to
            count += 1
            last_i = i
            last_j = j
            last_k = k
        last_exit = t_to
    return count


@jit_twins
def thibaudeau_rows(origins, directions, grid, offsets, cells, t_enter, t_exit, write):
    """Count (``write`` False) or write (True) every ray's cells; return the counts.

    One source for both CSR passes: counting passes empty output arrays,
    and writing puts ray ``row``'s cells from ``offsets[row]`` on.
    """
    n_rays = origins.shape[0]
    counts = np.empty(n_rays, dtype=np.int64)
    size = scratch_length(grid.rho_edges.shape[0] - 1, grid.theta_edges.shape[0] - 1,
                          grid.phi_edges.shape[0] - 1)
    for block in prange((n_rays + BLOCK - 1) // BLOCK):
        breaks = np.empty(size)
        for row in range(block * BLOCK, min(n_rays, (block + 1) * BLOCK)):
            counts[row] = thibaudeau_ray(
                origins, directions, row, grid, breaks, cells, t_enter, t_exit,
                offsets[row] if write else 0, write,
            )
    return counts
