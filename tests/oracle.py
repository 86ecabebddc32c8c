"""Slow, obviously-correct reference traversal (the geometry contract: docs/geometry.md).

Written for clarity, not speed, and sharing no code with the package: plain
numpy classification by ``searchsorted``, every crossing of the ray with every
boundary surface (full spheres, full vertical planes, full double cones: extra
break points are harmless because each interval is classified by its
midpoint), sorted, then classified and merged.

The line is the float64 one the package traces (origin and unit direction as
given), but its crossings with the boundaries are computed in extended
precision (``numpy.longdouble``, a 64-bit mantissa on x86-64): near a
tangency the roots of a quadratic lose half their digits, and in double
precision the oracle itself could not tell a dip of 1e-15 rad into a cone
(a real sliver of ~1e-6) from a miss. Cells are looked up in float64, as the
contract defines them.
"""

import numpy as np


def classify(points, rho_edges, theta_edges, phi_edges):
    """(M, 3) points -> (M, 3) cells, -1 rows outside. Same tie rule as docs/geometry.md."""
    points = np.atleast_2d(points)
    x, y, z = points[:, 0], points[:, 1], points[:, 2]
    rho = np.sqrt(x * x + y * y + z * z)
    theta = np.arctan2(x + 0.0, z + 0.0)
    # Wrap only what lies outside [theta_min, theta_min + 2 pi): shifting every
    # value would round a tiny azimuth onto an edge at 0.
    low = theta_edges[0]
    outside = (theta < low) | (theta >= low + 2 * np.pi)
    theta = np.where(outside, low + np.mod(theta - low, 2 * np.pi), theta)
    phi = np.arctan2(y + 0.0, np.sqrt(x * x + z * z))
    cells = np.empty((points.shape[0], 3), dtype=np.int64)
    inside = np.ones(points.shape[0], dtype=bool)
    axes = ((rho, rho_edges), (theta, theta_edges), (phi, phi_edges))
    for axis, (value, edges) in enumerate(axes):
        index = np.searchsorted(edges, value, side="right") - 1
        index[value == edges[-1]] = len(edges) - 2  # the region is closed (Eq. 1)
        inside &= (value >= edges[0]) & (value <= edges[-1])
        cells[:, axis] = index
    cells[~inside] = -1
    return cells


def _quadratic_roots(a, half_b, c, disc=None):
    """Real roots of a t^2 + 2 half_b t + c, without the cancellation of the textbook formula.

    When the ray runs almost parallel to a cone's generatrix ``a`` is ~1e-16 and
    ``(-half_b + sqrt(disc)) / a`` is noise; ``c / q`` keeps the finite root exact.
    ``disc``, when given, is ``half_b^2 - a c`` computed by the caller in a
    form free of cancellation.
    """
    if disc is None:
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
    """Every t > 0 where the ray meets a boundary surface (plus a few harmless extras).

    Every equation is solved for ``u = t - t_c`` about the line's closest
    point to the centre, ``p = o + t_c d``: written about the origin, their
    coefficients are differences of terms of size |o|^2, and a line passing
    h from the centre then had cone crossings off by about sqrt(eps) |o|,
    far more than the cells of size ~h it crosses there.

    The spheres' quadratic keeps ``|d|^2`` as it is: a float64 unit vector's
    squared length is 1 only to ~1e-16, and taking it as 1 moves a far
    origin's line by |o|^2 * 1e-16 in the squared distance from the centre,
    which is larger than rho_min^2 once |o| / rho_min passes ~1e8.
    """
    origin = np.asarray(origin, dtype=np.longdouble)
    direction = np.asarray(direction, dtype=np.longdouble)
    ox, oy, oz = origin
    dx, dy, dz = direction
    length2 = dx * dx + dy * dy + dz * dz
    t_c = -(ox * dx + oy * dy + oz * dz) / length2
    px, py, pz = origin + t_c * direction
    ts = []
    # About p, whose distance from the centre is its own: written about the
    # origin, |o|^2 - R^2 is rounded by |o|^2 times longdouble's eps, 3e-4
    # for |o| = 5e7, and a crossing near a tangency moved by its square root.
    p_dot_d = px * dx + py * dy + pz * dz  # about 0
    p2 = px * px + py * py + pz * pz
    for radius in np.asarray(rho_edges, dtype=np.longdouble):
        ts += [t_c + u for u in _quadratic_roots(length2, p_dot_d, p2 - radius * radius)]
    for angle in np.asarray(theta_edges, dtype=np.longdouble):
        denom = dx * np.cos(angle) - dz * np.sin(angle)
        if denom != 0.0:
            ts.append(t_c - (px * np.cos(angle) - pz * np.sin(angle)) / denom)
    for angle in np.asarray(phi_edges, dtype=np.longdouble):
        if abs(angle) >= np.pi / 2:
            continue
        if angle == 0.0:
            if dy != 0.0:
                ts.append(t_c - py / dy)
            continue
        tan2 = np.tan(angle) ** 2
        # half_b^2 - a c, written out, is a difference of two terms of size
        # (p_y d_y)^2 whose true value is of size tan^2: for a cone all but
        # flat (an edge 1e-15 from 0) it is rounding noise even in extended
        # precision. Expanded, the p_y^2 d_y^2 terms cancel exactly:
        # disc = tan^2 |d_y P - p_y D|^2 - tan^4 (P x D)^2 over (x, z).
        disc = (tan2 * ((dy * px - py * dx) ** 2 + (dy * pz - py * dz) ** 2)
                - tan2 * tan2 * (px * dz - pz * dx) ** 2)
        ts += [t_c + u for u in _quadratic_roots(
            dy * dy - tan2 * (dx * dx + dz * dz),
            py * dy - tan2 * (px * dx + pz * dz),
            py * py - tan2 * (px * px + pz * pz),
            disc,
        )]
    # The origin and the y axis are where theta and phi may jump.
    ts.append(t_c)
    if dx * dx + dz * dz > 0.0:
        ts.append(-(ox * dx + oz * dz) / (dx * dx + dz * dz))
    ts = np.array([t for t in ts if np.isfinite(t) and t > 0.0], dtype=np.longdouble)
    return np.unique(np.concatenate([np.zeros(1, dtype=np.longdouble), ts]))


