"""Slow, obviously-correct reference traversal (GEOMETRY.md, "What a correct trace is").

Written for clarity, not speed, and sharing no code with the package: plain
numpy classification by ``searchsorted``, every crossing of the ray with every
boundary surface (full spheres, full vertical planes, full double cones: extra
break points are harmless because each interval is classified by its
midpoint), sorted, then classified and merged.
"""

import numpy as np


def classify(points, rho_edges, theta_edges, phi_edges):
    """(M, 3) points -> (M, 3) cells, -1 rows outside. Same tie rule as GEOMETRY.md + README."""
    points = np.atleast_2d(points)
    x, y, z = points[:, 0], points[:, 1], points[:, 2]
    rho = np.sqrt(x * x + y * y + z * z)
    theta = np.arctan2(x + 0.0, z + 0.0)
    theta = theta_edges[0] + np.mod(theta - theta_edges[0], 2 * np.pi)
    phi = np.arctan2(y + 0.0, np.sqrt(x * x + z * z))
    cells = np.empty((points.shape[0], 3), dtype=np.int64)
    inside = np.ones(points.shape[0], dtype=bool)
    for axis, (value, edges) in enumerate(((rho, rho_edges), (theta, theta_edges), (phi, phi_edges))):
        index = np.searchsorted(edges, value, side="right") - 1
        index[value == edges[-1]] = len(edges) - 2  # the region is closed (Eq. 1)
        inside &= (value >= edges[0]) & (value <= edges[-1])
        cells[:, axis] = index
    cells[~inside] = -1
    return cells


def _quadratic_roots(a, half_b, c):
    """Real roots of a t^2 + 2 half_b t + c, without the cancellation of the textbook formula.

    When the ray runs almost parallel to a cone's generatrix ``a`` is ~1e-16 and
    ``(-half_b + sqrt(disc)) / a`` is noise; ``c / q`` keeps the finite root exact.
    """
    disc = half_b * half_b - a * c
    if disc < 0.0:
        return []
    q = -(half_b + np.copysign(np.sqrt(disc), half_b))
    roots = []
    if a != 0.0:
        roots.append(q / a)
    if q != 0.0:
        roots.append(c / q)
    return roots


def crossings(origin, direction, rho_edges, theta_edges, phi_edges):
    """Every t > 0 where the ray meets a boundary surface (plus a few harmless extras)."""
    ox, oy, oz = origin
    dx, dy, dz = direction
    ts = []
    for radius in rho_edges:
        ts += _quadratic_roots(1.0, ox * dx + oy * dy + oz * dz, ox * ox + oy * oy + oz * oz - radius**2)
    for angle in theta_edges:
        denom = dx * np.cos(angle) - dz * np.sin(angle)
        if denom != 0.0:
            ts.append(-(ox * np.cos(angle) - oz * np.sin(angle)) / denom)
    for angle in phi_edges:
        if abs(angle) >= np.pi / 2:
            continue
        if angle == 0.0:
            if dy != 0.0:
                ts.append(-oy / dy)
            continue
        tan2 = np.tan(angle) ** 2
        ts += _quadratic_roots(
            dy * dy - tan2 * (dx * dx + dz * dz),
            oy * dy - tan2 * (ox * dx + oz * dz),
            oy * oy - tan2 * (ox * ox + oz * oz),
        )
    # The origin and the y axis are where theta and phi may jump.
    ts.append(-(ox * dx + oy * dy + oz * dz))
    if dx * dx + dz * dz > 0.0:
        ts.append(-(ox * dx + oz * dz) / (dx * dx + dz * dz))
    ts = np.array([t for t in ts if np.isfinite(t) and t > 0.0])
    return np.unique(np.concatenate([[0.0], ts]))


