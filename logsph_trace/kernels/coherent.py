"""The coherent scan: a scan's rays binned by direction, most of them never walked.

Rays of a depth image that end in one cell's column after leaving the
sensor's cell agree on the cells they cross. ``bin_rays`` bins the rays by
direction on a cube around the sensor, ``mark_scan`` walks one ray of each
bin (its sample) and those the sample does not vouch for, and the cells
the others could cross are found by the columns in view (``columns_in_view``,
``near_masks``, ``mark_candidates``). docs/integration.md tells the whole
story; ``OccupancyGrid.integrate`` drives it.
"""

import math

import numpy as np
from numba import prange

from .._jit import jit
from .atomic import lower_to, store_relaxed
from .crossings import _sphere_time
from .geometry import grid_scratch_size, line_geometry
from .locate import BLOCK, phi_zone, rho_zone, theta_zone
from .ordered import in_turn, take
from .walk import FREE, _direction, _ray_length, walk_ray

# ``OccupancyGrid._mark_off_centre`` drives these kernels.
# Rays from a sensor in the egocentric gap cross most of their cells near it,
# where neighbouring rays cross the same cells. A sample of the rays is walked
# whole; each direction bin then gets a limit below which, by a proof
# (docs/integration.md), its other rays cross only cells the samples flagged,
# and those rays are walked from that limit's sphere on.
#
# Directions seen from the sensor are indexed by a cube map: face 2 * axis +
# (1 for the negative half), the axis of the largest |component| (ties to the
# earlier axis), and on it (u, v), the two other components over that one.



# An end point farther than this from every face of its cell (a fraction of
# rho_max + |sensor|, the exact kernel's scale) is in that cell by the walk too:
# the walk's crossing times are off by ~1e-15 of the scale, its tolerances 1e-9.
END_MARGIN = 1e-6


@jit(inline="always")
def _clear_of_theta(x, z, j, margin, grid):
    """Whether (x, ., z) lies in azimuthal sector ``j`` (narrower than a half
    turn) farther than ``margin`` from both its planes: the distance to a
    plane is r_xz sin(theta - edge)."""
    edges = grid.theta_edges
    return (0 <= j < edges.shape[0] - 1 and edges[j + 1] - edges[j] < math.pi
            and x * grid.theta_cos[j] - z * grid.theta_sin[j] > margin
            and z * grid.theta_sin[j + 1] - x * grid.theta_cos[j + 1] > margin)


@jit(inline="always")
def _clear_of_phi(y, flat, k, margin, grid):
    """Whether a point at height ``y`` and distance ``flat`` from the y axis
    lies in elevation band ``k`` farther than ``margin`` from both its cones
    (r sin(phi - edge), at most the distance to a cone)."""
    return (0 <= k < grid.phi_edges.shape[0] - 1
            and y * grid.phi_cos[k] - flat * grid.phi_sin[k] > margin
            and flat * grid.phi_sin[k + 1] - y * grid.phi_cos[k + 1] > margin)


@jit(inline="always")
def _end_zones(x, y, z, margin, grid, guesses):
    """Zones of the end point (x, y, z) when it lies clear of every face.

    Returns -1 in the egocentric gap, its shell i when it lies farther than
    ``margin`` from every face of its cell, with (i, j, k) in ``guesses``,
    and n_rho when it does not (or lies beyond rho_max): then only a walk
    knows. ``guesses`` hold the ray before's end zones, tried first.
    """
    rho_edges = grid.rho_edges
    n_rho = rho_edges.shape[0] - 1
    r = math.sqrt(x * x + y * y + z * z)
    if r < rho_edges[0] - margin:
        return -1
    i = min(max(guesses[0], 0), n_rho - 1)
    while i > 0 and r < rho_edges[i]:
        i -= 1
    while i < n_rho - 1 and r >= rho_edges[i + 1]:
        i += 1
    if not (r - rho_edges[i] > margin and rho_edges[i + 1] - r > margin):
        return n_rho
    j = guesses[1]
    if not _clear_of_theta(x, z, j, margin, grid):
        j = theta_zone(x, z, grid.theta_edges, grid.theta_kind)
        if not _clear_of_theta(x, z, j, margin, grid):
            return n_rho
    flat = math.sqrt(x * x + z * z)
    k = guesses[2]
    if not _clear_of_phi(y, flat, k, margin, grid):
        k = phi_zone(x, y, z, grid.phi_edges, grid.phi_kind)
        if not _clear_of_phi(y, flat, k, margin, grid):
            return n_rho
    guesses[0] = i
    guesses[1] = j
    guesses[2] = k
    return i