def oracle_trace(origin, direction, rho_edges, theta_edges, phi_edges, normalise=True):
    """Reference segments: (cells (n, 3) int, t_enter (n,), t_exit (n,)) for a unit direction.

    ``normalise=False`` takes ``direction`` as the unit vector it is (the
    package's own, ``_validate.rays``): numpy's norm may differ from the
    package's by an ulp, which turns the line by ``eps`` and moves it by
    ``eps |o|`` near the centre, more than a far origin's tolerance.
    """
    origin = np.asarray(origin, dtype=np.float64)
    direction = np.asarray(direction, dtype=np.float64)
    if normalise:
        direction = direction / np.linalg.norm(direction)  # the package's line, in float64
    breaks = crossings(origin, direction, rho_edges, theta_edges, phi_edges)
    # Beyond the last break the ray only moves away from rho_max: outside for good.
    starts, ends = breaks[:-1], breaks[1:]
    mids = 0.5 * (starts + ends)
    # Midpoints in extended precision, classified in float64: the contract's
    # lookup (its tie rule puts a float64 angle equal to an edge above it).
    points = origin.astype(np.longdouble) + mids[:, None] * direction.astype(np.longdouble)
    cells = classify(points.astype(np.float64), rho_edges, theta_edges, phi_edges)
    starts, ends = starts.astype(np.float64), ends.astype(np.float64)
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


def cut_at(trace, t_max):
    """A reference trace (cells, t_enter, t_exit) cut at distance ``t_max``, as
    ``trace_many(..., t_max=...)`` cuts it."""
    cells, t_enter, t_exit = trace
    keep = t_enter < t_max
    return cells[keep], t_enter[keep], np.minimum(t_exit[keep], t_max)