def oracle_trace(origin, direction, rho_edges, theta_edges, phi_edges):
    """Reference segments: (cells (n, 3) int, t_enter (n,), t_exit (n,)) for a unit direction."""
    origin = np.asarray(origin, dtype=np.float64)
    direction = np.asarray(direction, dtype=np.float64)
    direction = direction / np.linalg.norm(direction)
    breaks = crossings(origin, direction, rho_edges, theta_edges, phi_edges)
    # Beyond the last break the ray only moves away from rho_max: outside for good.
    starts, ends = breaks[:-1], breaks[1:]
    mids = 0.5 * (starts + ends)
    cells = classify(origin + mids[:, None] * direction, rho_edges, theta_edges, phi_edges)
    out_cells, out_t0, out_t1 = [], [], []
    for cell, t0, t1 in zip(cells, starts, ends):
        if cell[0] < 0 or t1 <= t0:
            continue
        if out_cells and out_t1[-1] == t0 and np.array_equal(out_cells[-1], cell):
            out_t1[-1] = t1
            continue
        out_cells.append(cell)
        out_t0.append(t0)
        out_t1.append(t1)
    return (np.array(out_cells, dtype=np.int64).reshape(-1, 3), np.array(out_t0), np.array(out_t1))


def normalise(cells, t_enter, t_exit, tol):
    """Drop segments shorter than ``tol`` and re-merge neighbours of the same cell.

    GEOMETRY.md: segments shorter than about 1e-9 of the region's size may be
    kept or dropped by floating point; the comparison ignores them.
    """
    out_cells, out_t0, out_t1 = [], [], []
    for cell, t0, t1 in zip(np.asarray(cells), np.asarray(t_enter), np.asarray(t_exit)):
        if t1 - t0 < tol:
            continue
        if out_cells and abs(t0 - out_t1[-1]) <= 2 * tol and np.array_equal(out_cells[-1], cell):
            out_t1[-1] = t1
            continue
        out_cells.append(np.asarray(cell, dtype=np.int64))
        out_t0.append(t0)
        out_t1.append(t1)
    return (np.array(out_cells, dtype=np.int64).reshape(-1, 3), np.array(out_t0), np.array(out_t1))


# Near tangency to a sphere or cone the chord is 2 sqrt(R^2 - h^2): rounding of
# h^2 by eps R^2 shows up as a sliver of up to ~sqrt(eps) R, in the oracle as in
# the kernel. Tests that aim at exact tangencies allow slivers (and boundary
# shifts) of this size; random rays are held to 1e-9.
TANGENT_SLIVER = 2.0 * np.sqrt(np.finfo(np.float64).eps)


def compare(got, want, scale, rel=1e-9):
    """Return None when two traces agree (GEOMETRY.md), else a message saying where they differ.

    Segments shorter than ``rel * scale`` are dropped on both sides; the rest must
    have equal cells and distances within ``rel`` (relative to the distance, or to
    ``scale`` for distances near zero).
    """
    tol = rel * scale
    got_cells, got_t0, got_t1 = normalise(*got, tol)
    want_cells, want_t0, want_t1 = normalise(*want, tol)
    if got_cells.shape != want_cells.shape or not np.array_equal(got_cells, want_cells):
        return f"cells differ:\n got  {got_cells.tolist()}\n want {want_cells.tolist()}"
    # "Segment distances agree to 1e-9 relative": relative to the distance itself,
    # or to the region's size for distances near zero.
    allowed = rel * np.maximum(np.abs(want_t1), scale)
    error = np.maximum(np.abs(got_t0 - want_t0), np.abs(got_t1 - want_t1))
    if np.any(error > allowed):
        return f"distances differ by up to {np.max(error):.3e} (allowed {np.min(allowed):.1e})"
    return None


def box_oracle_trace(origin, direction, low, high, shape):
    """Brute-force Cartesian reference: every plane crossing, sorted, midpoints classified."""
    origin = np.asarray(origin, dtype=np.float64)
    direction = np.asarray(direction, dtype=np.float64)
    direction = direction / np.linalg.norm(direction)
    ts = [0.0]
    for axis in range(3):
        if direction[axis] != 0.0:
            planes = np.linspace(low[axis], high[axis], shape[axis] + 1)
            ts += list((planes - origin[axis]) / direction[axis])
    ts = np.unique([t for t in ts if t >= 0.0])
    starts, ends = ts[:-1], ts[1:]
    mids = origin + 0.5 * (starts + ends)[:, None] * direction
    size = (np.asarray(high) - np.asarray(low)) / np.asarray(shape)
    index = np.floor((mids - low) / size).astype(np.int64)
    inside = np.all((mids >= low) & (mids <= high), axis=1)
    index = np.minimum(index, np.asarray(shape) - 1)
    keep = inside & (ends > starts)
    return index[keep], starts[keep], ends[keep]