@jit(inline="always")
def _above_between(g1, slope1, g2, slope2, length, margin):
    """Whether a convex function with values ``g1``, ``g2`` (both above
    ``margin``) and slopes ``slope1``, ``slope2`` at the ends of an interval of
    ``length`` stays above ``margin`` on it: its tangents at the ends are
    below it, so its minimum is at least where they meet."""
    if slope1 >= 0.0 or slope2 <= 0.0:
        return True  # monotone: the minimum is at an end
    along = (g1 - g2 + slope2 * length) / (slope2 - slope1)
    return g1 + slope1 * along > margin


@jit(inline="always")
def _stays_in_column(x1, y1, z1, x2, y2, z2, dx, dy, dz, length, j, k, margin, grid):
    """Whether the segment from (x1, y1, z1) along (dx, dy, dz) to an end point
    (x2, y2, z2) clear of column (j, k), ``length`` long, stays clear of it.

    A theta sector narrower than a half turn is convex: both ends clear is
    enough. The side phi >= a of a band is convex for a > 0, and phi <= b
    for b < 0. Across the other sides, r sin(phi - edge) (the ends' margins
    in ``_clear_of_phi``) is a convex function along the segment
    (``_above_between``).
    """
    if not _clear_of_theta(x1, z1, j, margin, grid):
        return False
    flat1 = math.sqrt(x1 * x1 + z1 * z1)
    if not _clear_of_phi(y1, flat1, k, margin, grid):
        return False
    flat2 = math.sqrt(x2 * x2 + z2 * z2)
    away1 = (x1 * dx + z1 * dz) / flat1  # d flat / dt
    away2 = (x2 * dx + z2 * dz) / flat2
    sin_a = grid.phi_sin[k]
    cos_a = grid.phi_cos[k]
    if sin_a <= 0.0 and not _above_between(
            y1 * cos_a - flat1 * sin_a, dy * cos_a - away1 * sin_a,
            y2 * cos_a - flat2 * sin_a, dy * cos_a - away2 * sin_a, length, margin):
        return False
    sin_b = grid.phi_sin[k + 1]
    cos_b = grid.phi_cos[k + 1]
    return sin_b < 0.0 or _above_between(
        flat1 * sin_b - y1 * cos_b, away1 * sin_b - dy * cos_b,
        flat2 * sin_b - y2 * cos_b, away2 * sin_b - dy * cos_b, length, margin)


# Which rays ``mark_scan`` walks: every one, the coherent scan's samples (the
# first ray of each coarse bin), or the others.
WALK_ALL = 0
WALK_SAMPLES = 1
WALK_OTHERS = 2