def normalise(cells, t_enter, t_exit, tol):
    """Drop segments shorter than ``tol`` and re-merge neighbours of the same cell.

    docs/geometry.md: segments shorter than about 1e-9 of the region's size may be
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

# A ray built to graze a sphere or cone closer than float64 resolves (an
# offset below ~1e-12 of the scene) truly dips into the next cell, or not, by
# a depth of a few eps L that the package decides in float64: a sliver of up
# to ~2 sqrt(eps) L may show or not (measured: at most 2.25 sqrt(eps) L over
# 3,600 such rays per method against this extended-precision oracle). Real
# dips of 1e-15 of the scene into a cone are slivers of ~8 sqrt(eps) L, which
# both resolve, so the threshold sits between the two.
UNRESOLVED_TANGENT = 4.0 * np.sqrt(np.finfo(np.float64).eps)


def compare(got, want, scale, rel=1e-9, rel_distances=None):
    """None when two traces agree (docs/geometry.md), else a message saying where they differ.

    Segments shorter than ``rel * scale`` are dropped on both sides; the rest must
    have equal cells and distances within ``rel_distances`` (default ``rel``;
    relative to the distance, or to ``scale`` for distances near zero).
    """
    tol = rel * scale
    rel = rel if rel_distances is None else rel_distances
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


# ---- references for what is built on traces (cones, the occupancy map) ----


def union_of_rays(traces, ray_weights):
    """Reference cone aggregation: per cell, the weight of the rays that cross it and the
    first distance at which any ray reaches it (``trace_cone``'s ``weights``, unnormalised,
    and ``t_first``). ``traces`` is a sequence of per-ray (cells, t_enter) pairs."""
    weights, first = {}, {}
    for ray, (cells, t_enter) in enumerate(traces):
        seen = set()
        for cell, t0 in zip(map(tuple, np.asarray(cells).tolist()), t_enter):
            first[cell] = min(first.get(cell, np.inf), t0)
            if cell not in seen:
                weights[cell] = weights.get(cell, 0.0) + ray_weights[ray]
                seen.add(cell)
    return weights, first


def reference_log_odds(shape, offsets, cells, t_exit, distances, is_hit,
                       p_hit=0.7, p_miss=0.4):
    """One scan's log-odds map from its sensor rays' traces (CSR, cut at ``distances``).

    OctoMap's update, once per cell per scan: every cell a ray crosses is free,
    the cell holding its end point is hit when ``is_hit`` and the trace reaches
    the end point, and a hit wins over a miss.
    """
    cells = np.asarray(cells, dtype=np.int64)
    flat = np.ravel_multi_index(tuple(cells.T), shape)
    free = np.zeros(int(np.prod(shape)), dtype=bool)
    free[flat] = True
    counts = np.diff(offsets)
    last = np.asarray(offsets[1:]) - 1
    ends = (counts > 0) & np.asarray(is_hit)
    ends[ends] &= np.asarray(t_exit)[last[ends]] >= np.asarray(distances)[ends]
    hit = np.zeros_like(free)
    hit[flat[last[ends]]] = True
    log_odds = np.zeros(free.shape, dtype=np.float32)
    log_odds[free] = np.float32(np.log(p_miss / (1.0 - p_miss)))
    log_odds[hit] = np.float32(np.log(p_hit / (1.0 - p_hit)))
    return log_odds.reshape(shape)


def first_occupied(traces, ray_weights, log_odds, unknown=0.0, free_below=0.5,
                   min_distance=0.0):
    """Reference fixation probability per cell: sum over rays of weight x P(the cell is
    the first occupied one the ray meets), with P(c) = p_c prod(1 - p) over the distinct
    cells before c. ``traces``: per-ray (cells, t_exit) pairs; ``log_odds`` the dense map."""
    out = {}
    for ray, (cells, t_exit) in enumerate(traces):
        clear = 1.0
        seen = set()
        for cell, t1 in zip(map(tuple, np.asarray(cells).tolist()), t_exit):
            if t1 <= min_distance or cell in seen:
                continue
            seen.add(cell)
            value = float(log_odds[cell])
            p = unknown if value == 0.0 else 1.0 / (1.0 + np.exp(-value))
            if value != 0.0 and p < free_below:
                p = 0.0
            out[cell] = out.get(cell, 0.0) + ray_weights[ray] * p * clear
            clear *= 1.0 - p
    return out


def _outside_cell(points, cells, rho_edges, theta_edges, phi_edges):
    """How far each point lies outside its closed cell (0 inside): the largest of
    its distances beyond the cell's spheres, half-planes' planes and cones, each
    measured as a length (an angle times the radius it turns at)."""
    x, y, z = points[:, 0], points[:, 1], points[:, 2]
    rho = np.sqrt(x * x + y * y + z * z)
    flat = np.sqrt(x * x + z * z)
    i, j, k = cells[:, 0], cells[:, 1], cells[:, 2]
    radial = np.maximum(np.maximum(rho_edges[i] - rho, rho - rho_edges[i + 1]), 0.0)
    # Azimuth past the sector, either way round, as a turn of at most pi / 2.
    past = np.mod(np.arctan2(x, z) - theta_edges[j], 2 * np.pi)
    width = theta_edges[j + 1] - theta_edges[j]
    beyond = np.where(past <= width, 0.0, np.minimum(past - width, 2 * np.pi - past))
    azimuthal = flat * np.sin(np.minimum(beyond, np.pi / 2))
    phi = np.arctan2(y, flat)
    above = np.maximum(np.maximum(phi_edges[k] - phi, phi - phi_edges[k + 1]), 0.0)
    polar = rho * np.sin(np.minimum(above, np.pi / 2))
    return np.maximum(np.maximum(radial, azimuthal), polar)


def _depth_in_region(points, rho_edges, theta_edges, phi_edges):
    """Distance of each point from the region's boundary (any sign): 0 on it."""
    x, y, z = points[:, 0], points[:, 1], points[:, 2]
    rho = np.sqrt(x * x + y * y + z * z)
    flat = np.sqrt(x * x + z * z)
    depth = np.abs(rho - rho_edges[-1])
    if rho_edges[0] > 0.0:
        depth = np.minimum(depth, np.abs(rho - rho_edges[0]))
    if theta_edges[-1] - theta_edges[0] < 2 * np.pi - 1e-12:
        for edge in (theta_edges[0], theta_edges[-1]):
            turn = np.abs(np.mod(np.arctan2(x, z) - edge + np.pi, 2 * np.pi) - np.pi)
            depth = np.minimum(depth, flat * np.sin(np.minimum(turn, np.pi / 2)))
    phi = np.arctan2(y, flat)
    for edge in (phi_edges[0], phi_edges[-1]):
        if abs(edge) < np.pi / 2 - 1e-12:
            depth = np.minimum(depth, rho * np.sin(np.minimum(np.abs(phi - edge), np.pi / 2)))
    return depth


def _union(t_enter, t_exit, tol):
    merged = []
    for start, end in sorted(zip(np.asarray(t_enter).tolist(), np.asarray(t_exit).tolist())):
        if merged and start <= merged[-1][1] + tol:
            merged[-1][1] = max(merged[-1][1], end)
        else:
            merged.append([start, end])
    return merged


def within_faces(got, origin, direction, rho_edges, theta_edges, phi_edges, scale, rel=1e-9,
                 t_max=np.inf):
    """None when a trace is right for a ray that may lie in a boundary, else a message.

    A ray lying in a half-plane or on a cone (its whole stretch there, not
    just a point) is in the cells on both sides at once, and rounding picks
    one; the oracle's extended precision may pick the other, even cell by
    cell. So instead of the oracle's cells: every segment (at 1%, 50% and
    99% of it) lies in the closure of its cell to within ``rel * scale``, and
    the stretches covered differ from the oracle's (up to ``t_max``) only
    where the ray runs along the region's own boundary, within ``rel *
    scale`` of it.
    """
    tol = rel * scale
    cells, t_enter, t_exit = (np.asarray(a) for a in got)
    origin = np.asarray(origin, dtype=np.float64)
    direction = np.asarray(direction, dtype=np.float64)
    if cells.shape[0]:
        at = np.concatenate([t_enter + f * (t_exit - t_enter) for f in (0.01, 0.5, 0.99)])
        points = origin + at[:, None] * direction
        outside = _outside_cell(points, np.tile(cells, (3, 1)), rho_edges, theta_edges, phi_edges)
        worst = int(np.argmax(outside))
        if outside[worst] > tol:
            row = worst % cells.shape[0]
            return (f"segment {row} (cell {cells[row].tolist()}, t {t_enter[row]:.6g} to "
                    f"{t_exit[row]:.6g}) lies {outside[worst]:.3e} outside its cell")
    want = oracle_trace(origin, direction, rho_edges, theta_edges, phi_edges)
    covered = _union(t_enter, t_exit, tol)
    before = want[1] < t_max
    reference = _union(want[1][before], np.minimum(want[2][before], t_max), tol)
    breaks = sorted({t for stretch in covered + reference for t in stretch})
    for start, end in zip(breaks[:-1], breaks[1:]):
        middle = 0.5 * (start + end)
        inside = [any(a <= middle <= b for a, b in stretches) for stretches in (covered,
                                                                                reference)]
        if end - start > tol and inside[0] != inside[1]:
            depth = _depth_in_region((origin + middle * direction)[None], rho_edges,
                                     theta_edges, phi_edges)[0]
            if depth > tol:
                return (f"t {start:.6g} to {end:.6g} is {'' if inside[0] else 'not '}covered "
                        f"but the oracle says otherwise, {depth:.3e} from the region's boundary")
    return None