@jit(parallel=True)
def mark_scan(origin, points, max_range, grid, free, hits, walk, coarse, first, bins, limit, skip,
              workers):
    """Walk the ray from ``origin`` to every point of a scan (see ``walk_ray``).

    ``max_range``: rays are cut there and end in no hit (``inf``: none).
    ``grid`` is the grid's ``GridArrays``. ``free`` (n_cells,) uint8: the
    flags, shared by the ``workers`` (one per thread, each taking blocks of
    rays in turn: ``in_turn``); ``hits[row]`` gets ray ``row``'s hit cell
    (column-major index) or -1.
    ``walk``: the rays to walk, ``WALK_ALL``, ``WALK_SAMPLES`` or
    ``WALK_OTHERS`` (``coarse`` and ``first`` tell a sample: ``is_sample``),
    each in row order. A ray may start on sphere
    ``limit`` of its direction bin (``bins``), ``skip`` at most (see
    ``_mark_off_centre``); with ``skip == 0`` every ray is walked whole.

    Every cell a ray crosses below its start sphere is flagged already, so
    a ray that ends below it, clear of its end cell's faces (``_end_zones``),
    adds only its hit, and one that stays in its end cell's column from the
    start sphere on (``_stays_in_column``) that column's shells: neither is
    walked.

    Returns how many rays were let start beyond the gap's sphere, and how
    many of those ended below it and stayed in one column (not walked).
    """
    n_rays = points.shape[0]
    ox = origin[0]
    oy = origin[1]
    oz = origin[2]
    ir = rho_zone(ox, oy, oz, grid.rho_edges, grid.rho_kind)
    jt = theta_zone(ox, oz, grid.theta_edges, grid.theta_kind)
    kp = phi_zone(ox, oy, oz, grid.phi_edges, grid.phi_kind)
    size = grid_scratch_size(grid)
    n_rho = grid.rho_edges.shape[0] - 1
    n_phi = grid.phi_edges.shape[0] - 1
    margin = END_MARGIN * (grid.rho_edges[n_rho] + math.sqrt(ox * ox + oy * oy + oz * oz))
    skipped = 0
    ended = 0
    straight = 0
    step, n_blocks, counter = in_turn(n_rays, workers, BLOCK)
    for worker in prange(workers):
        times = np.empty((3, size), dtype=np.float64)
        zones = np.empty((3, size), dtype=np.int64)
        lookups = np.empty(8, dtype=np.int64)
        guesses = np.zeros(3, dtype=np.int64)
        block = take(counter, n_blocks)
        while block >= 0:
            guesses[:] = 0
            for row in range(block * step, min(n_rays, (block + 1) * step)):
                if walk != WALK_ALL and is_sample(coarse, first, row) != (walk == WALK_SAMPLES):
                    continue
                hits[row] = -1
                # The ray as ``sensor_ray`` gives it, its direction divided out
                # only where it is walked (below).
                x = points[row, 0]
                y = points[row, 1]
                z = points[row, 2]
                length, distance, is_hit = _ray_length(points, row, ox, oy, oz, max_range)
                if length == 0.0:
                    continue  # a point at the sensor: no ray
                start = min(np.int64(limit[bins[row]]), skip) if skip > 0 else 0
                skipped += start > 0
                if start > 0:
                    # The end point: the scan's point, within an ulp or so of
                    # where the walk ends, far inside ``END_MARGIN``; else the
                    # point at max_range. (Most rays end here: the three
                    # divisions of the direction were 4-5 ms of 30 on one
                    # thread, table scan 10 cm off.)
                    if not is_hit:
                        dx, dy, dz = _direction(points, row, ox, oy, oz, length)
                        x = ox + distance * dx
                        y = oy + distance * dy
                        z = oz + distance * dz
                    i = _end_zones(x, y, z, margin, grid, guesses)
                    cell = ((guesses[1] * n_phi + guesses[2]) * n_rho + i)
                    if i < start:
                        if is_hit and i >= 0:
                            hits[row] = cell
                        ended += 1
                        continue
                    if i < n_rho:
                        dx, dy, dz = _direction(points, row, ox, oy, oz, length)
                        t_closest, h2, _, _, _ = line_geometry(ox, oy, oz, dx, dy, dz)
                        t_in = _sphere_time(t_closest, h2, grid.rho_sq[start], True)
                        if _stays_in_column(ox + t_in * dx, oy + t_in * dy, oz + t_in * dz, x, y, z,
                                            dx, dy, dz, distance - t_in, guesses[1], guesses[2],
                                            margin, grid):
                            # Whole shells from the start sphere to the end cell.
                            for shell in range(start, i + (not is_hit)):
                                store_relaxed(free, cell - i + shell, FREE)
                            if is_hit:
                                hits[row] = cell
                            straight += 1
                            continue
                dx, dy, dz = _direction(points, row, ox, oy, oz, length)
                hits[row] = walk_ray(ox, oy, oz, dx, dy, dz, distance, is_hit, ir, jt, kp, grid,
                                     times, zones, lookups, free, start)
            block = take(counter, n_blocks)
    return skipped, ended, straight


@jit(inline="always")
def _face_uv(x, y, z):
    """Cube-map face of direction (x, y, z) (not all zero) and its (u, v) there:
    ``_on_face`` of that face, from the one set of comparisons (a fifth of
    ``bin_rays``' time went to choosing the face twice)."""
    ax = abs(x)
    ay = abs(y)
    az = abs(z)
    if ax >= ay and ax >= az:
        return (0 if x > 0.0 else 1), y / ax, z / ax
    if ay >= az:
        return (2 if y > 0.0 else 3), x / ay, z / ay
    return (4 if z > 0.0 else 5), x / az, y / az


@jit(inline="always")
def _on_face(face, x, y, z):
    """(component along ``face``'s axis, u, v) of direction (x, y, z); u and v
    are meaningful where the first is > 0."""
    axis = face // 2
    sign = 1.0 - 2.0 * (face % 2)
    if axis == 0:
        major, a, b = sign * x, y, z
    elif axis == 1:
        major, a, b = sign * y, x, z
    else:
        major, a, b = sign * z, x, y
    if major <= 0.0:
        return major, 0.0, 0.0
    return major, a / major, b / major


@jit(inline="always")
def _bin_of(u, q):
    """Bin 0..q-1 of u in [-1, 1] (clamped)."""
    return min(max(int((u + 1.0) * 0.5 * q), 0), q - 1)


@jit(inline="always")
def _no_boxes(boxes):
    """Set every face's box (lowest and highest u, then v) to hold nothing."""
    for face in range(6):
        boxes[face, 0] = np.inf
        boxes[face, 1] = -np.inf
        boxes[face, 2] = np.inf
        boxes[face, 3] = -np.inf


@jit(inline="always")
def _take_in(boxes, face, u, v):
    """Widen ``face``'s box to hold (u, v)."""
    boxes[face, 0] = min(boxes[face, 0], u)
    boxes[face, 1] = max(boxes[face, 1], u)
    boxes[face, 2] = min(boxes[face, 2], v)
    boxes[face, 3] = max(boxes[face, 3], v)


@jit
def ray_extent(origin, points, stride, boxes):
    """``boxes[face]``: the lowest and highest u, then v, of the directions from
    ``origin`` of every ``stride``-th ray on each cube-map face (inf, -inf
    where there are none): the scan's extent, roughly, to size its samples
    by (``occupancy._coarsening``)."""
    _no_boxes(boxes)
    for row in range(0, points.shape[0], stride):
        x = points[row, 0] - origin[0]
        y = points[row, 1] - origin[1]
        z = points[row, 2] - origin[2]
        if x != 0.0 or y != 0.0 or z != 0.0:
            face, u, v = _face_uv(x, y, z)
            _take_in(boxes, face, u, v)


@jit(parallel=True)
def bin_rays(origin, points, q, q_coarse, bins, coarse, first, boxes):
    """Cube-map bin of each ray's direction from ``origin`` (``q`` x ``q`` per
    face, and ``q_coarse`` x ``q_coarse`` in ``coarse``); -1 for no ray (a
    point at the sensor). ``first[b]``: the first row in coarse bin ``b`` (a
    sample), or the number of rows where none is. ``boxes[face]``: the
    lowest and highest u, then v, of the rays on each face (inf, -inf where
    there are none), merged from each block's in block order.

    The offset to the point is binned as it is: dividing by its length, as
    ``sensor_ray`` does, moves (u, v) by an ulp or so, well inside the 1e-12
    that every bound on a bin's contents is widened by.
    """
    n_rays = points.shape[0]
    n_blocks = (n_rays + BLOCK - 1) // BLOCK
    block_boxes = np.empty((n_blocks, 6, 4), dtype=np.float64)
    for b in prange(first.shape[0]):
        first[b] = n_rays
    for block in prange(n_blocks):
        box = block_boxes[block]
        _no_boxes(box)
        for row in range(block * BLOCK, min(n_rays, (block + 1) * BLOCK)):
            x = points[row, 0] - origin[0]
            y = points[row, 1] - origin[1]
            z = points[row, 2] - origin[2]
            if x == 0.0 and y == 0.0 and z == 0.0:
                bins[row] = -1
                coarse[row] = -1
            else:
                face, u, v = _face_uv(x, y, z)
                bins[row] = (face * q + _bin_of(u, q)) * q + _bin_of(v, q)
                b = (face * q_coarse + _bin_of(u, q_coarse)) * q_coarse + _bin_of(v, q_coarse)
                coarse[row] = b
                # Rows rise within a block: the locked minimum only for the
                # first of a bin here, and only while no earlier row is in.
                lower_to(first, b, row)
                _take_in(box, face, u, v)
    _no_boxes(boxes)
    for block in range(n_blocks):  # minima and maxima: the same in any order
        for face in range(6):
            other = block_boxes[block, face]
            boxes[face, 0] = min(boxes[face, 0], other[0])
            boxes[face, 1] = max(boxes[face, 1], other[1])
            boxes[face, 2] = min(boxes[face, 2], other[2])
            boxes[face, 3] = max(boxes[face, 3], other[3])


@jit(inline="always")
def is_sample(coarse, first, row):
    """Whether ``row`` is its coarse bin's sample, its first ray (``bin_rays``)."""
    b = coarse[row]
    return b >= 0 and first[b] == row


# ``ray_cone`` takes the bins in blocks of this many, in turn; it sums their
# centres block by block, then the blocks' sums in order: the same sum, bit
# for bit, on any number of threads.
CONE_BLOCK = 256


@jit(inline="always")
def _bin_corner(b, q, du, dv):
    """Unit direction of a point of cube-map bin ``b`` (``q`` x ``q`` per face):
    ``du``, ``dv`` in [0, 1] across it (0.5, 0.5: its centre)."""
    face = b // (q * q)
    rest = b - face * q * q
    step = 2.0 / q
    u = -1.0 + (rest // q + du) * step
    v = -1.0 + (rest % q + dv) * step
    sign = 1.0 - 2.0 * (face % 2)
    axis = face // 2
    if axis == 0:
        x, y, z = sign, u, v
    elif axis == 1:
        x, y, z = u, sign, v
    else:
        x, y, z = u, v, sign
    norm = math.sqrt(x * x + y * y + z * z)
    return x / norm, y / norm, z / norm


@jit(parallel=True)
def ray_cone(first, n_rays, q, workers, cone):
    """A cone holding every direction of the cube-map bins ``b`` with
    ``first[b] < n_rays`` (``q`` x ``q`` per face; ``bin_rays``: the bins that
    hold a ray), into ``cone``: (axis x, y, z, half-angle).

    The axis is the bins' centres' mean direction; the half-angle the largest
    angle from it to a bin's corner, plus 1e-9: a bin's directions form a
    convex cone, spanned by its corners, so a convex cone (one no wider than
    a half-space) that holds the corners holds the bin. A wider one is not
    convex, so then, and when the centres sum to zero, the half-angle is pi
    (+ 1e-9): every direction.

    Both passes run on ``workers`` threads, which take blocks of bins
    (``CONE_BLOCK``) in turn: the bins with rays lie together, where the scan
    looks. The sum goes block by block, so the cone does not depend on the
    thread count.
    """
    n = first.shape[0]
    n_blocks = (n + CONE_BLOCK - 1) // CONE_BLOCK
    sums = np.empty((n_blocks, 3), dtype=np.float64)
    lows = np.empty(n_blocks, dtype=np.float64)
    counter = np.zeros(1, dtype=np.int64)
    for worker in prange(workers):
        block = take(counter, n_blocks)
        while block >= 0:
            sx = 0.0
            sy = 0.0
            sz = 0.0
            held = False
            for b in range(block * CONE_BLOCK, min(n, (block + 1) * CONE_BLOCK)):
                if first[b] < n_rays:
                    x, y, z = _bin_corner(b, q, 0.5, 0.5)
                    sx += x
                    sy += y
                    sz += z
                    held = True
            sums[block, 0] = sx  # once a block: neighbouring blocks share cache lines
            sums[block, 1] = sy
            sums[block, 2] = sz
            lows[block] = 1.0 if held else 2.0  # 2: no bin here, the next pass skips it
            block = take(counter, n_blocks)
    ax = 0.0
    ay = 0.0
    az = 0.0
    for block in range(n_blocks):
        ax += sums[block, 0]
        ay += sums[block, 1]
        az += sums[block, 2]
    norm = math.sqrt(ax * ax + ay * ay + az * az)
    if not norm > 0.0:  # directions all round, in balance (or none): no mean direction
        cone[0] = 1.0
        cone[1] = 0.0
        cone[2] = 0.0
        cone[3] = math.pi + 1e-9
        return
    ax /= norm
    ay /= norm
    az /= norm
    counter[0] = 0
    for worker in prange(workers):
        block = take(counter, n_blocks)
        while block >= 0:
            if lows[block] < 2.0:
                low = 1.0
                for b in range(block * CONE_BLOCK, min(n, (block + 1) * CONE_BLOCK)):
                    if first[b] < n_rays:
                        for corner in range(4):
                            x, y, z = _bin_corner(b, q, corner % 2, corner // 2)
                            low = min(low, x * ax + y * ay + z * az)
                lows[block] = low
            block = take(counter, n_blocks)
    lowest = 1.0  # min is exact in any order
    for block in range(n_blocks):
        lowest = min(lowest, lows[block])
    cone[0] = ax
    cone[1] = ay
    cone[2] = az
    # Wider than a half-space, the cone is no longer convex: a bin could hold
    # directions outside it with every corner inside. It is then the sphere.
    cone[3] = math.acos(lowest) + 1e-9 if lowest >= 0.0 else math.pi + 1e-9


@jit(parallel=True)
def columns_in_view(origin, grid, rays, view):
    """``view[column]`` = 1 where a direction from ``origin`` to the column (at
    rho >= rho_min) may lie in the rays' cone (``rays``: axis x, y, z and
    half-angle), else 0: no ray meets that column.

    Seen from the sensor, a point at rho >= rho_min lies within asin(|origin|
    / rho_min) of its direction from the centre; a column's directions from
    the centre lie within half its theta and phi widths of its middle one
    (the bisector of its edges), at most ``half`` for the grid's widest.
    """
    n_theta = grid.theta_edges.shape[0] - 1
    n_phi = grid.phi_edges.shape[0] - 1
    ox = origin[0]
    oy = origin[1]
    oz = origin[2]
    parallax = math.asin(math.sqrt(ox * ox + oy * oy + oz * oz) / grid.rho_edges[0])
    half = 0.0
    for j in range(n_theta):
        half = max(half, grid.theta_edges[j + 1] - grid.theta_edges[j])
    widest_phi = 0.0
    for k in range(n_phi):
        widest_phi = max(widest_phi, grid.phi_edges[k + 1] - grid.phi_edges[k])
    reach = rays[3] + 0.5 * (half + widest_phi) + parallax + 1e-9
    least = math.cos(reach) if reach < math.pi else -2.0
    for column in prange(n_theta * n_phi):
        j = column // n_phi
        k = column % n_phi
        sin_t = grid.theta_sin[j] + grid.theta_sin[j + 1]
        cos_t = grid.theta_cos[j] + grid.theta_cos[j + 1]
        sin_p = grid.phi_sin[k] + grid.phi_sin[k + 1]
        cos_p = grid.phi_cos[k] + grid.phi_cos[k + 1]
        flat = math.sqrt(sin_t * sin_t + cos_t * cos_t)
        tall = math.sqrt(sin_p * sin_p + cos_p * cos_p)
        if flat == 0.0 or tall == 0.0:
            view[column] = 1  # a half-turn wide: no bisector, keep it
            continue
        scale = cos_p / (flat * tall)
        cosine = (scale * sin_t * rays[0] + sin_p / tall * rays[1] + scale * cos_t * rays[2])
        view[column] = cosine >= least - 1e-12


@jit(parallel=True)
def near_masks(words, n_rho, skip, view, masks, workers):
    """Bit i of ``masks[column]``: cell (i, column) is flagged, for i < ``skip``.

    Only columns in ``view`` are read (no ray meets the others), in blocks
    that the ``workers`` take in turn (``in_turn``). ``words`` are the flags
    (a byte per cell, column-major) seen as uint64: eight cells with no flag
    are passed over at once.
    """
    n_columns = masks.shape[0]
    step, n_blocks, counter = in_turn(n_columns, workers, BLOCK)
    for worker in prange(workers):
        block = take(counter, n_blocks)
        while block >= 0:
            for column in range(block * step, min(n_columns, (block + 1) * step)):
                mask = np.uint64(0)
                i = 0
                while i < (skip if view[column] else 0):
                    # The word holding cell i: its bytes (little-endian) are
                    # the cells from ``index`` to the word's end.
                    index = column * n_rho + i
                    word = index // 8
                    flags = words[word]
                    if flags != 0:
                        for cell in range(index, min(word * 8 + 8, column * n_rho + skip)):
                            if (flags >> np.uint64(8 * (cell - word * 8))) & np.uint64(0xFF):
                                mask |= np.uint64(1) << np.uint64(cell - column * n_rho)
                    i = word * 8 + 8 - column * n_rho
                masks[column] = mask
            block = take(counter, n_blocks)


# The largest angle between a cube-map face's axis and a direction of that face.
FACE_REACH = math.acos(1.0 / math.sqrt(3.0))


# A cell's shadow is bounded through its angular patch split into parts of at
# most this span (theta + phi, radians), and at most MAX_PARTS x MAX_PARTS.
SUBPATCH_SPAN = 0.05
MAX_PARTS = 12
MAX_CORNERS = 2 * (MAX_PARTS + 1) ** 2


@jit(inline="always")
def _split_point(edges, sines, cosines, index, step, parts):
    """Sine and cosine of the angle ``step`` / ``parts`` of the way from edge
    ``index`` to the next: the edges' own where the split meets them."""
    if step == 0:
        return sines[index], cosines[index]
    if step == parts:
        return sines[index + 1], cosines[index + 1]
    angle = edges[index] + (edges[index + 1] - edges[index]) * step / parts
    return math.sin(angle), math.cos(angle)


@jit(inline="always")
def _mark_shadow(ox, oy, oz, grid, i, j, k, q, rays, boxes, corners, limit):
    """Lower to ``i`` the ``limit`` of every bin holding a direction from (ox, oy, oz)
    that meets cell (i, j, k).

    The angular patch is split in ``parts`` x ``parts`` (``SUBPATCH_SPAN``),
    and the cell lies within ``sag`` of the convex hull of the parts' corners
    on both spheres (a curved face bulges by at most r1 (1 - cos(D / 2)) over
    a part of angular span D), and so within ``radius`` of their centroid g
    (``corners``: scratch of shape (3, ``MAX_CORNERS``)): the directions meeting it
    are within ``alpha`` of g's. None of them is a ray's when that cap misses
    the rays' cone (``rays``: axis x, y, z and half-angle), and none is a
    face's when the cap misses its directions (within 54.7 degrees of its
    axis). On a face that all the corners point along, the hull's directions
    project into the bounding box of the corners' (u, v), and the cell's
    within ``spread`` of them. Otherwise the whole face's bins are lowered.
    """
    r0 = grid.rho_edges[i]
    r1 = grid.rho_edges[i + 1]
    width = grid.theta_edges[j + 1] - grid.theta_edges[j]
    height = grid.phi_edges[k + 1] - grid.phi_edges[k]
    # Corners of a parts x parts split of the angular patch, on both spheres:
    # the finer the split, the closer the hull hugs the curved faces.
    parts = min(max(int(math.ceil((width + height) / SUBPATCH_SPAN)), 1), MAX_PARTS)
    sag = r1 * (1.0 - math.cos(min(0.5 * (width + height) / parts, 0.5 * math.pi)))
    spread = 1.6 * sag / (r0 - math.sqrt(ox * ox + oy * oy + oz * oz)) + 1e-9
    n_points = 2 * (parts + 1) * (parts + 1)
    gx = 0.0
    gy = 0.0
    gz = 0.0
    c = 0
    for radius in (r0, r1):
        for a in range(parts + 1):
            sin_t, cos_t = _split_point(grid.theta_edges, grid.theta_sin, grid.theta_cos, j, a,
                                        parts)
            for b in range(parts + 1):
                sin_p, cos_p = _split_point(grid.phi_edges, grid.phi_sin, grid.phi_cos, k, b,
                                            parts)
                flat = radius * cos_p
                corners[0, c] = flat * sin_t - ox
                corners[1, c] = radius * sin_p - oy
                corners[2, c] = flat * cos_t - oz
                gx += corners[0, c] / n_points
                gy += corners[1, c] / n_points
                gz += corners[2, c] / n_points
                c += 1
    reach2 = 0.0
    for c in range(n_points):
        reach2 = max(reach2, (corners[0, c] - gx) ** 2 + (corners[1, c] - gy) ** 2
                     + (corners[2, c] - gz) ** 2)
    radius = (math.sqrt(reach2) + sag) * (1.0 + 1e-9)
    distance = math.sqrt(gx * gx + gy * gy + gz * gz)
    everything = radius >= distance  # the sensor inside the ball: no cap
    alpha = math.asin(min(radius / distance, 1.0)) + 1e-9
    ex = gx / distance
    ey = gy / distance
    ez = gz / distance
    # An angle above a bound is a cosine below the bound's cosine (acos
    # falls on [-1, 1]): one cos per bound, not an acos per test (up to
    # seven a cell; 8-10% of ``mark_candidates``). Rounding can turn a test
    # only within an ulp or so of its bound, well inside the 1e-9 in alpha.
    face_least = -2.0  # the cap meets every face
    if not everything:
        reach = rays[3] + alpha
        if reach < math.pi and ex * rays[0] + ey * rays[1] + ez * rays[2] < math.cos(reach):
            return  # no ray's direction meets the cell
        if FACE_REACH + alpha < math.pi:
            face_least = math.cos(FACE_REACH + alpha)
    for face in range(6):
        axis = face // 2
        sign = 1.0 - 2.0 * (face % 2)
        along = sign * (ex if axis == 0 else (ey if axis == 1 else ez))
        if along < face_least:
            continue  # the cap misses this face's directions
        u_min = np.inf
        u_max = -np.inf
        v_min = np.inf
        v_max = -np.inf
        front = True
        for c in range(n_points):
            major, u, v = _on_face(face, corners[0, c], corners[1, c], corners[2, c])
            front = front and major > 0.0
            u_min = min(u_min, u)
            u_max = max(u_max, u)
            v_min = min(v_min, v)
            v_max = max(v_max, v)
        # The rays on this face lie in its box (``bin_rays``), to within the
        # 1e-12 that every bound on a bin's contents is widened by.
        u_low = boxes[face, 0] - 1e-12
        u_high = boxes[face, 1] + 1e-12
        v_low = boxes[face, 2] - 1e-12
        v_high = boxes[face, 3] + 1e-12
        if front and spread <= 0.1:
            # A direction of the face is within 54.7 degrees of its axis, one
            # ``spread`` from it within 60.5, where the projection's scale is
            # below 1 / cos^2 = 4.21.
            widen = 4.25 * spread + 1e-12
            u_low = max(u_low, u_min - widen)
            u_high = min(u_high, u_max + widen)
            v_low = max(v_low, v_min - widen)
            v_high = min(v_high, v_max + widen)
        if not (u_low <= u_high and v_low <= v_high):
            continue  # no ray on this face meets the cell (or none is on it)
        u_from = _bin_of(u_low, q)
        u_to = _bin_of(u_high, q)
        v_from = _bin_of(v_low, q)
        v_to = _bin_of(v_high, q)
        for bu in range(u_from, u_to + 1):
            for bv in range(v_from, v_to + 1):
                index = (face * q + bu) * q + bv
                lower_to(limit, index, i)  # shared by all threads


@jit(parallel=True)
def mark_candidates(origin, grid, masks, skip, q, rays, view, boxes, limit, workers):
    """Set ``limit[bin]`` to the lowest shell below ``skip`` of a cell that a
    walked ray with a direction in that bin might flag while the sampled rays
    (``masks``) did not (``skip`` where there is none).

    Such a cell is the first on a ray's walk that the samples missed: either
    the ray's first cell (shell 0) or a neighbour of one they flagged. A walk
    moves between cells that share a face, across the theta seam, or, at the
    y axis, between any two columns of a polar row (the grid's ranges are
    full), so neighbours are taken in the 3 x 3 x 3 block around a cell, and
    every column of a polar row neighbours the others. ``rays``: a cone (axis
    x, y, z and half-angle) holding every ray's direction; columns not in
    ``view`` (``columns_in_view``) are passed over; the ``workers`` (one per
    thread) take blocks of columns in turn (``in_turn``) and lower the one
    ``limit`` together (``atomic.lower_to``: a minimum, the same on any
    number of threads).
    """
    n_theta = grid.theta_edges.shape[0] - 1
    n_phi = grid.phi_edges.shape[0] - 1
    below = (np.uint64(1) << np.uint64(skip)) - np.uint64(1)
    pole_low = np.uint64(0)
    pole_high = np.uint64(0)
    for j in range(n_theta):
        pole_low |= masks[j * n_phi]
        pole_high |= masks[j * n_phi + n_phi - 1]
    n_bins = limit.shape[0]
    for block in prange((n_bins + BLOCK - 1) // BLOCK):
        limit[block * BLOCK:min(n_bins, (block + 1) * BLOCK)] = skip
    n_columns = n_theta * n_phi
    step, n_blocks, counter = in_turn(n_columns, workers, BLOCK)
    for worker in prange(workers):
        corners = np.empty((3, MAX_CORNERS), dtype=np.float64)
        block = take(counter, n_blocks)
        while block >= 0:
            for column in range(block * step, min(n_columns, (block + 1) * step)):
                if view[column]:
                    _mark_column_candidates(origin[0], origin[1], origin[2], grid, masks, skip,
                                            q, column // n_phi, column % n_phi, below, pole_low,
                                            pole_high, rays, boxes, corners, limit)
            block = take(counter, n_blocks)


@jit(inline="always")
def _mark_column_candidates(ox, oy, oz, grid, masks, skip, q, j, k, below, pole_low, pole_high,
                            rays, boxes, corners, limit):
    """``mark_candidates`` for column (j, k)."""
    n_theta = grid.theta_edges.shape[0] - 1
    n_phi = grid.phi_edges.shape[0] - 1
    one = np.uint64(1)
    grown = one  # shell 0: any ray's first cell
    for dj in range(-1, 2):
        jj = (j + dj) % n_theta
        for dk in range(-1, 2):
            kk = k + dk
            if 0 <= kk < n_phi:
                near = masks[jj * n_phi + kk]
                grown |= near | (near << one) | (near >> one)
    if k == 0:
        grown |= pole_low | (pole_low << one) | (pole_low >> one)
    if k == n_phi - 1:
        grown |= pole_high | (pole_high << one) | (pole_high >> one)
    candidates = grown & ~masks[j * n_phi + k] & below
    for i in range(skip):
        if (candidates >> np.uint64(i)) & one:
            _mark_shadow(ox, oy, oz, grid, i, j, k, q, rays, boxes, corners, limit)
