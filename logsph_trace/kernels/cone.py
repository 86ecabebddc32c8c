"""Sample the rays of cones, and aggregate their traces into weighted cells (``@jit`` only).

A cone's rays stay close to each other, so at each radius the cells they
cross fill a small box of (theta, phi) index space; the boxes are addressed
densely (no hashing, no sort of all segments). The azimuth is shifted by
``j_shift`` first, so a cone straddling the theta seam still makes a compact
box.
"""

import math

import numpy as np
from numba import prange

from .._jit import jit

# The Fibonacci spiral's step around the axis: pi (3 - sqrt(5)) radians.
GOLDEN_ANGLE = math.pi * (3.0 - math.sqrt(5.0))


@jit(inline="always")
def _frame(x, y, z):
    """Two unit vectors completing the unit axis (x, y, z) to a right-handed
    orthonormal frame, as six numbers: first = axis x helper, normalised;
    second = axis x first."""
    if abs(x) < 0.9:  # helper (1, 0, 0)
        first_x, first_y, first_z = 0.0, z, -y
    else:  # helper (0, 1, 0)
        first_x, first_y, first_z = -z, 0.0, x
    length = math.sqrt(first_x * first_x + first_y * first_y + first_z * first_z)
    first_x, first_y, first_z = first_x / length, first_y / length, first_z / length
    return (first_x, first_y, first_z,
            y * first_z - z * first_y, z * first_x - x * first_z, x * first_y - y * first_x)


@jit(inline="always")
def _ray_angles(index, n_rays, half_angle, fibonacci, rings):
    """Angle from the axis and angle around it of ray ``index`` of a cone's
    ``n_rays`` (see ``sample_cones``)."""
    if fibonacci:
        cos_angle = 1.0 - (1.0 - math.cos(half_angle)) * (index + 0.5) / n_rays
        return math.acos(min(max(cos_angle, -1.0), 1.0)), index * GOLDEN_ANGLE
    if index == 0:
        return 0.0, 0.0
    # Ring r holds rays 1 + 3 r (r - 1) to 3 r (r + 1), 6 r of them; the root
    # is off by at most one either way in floating point.
    ring = max(1, int(math.ceil((-3.0 + math.sqrt(9.0 + 12.0 * index)) / 6.0)))
    while 3 * ring * (ring + 1) < index:
        ring += 1
    while ring > 1 and 3 * ring * (ring - 1) >= index:
        ring -= 1
    count = 6 * ring
    around = 2.0 * math.pi * ((index - 1 - 3 * ring * (ring - 1)) + 0.5 * (ring % 2)) / count
    return half_angle * ring / rings, around


@jit(inline="always")
def normalise(weights):
    """Divide ``weights`` by their sum in place, unless it is not positive.

    The sum is compensated (Neumaier), so its error does not grow with the
    count. One definition for every path: a cone's weights come out the
    same, bit for bit, however many cones a call holds.
    """
    total = 0.0
    compensation = 0.0
    for index in range(weights.shape[0]):
        value = weights[index]
        new_total = total + value
        if abs(total) >= abs(value):
            compensation += (total - new_total) + value
        else:
            compensation += (value - new_total) + total
        total = new_total
    total += compensation
    if total > 0:
        for index in range(weights.shape[0]):
            weights[index] /= total


RADIX_BITS = 11  # digits of the first-reach sort: six passes over a 64-bit key


@jit(runtime=True)
def first_reach_order(t_first):
    """Return the indices that sort ``t_first`` ascending, equal values in the order given.

    numpy's ``argsort(kind="stable")`` for any values but NaN, at a third of
    numba's merge sort's cost on a cone's ~2,000 cells: a least-significant-
    digit radix sort of the values' bits, ``RADIX_BITS`` at a time, which
    is stable by construction. The bits are mapped so that their order as
    unsigned integers is the numbers' order (negative numbers flipped, the
    sign bit set on the others), after ``+ 0.0`` makes -0.0 into 0.0, its
    equal. A pass whose digit every key shares is skipped.
    """
    n = t_first.shape[0]
    keys = np.empty(n, dtype=np.uint64)
    sign = np.uint64(1) << np.uint64(63)
    for row in range(n):
        bits = np.float64(t_first[row] + 0.0).view(np.uint64)
        keys[row] = ~bits if bits & sign else bits | sign
    order = np.arange(n)
    if n < 2:
        return order
    other_keys = np.empty(n, dtype=np.uint64)
    other_order = np.empty(n, dtype=np.int64)
    digits = np.uint64((1 << RADIX_BITS) - 1)
    count = np.empty(1 << RADIX_BITS, dtype=np.int64)
    for low_bit in range(0, 64, RADIX_BITS):
        shift = np.uint64(low_bit)
        count[:] = 0
        for row in range(n):
            count[(keys[row] >> shift) & digits] += 1
        if count[(keys[0] >> shift) & digits] == n:
            continue
        total = 0
        for digit in range(count.shape[0]):
            total, count[digit] = total + count[digit], total
        for row in range(n):
            digit = (keys[row] >> shift) & digits
            other_keys[count[digit]] = keys[row]
            other_order[count[digit]] = order[row]
            count[digit] += 1
        keys, other_keys = other_keys, keys
        order, other_order = other_order, order
    return order


@jit
def sample_cones(axes, half_angles, ray_at, fibonacci, rings, sigmas, directions, angles,
                 weights):
    """Sample the rays of many cones.

    Cone ``c`` has the unit axis ``axes[c]``, the half-angle ``half_angles[c]``
    and rays ``ray_at[c]:ray_at[c + 1]`` of the outputs ``directions`` (n, 3),
    ``angles`` (n,) (each ray's angle from the axis) and ``weights`` (n,).
    One ray is the axis alone. ``fibonacci``: a Fibonacci spiral over the
    cap, ray i at cos(angle) = 1 - (1 - cos h) (i + 0.5) / n, i golden
    angles around (equal solid angle per ray); else the axis and
    ``rings[c]`` rings of 6 r rays at angles r h / rings[c], odd rings
    turned by half a step (the count must be 1 + 3 R (R + 1)). Weights:
    ``exp(-angle^2 / (2 sigma^2))`` for ``sigmas[c] > 0``, relative to the
    ray nearest the axis (a tiny sigma cannot underflow them all), else
    uniform; normalised per cone (``normalise``). On one thread: a cone's
    few thousand rays take microseconds, and a parallel loop would take
    seconds more to compile on the first call.

    Each ray depends only on its cone and its index in it, so a cone's rays
    are the same bits whatever else the call holds: :func:`trace_cone` and
    :func:`trace_cones` sample through this one kernel.
    """
    n_cones = ray_at.shape[0] - 1
    c = 0
    for ray in range(ray_at[n_cones]):
        while ray >= ray_at[c + 1]:
            c += 1
        start, n_rays = ray_at[c], ray_at[c + 1] - ray_at[c]
        x, y, z = axes[c, 0], axes[c, 1], axes[c, 2]
        if n_rays == 1:
            directions[ray, 0], directions[ray, 1], directions[ray, 2] = x, y, z
            angles[ray] = 0.0
            weights[ray] = 0.0  # the exponent
            continue
        first_x, first_y, first_z, second_x, second_y, second_z = _frame(x, y, z)
        angle, around = _ray_angles(ray - start, n_rays, half_angles[c], fibonacci, rings[c])
        cos_around, sin_around = math.cos(around), math.sin(around)
        cos_angle, sin_angle = math.cos(angle), math.sin(angle)
        directions[ray, 0] = cos_angle * x + sin_angle * (cos_around * first_x
                                                          + sin_around * second_x)
        directions[ray, 1] = cos_angle * y + sin_angle * (cos_around * first_y
                                                          + sin_around * second_y)
        directions[ray, 2] = cos_angle * z + sin_angle * (cos_around * first_z
                                                          + sin_around * second_z)
        angles[ray] = angle
        weights[ray] = -0.5 * (angle / sigmas[c]) ** 2 if sigmas[c] > 0 else 0.0
    for c in range(n_cones):
        largest = -np.inf  # the largest exponent: the ray nearest the axis
        nearest = np.inf
        for ray in range(ray_at[c], ray_at[c + 1]):
            largest = max(largest, weights[ray])
            nearest = min(nearest, angles[ray])
        for ray in range(ray_at[c], ray_at[c + 1]):
            # A sigma so small that every exponent is -inf (1e-170 rad): all the
            # weight goes to the rays nearest the axis, the limit of the Gaussian.
            weights[ray] = (math.exp(weights[ray] - largest) if largest > -np.inf
                            else (1.0 if angles[ray] == nearest else 0.0))
        normalise(weights[ray_at[c]:ray_at[c + 1]])


@jit
def shifted(j, j_shift, n_theta):
    """(j + j_shift) mod n_theta for 0 <= j, j_shift < n_theta, without a division."""
    shifted = np.int64(j) + j_shift
    return shifted - n_theta if shifted >= n_theta else shifted


@jit(inline="always")
def _no_extents(rows, n_rho):
    """``rows`` x ``n_rho`` empty extents for ``_extents_of``: (low_j, high_j,
    low_k, high_k), the lows the largest int64, the highs -1."""
    big = np.iinfo(np.int64).max
    return (np.full((rows, n_rho), big, dtype=np.int64), np.full((rows, n_rho), -1, dtype=np.int64),
            np.full((rows, n_rho), big, dtype=np.int64), np.full((rows, n_rho), -1, dtype=np.int64))


@jit(inline="always")
def _extents_of(seg_from, seg_to, cells, n_theta, j_shift, low_j, high_j, low_k, high_k):
    """Widen the per-shell extents (n_rho,) of shifted theta and phi indices to
    hold segments ``seg_from:seg_to``.

    A ray's segments come in runs within one shell (3.7 segments a run in
    50 default cones): a run's extents stay in registers and are stored
    once, which took a fifth off this pass, where each segment loaded and
    stored the four extents of its shell.
    """
    shell = -1
    run_low_j = run_high_j = run_low_k = run_high_k = 0
    for seg in range(seg_from, seg_to):
        i = np.int64(cells[seg, 0])
        j = shifted(cells[seg, 1], j_shift, n_theta)
        k = np.int64(cells[seg, 2])
        if i == shell:
            run_low_j, run_high_j = min(run_low_j, j), max(run_high_j, j)
            run_low_k, run_high_k = min(run_low_k, k), max(run_high_k, k)
            continue
        if shell >= 0:
            _widen(shell, run_low_j, run_high_j, run_low_k, run_high_k, low_j, high_j, low_k,
                   high_k)
        shell, run_low_j, run_high_j, run_low_k, run_high_k = i, j, j, k, k
    if shell >= 0:
        _widen(shell, run_low_j, run_high_j, run_low_k, run_high_k, low_j, high_j, low_k, high_k)


@jit(inline="always")
def _widen(i, run_low_j, run_high_j, run_low_k, run_high_k, low_j, high_j, low_k, high_k):
    """Widen shell ``i``'s extents to hold a run's."""
    low_j[i] = min(low_j[i], run_low_j)
    high_j[i] = max(high_j[i], run_high_j)
    low_k[i] = min(low_k[i], run_low_k)
    high_k[i] = max(high_k[i], run_high_k)


@jit(inline="always")
def _box_layout(offsets, starts, firsts, cells, n_rho, n_theta, j_shift):
    """Per shell, the (theta, phi) box the chunks' segments fill, laid end to end.

    Returns (low_j, low_k, span_k, base): shell ``i``'s box starts at
    ``base[i]``, cell (i, j, k) is at ``base[i] + (j' - low_j[i]) * span_k[i] +
    k - low_k[i]`` with ``j'`` the shifted azimuth; ``base[n_rho]`` is the
    total. Each chunk finds its own extents (in parallel: the function is
    inlined into its parallel callers, so its ``prange`` is theirs), then
    they are merged.
    """
    n_chunks = starts.shape[0] - 1
    low_j, high_j, low_k, high_k = _no_extents(n_chunks, n_rho)
    for chunk in prange(n_chunks):
        _extents_of(firsts[chunk], offsets[starts[chunk + 1]], cells, n_theta, j_shift,
                    low_j[chunk], high_j[chunk], low_k[chunk], high_k[chunk])
    for i in range(n_rho):  # n_rho x n_chunks values: too few to share out
        for chunk in range(1, n_chunks):
            low_j[0, i] = min(low_j[0, i], low_j[chunk, i])
            high_j[0, i] = max(high_j[0, i], high_j[chunk, i])
            low_k[0, i] = min(low_k[0, i], low_k[chunk, i])
            high_k[0, i] = max(high_k[0, i], high_k[chunk, i])
    span_k, base = box_bases(low_j[0], high_j[0], low_k[0], high_k[0])
    return low_j[0], low_k[0], span_k, base


@jit(runtime=True)
def box_bases(low_j, high_j, low_k, high_k):
    """One cone's boxes from its per-shell extents (n_rho,) (``high_j`` -1: a
    shell no ray reached): (span_k (n_rho,), base (n_rho + 1,)), as in
    ``_box_layout``."""
    n_rho = low_j.shape[0]
    span_k = np.zeros(n_rho, dtype=np.int64)
    base = np.zeros(n_rho + 1, dtype=np.int64)
    for i in range(n_rho):
        if high_j[i] >= 0:
            span_k[i] = high_k[i] - low_k[i] + 1
            base[i + 1] = base[i] + (high_j[i] - low_j[i] + 1) * span_k[i]
        else:
            base[i + 1] = base[i]
    return span_k, base


@jit(inline="always")
def _box_copies(pool, ray_pool, needed):
    """Flat scratch for ``needed`` boxes and chunks: (weights, first reaches,
    last rays), from the caller's ``pool`` (float64, two values a box and
    chunk) and ``ray_pool`` (int64, one) when they are large enough, else
    allocated (see ``_boxes``)."""
    if pool.shape[0] >= 2 * needed and ray_pool.shape[0] >= needed:
        return pool[:needed], pool[needed:2 * needed], ray_pool[:needed]
    return np.empty(needed), np.empty(needed), np.empty(needed, dtype=np.int64)


@jit(inline="always")
def _boxes(offsets, starts, firsts, cells, n_rho, n_theta, j_shift, pool, ray_pool):
    """The layout (``_box_layout``) and, per chunk, its empty boxes: summed
    value 0, first reach inf, last ray -1 (none). Each chunk's boxes are
    filled by the thread that will use them (first touch on its own core).

    The boxes are taken from the caller's ``pool`` (float64, two values a
    box and chunk) and ``ray_pool`` (int64, one) when they are large
    enough, else allocated. Fresh memory here was the cost: a 1,000-ray cone
    in 16 chunks spent 0.5 ms of its 1.7 ms aggregation in page faults of
    its 1.1 MB of copies, whenever the allocator handed back pages it had
    just returned to the system. Returns the layout, the boxes and how many
    values ``ray_pool`` needs (``pool`` twice as many).
    """
    layout = _box_layout(offsets, starts, firsts, cells, n_rho, n_theta, j_shift)
    n_chunks = starts.shape[0] - 1
    size = layout[3][n_rho]
    needed = n_chunks * size
    weight, first, last_ray = _box_copies(pool, ray_pool, needed)
    weight = weight.reshape((n_chunks, size))
    first = first.reshape((n_chunks, size))
    last_ray = last_ray.reshape((n_chunks, size))
    for chunk in prange(n_chunks):
        for box in range(size):
            weight[chunk, box] = 0.0
            first[chunk, box] = np.inf
            last_ray[chunk, box] = -1
    return layout, weight, first, last_ray, needed


@jit(inline="always")
def box_of(cells, seg, low_j, low_k, span_k, base, n_theta, j_shift):
    """The box index of segment ``seg``'s cell (see ``_box_layout``)."""
    i = cells[seg, 0]
    j = shifted(cells[seg, 1], j_shift, n_theta)
    return base[i] + (j - low_j[i]) * span_k[i] + (cells[seg, 2] - low_k[i])


@jit(inline="always")
def unbox(box, i, low_j, low_k, span_k, base, n_theta, j_shift):
    """The (j, k) of box ``box`` of shell ``i``: ``box_of``'s inverse."""
    offset = box - base[i]
    return (shifted(offset // span_k[i] + low_j[i], n_theta - j_shift, n_theta),
            offset % span_k[i] + low_k[i])


@jit(inline="always")
def _box_cells(weight, first, last_ray, low_j, low_k, span_k, base, n_theta, j_shift):
    """Sum the chunks' boxes into chunk 0's; return the boxes some ray reached as
    (cells (u, 3) int32, weights (u,), t_first (u,)), unsorted: shell by shell,
    in box order. Both passes run one shell per ``prange`` iteration (inlined
    into the parallel callers); the chunks are summed in chunk order, so the
    sums do not depend on the thread count.

    A shell's boxes are summed a chunk at a time, along the rows: box by box,
    each chunk's value was a row (a cache line) away from the last, and with
    1,000 rays on one thread the sum took about 55 us more per chunk.
    """
    n_rho = base.shape[0] - 1
    reached = np.zeros(n_rho + 1, dtype=np.int64)  # per shell, then where each shell's start
    for i in prange(n_rho):
        reached[i + 1] = _merge_shell(weight, first, last_ray, base, i)
    for i in range(n_rho):
        reached[i + 1] += reached[i]
    out_cells = np.empty((reached[n_rho], 3), dtype=np.int32)
    out_weight = np.empty(reached[n_rho])
    out_first = np.empty(reached[n_rho])
    for i in prange(n_rho):
        _write_shell(weight, first, last_ray, low_j, low_k, span_k, base, n_theta, j_shift, i,
                     reached[i], out_cells, out_weight, out_first)
    return out_cells, out_weight, out_first


@jit(inline="always")
def _merge_shell(weight, first, last_ray, base, i):
    """Sum shell ``i``'s boxes of every chunk into chunk 0's, in chunk order;
    return how many some ray reached."""
    for chunk in range(1, weight.shape[0]):
        for box in range(base[i], base[i + 1]):
            weight[0, box] += weight[chunk, box]
            first[0, box] = min(first[0, box], first[chunk, box])
            last_ray[0, box] = max(last_ray[0, box], last_ray[chunk, box])
    count = 0
    for box in range(base[i], base[i + 1]):
        count += last_ray[0, box] != -1
    return count


@jit(inline="always")
def _write_shell(weight, first, last_ray, low_j, low_k, span_k, base, n_theta, j_shift, i, at,
                 out_cells, out_weight, out_first):
    """Write shell ``i``'s reached boxes (merged into chunk 0), in box order,
    from row ``at`` of the outputs on; return the row after the last."""
    for box in range(base[i], base[i + 1]):
        if last_ray[0, box] == -1:
            continue
        out_cells[at, 0] = i
        out_cells[at, 1], out_cells[at, 2] = unbox(box, i, low_j, low_k, span_k, base, n_theta,
                                                   j_shift)
        out_weight[at] = weight[0, box]
        out_first[at] = first[0, box]
        at += 1
    return at


@jit(parallel=True)
def aggregate_boxes(offsets, starts, firsts, cells, t_enter, weights, n_rho, n_theta, j_shift,
                    pool, ray_pool):
    """Per cell: summed weight over the rays crossing it (each ray once), first t.

    Parameters: CSR ``offsets`` (m + 1,) into ``cells`` (K, 3) and ``t_enter``
    (K,): ray ``r``'s segments are ``offsets[r]:offsets[r + 1]``; ``starts``
    (c + 1,): chunks of rays, one ``prange`` iteration each; ``firsts`` (c,):
    where each chunk's first ray begins. Nothing else is read, so the arrays
    may hold gaps between chunks: the regions a parallel trace fills, where
    ``offsets[starts[c]]`` is the end of the previous region, not
    ``firsts[c]``. ``weights`` (m,): each ray's weight, added once to every
    cell it crosses. ``pool`` and ``ray_pool``: scratch for the chunks'
    boxes (``_boxes``). Returns (cells (u, 3) int32, weights (u,) float64
    unnormalised, t_first (u,) float64), unsorted, and the values
    ``ray_pool`` would need to hold the boxes (``pool``: twice as many).

    Each radial shell gets its own dense (theta, phi) box: at one radius the
    cone's footprint is a compact patch, so the boxes together stay small.
    Each chunk fills its own copy of the boxes (no shared writes); the copies
    are then summed, box by box.
    """
    (low_j, low_k, span_k, base), weight, first, last_ray, needed = _boxes(
        offsets, starts, firsts, cells, n_rho, n_theta, j_shift, pool, ray_pool)
    for chunk in prange(starts.shape[0] - 1):
        _add_rays(offsets, starts[chunk], starts[chunk + 1], firsts[chunk], cells, t_enter,
                  weights, low_j, low_k, span_k, base, n_theta, j_shift, weight[chunk],
                  first[chunk], last_ray[chunk])
    out_cells, out_weight, out_first = _box_cells(weight, first, last_ray, low_j, low_k, span_k,
                                                  base, n_theta, j_shift)
    return out_cells, out_weight, out_first, needed


@jit(inline="always")
def _add_rays(offsets, ray_from, ray_to, first_seg, cells, t_enter, weights, low_j, low_k,
              span_k, base, n_theta, j_shift, weight, first, last_ray):
    """Add rays ``ray_from:ray_to`` to one chunk's boxes (``weight``, ``first``,
    ``last_ray``: its rows); the first ray's segments begin at ``first_seg``."""
    for ray in range(ray_from, ray_to):
        begin = first_seg if ray == ray_from else offsets[ray]
        for seg in range(begin, offsets[ray + 1]):
            box = box_of(cells, seg, low_j, low_k, span_k, base, n_theta, j_shift)
            # Branch-free: a ray re-entering a cell counts once; first reach is a min.
            weight[box] += weights[ray] * (last_ray[box] != ray)
            last_ray[box] = ray
            first[box] = min(first[box], t_enter[seg])


@jit(parallel=True)
def aggregate_cones(offsets, cone_rays, bounds, cone_bounds, cells, t_enter, weights, n_rho,
                    n_theta, j_shifts, pool, ray_pool):
    """``aggregate_boxes`` for many cones at once, each sorted by first reach.

    The rays' packed CSR ``offsets``, ``cells``, ``t_enter`` and ``weights``
    are the cones' in turn: cone ``c``'s rays are ``cone_rays[c]:cone_rays[c
    + 1]``, cut into chunks at ``bounds[cone_bounds[c]:cone_bounds[c + 1]]``
    (ray indices, the cone's first and end included), azimuths shifted by
    ``j_shifts[c]``. Each cone is one ``prange`` iteration: its chunks are
    summed in order as ``aggregate_boxes`` sums them, so every cone's cells
    and sums are the ones ``aggregate_boxes`` gives for it alone, bit for
    bit, with no parallel call per cone. ``pool``, ``ray_pool``: scratch for
    the chunks' boxes, as there.

    Returns (cells (U, 3) int32, weights (U,), t_first (U,), at (c + 1,),
    found (c,), needed): cone ``c``'s cells are rows ``at[c]:at[c] +
    found[c]``, ordered by first reach (ties in box order, as a stable sort
    of ``aggregate_boxes``' output puts them), its weights normalised in
    that order as ``by_first_reach`` normalises them (``normalise``).
    """
    n_cones = cone_rays.shape[0] - 1
    low_j, high_j, low_k, high_k = _no_extents(n_cones, n_rho)
    for c in prange(n_cones):
        _extents_of(offsets[cone_rays[c]], offsets[cone_rays[c + 1]], cells, n_theta,
                    j_shifts[c], low_j[c], high_j[c], low_k[c], high_k[c])
    span_k = np.empty((n_cones, n_rho), dtype=np.int64)
    base = np.empty((n_cones, n_rho + 1), dtype=np.int64)
    at = np.zeros(n_cones + 1, dtype=np.int64)  # where each cone's boxes, and cells, start
    pool_at = np.zeros(n_cones + 1, dtype=np.int64)  # ... and its chunks' copies of them
    for c in range(n_cones):
        span_k[c], base[c] = box_bases(low_j[c], high_j[c], low_k[c], high_k[c])
        at[c + 1] = at[c] + base[c, n_rho]
        pool_at[c + 1] = pool_at[c] + (cone_bounds[c + 1] - cone_bounds[c] - 1) * base[c, n_rho]
    needed = pool_at[n_cones]
    weight_all, first_all, last_all = _box_copies(pool, ray_pool, needed)
    out_cells = np.empty((at[n_cones], 3), dtype=np.int32)
    out_weight = np.empty(at[n_cones])
    out_first = np.empty(at[n_cones])
    found = np.zeros(n_cones, dtype=np.int64)
    for c in prange(n_cones):
        n_chunks = cone_bounds[c + 1] - cone_bounds[c] - 1
        size = base[c, n_rho]
        weight = weight_all[pool_at[c]:pool_at[c + 1]].reshape((n_chunks, size))
        first = first_all[pool_at[c]:pool_at[c + 1]].reshape((n_chunks, size))
        last_ray = last_all[pool_at[c]:pool_at[c + 1]].reshape((n_chunks, size))
        weight[:, :] = 0.0
        first[:, :] = np.inf
        last_ray[:, :] = -1
        for chunk in range(n_chunks):
            ray_from = bounds[cone_bounds[c] + chunk]
            _add_rays(offsets, ray_from, bounds[cone_bounds[c] + chunk + 1], offsets[ray_from],
                      cells, t_enter, weights, low_j[c], low_k[c], span_k[c], base[c], n_theta,
                      j_shifts[c], weight[chunk], first[chunk], last_ray[chunk])
        end = at[c]
        for i in range(n_rho):
            _merge_shell(weight, first, last_ray, base[c], i)
            end = _write_shell(weight, first, last_ray, low_j[c], low_k[c], span_k[c], base[c],
                               n_theta, j_shifts[c], i, end, out_cells, out_weight, out_first)
        found[c] = end - at[c]
        order = first_reach_order(out_first[at[c]:end])
        cells_now = out_cells[at[c]:end].copy()
        weight_now = out_weight[at[c]:end].copy()
        first_now = out_first[at[c]:end].copy()
        for row in range(end - at[c]):
            out_cells[at[c] + row] = cells_now[order[row]]
            out_weight[at[c] + row] = weight_now[order[row]]
            out_first[at[c] + row] = first_now[order[row]]
        normalise(out_weight[at[c]:end])
    return out_cells, out_weight, out_first, at, found, needed


@jit(inline="always")
def stop_probability(log_odds, cells, seg, n_theta, n_phi, unknown, free_below):
    """The probability that segment ``seg``'s cell stops a gaze (see ``fixation_boxes``)."""
    value = log_odds[(cells[seg, 0] * n_theta + cells[seg, 1]) * n_phi + cells[seg, 2]]
    if value == 0:
        return unknown
    p = 1.0 / (1.0 + math.exp(-np.float64(value)))
    return 0.0 if p < free_below else p


@jit(parallel=True)
def fixation_boxes(offsets, starts, firsts, cells, t_enter, t_exit, weights, log_odds, n_theta,
                   n_phi, min_distance, unknown, free_below, j_shift, pool, ray_pool):
    """Per cell: summed over rays, weight x P(it is the first occupied cell the ray meets).

    The arrays and chunks as for ``aggregate_boxes``, plus ``t_exit`` and the
    flat map ``log_odds``. Only the cells the rays cross are turned into
    probabilities: ``unknown`` for a never-observed cell (log-odds 0), 0 below
    ``free_below``. Along a ray, P_first(c) = p_c times the product of
    (1 - p) over the distinct cells before c; a cell the ray re-enters adds
    nothing (had it been occupied, the ray would have stopped at the first
    entry), which the box's last ray tells in one load. Segments ending
    within ``min_distance`` are skipped. ``t_first`` is every cell's first
    reach, as in the cone. Returns as ``aggregate_boxes`` does.
    """
    n_rho = log_odds.shape[0] // (n_theta * n_phi)
    (low_j, low_k, span_k, base), weight, first, last_ray, needed = _boxes(
        offsets, starts, firsts, cells, n_rho, n_theta, j_shift, pool, ray_pool)
    for chunk in prange(starts.shape[0] - 1):
        for ray in range(starts[chunk], starts[chunk + 1]):
            begin = firsts[chunk] if ray == starts[chunk] else offsets[ray]
            clear = 1.0  # probability that nothing so far stopped the gaze
            for seg in range(begin, offsets[ray + 1]):
                box = box_of(cells, seg, low_j, low_k, span_k, base, n_theta, j_shift)
                first[chunk, box] = min(first[chunk, box], t_enter[seg])
                if t_exit[seg] <= min_distance:
                    continue  # not counted, and not seen: met again beyond, it counts there
                if last_ray[chunk, box] == ray:
                    continue  # re-entered: counted at its first entry
                last_ray[chunk, box] = ray
                p = stop_probability(log_odds, cells, seg, n_theta, n_phi, unknown, free_below)
                weight[chunk, box] += weights[ray] * p * clear
                clear *= 1.0 - p
    out_cells, out_weight, out_first = _box_cells(weight, first, last_ray, low_j, low_k, span_k,
                                                  base, n_theta, j_shift)
    return out_cells, out_weight, out_first, needed


@jit(runtime=True)
def sparse_cone(offsets, starts, firsts, cells, t_enter, t_exit, weights, log_odds, n_theta,
                n_phi, j_shift, fixation, min_distance, unknown, free_below, slots):
    """``aggregate_boxes`` (``fixation`` False) or ``fixation_boxes`` (True) without boxes.

    The same arguments (``log_odds`` and ``t_exit`` are read only for
    fixation) and the same results, bit for bit, in the same (box) order,
    for cones whose boxes would be mostly empty: from eyes facing the robot,
    a cone crosses the shells near the eyes twice, far apart in azimuth and
    elevation, and over the map's pole, so a shell's box spans most of it.
    Here each cell the rays cross gets one entry of a compact list, found
    through ``slots`` (one int32 per map cell, never cleared: an entry is
    valid when the list's cell at that slot is the cell), so the work is
    one pass over the segments and a sort of the cells reached.

    The sums are the boxes' sums: each chunk of rays adds into its own
    running sum, from 0, in ray order, and the chunks' sums are added
    together in chunk order, as the boxes merge them. Serial: one thread.
    The cells come back in the order the rays first meet them, with each
    one's box-order key (unique): the caller sorts them by it
    (``np.argsort``, outside, so that no sort is compiled here).
    """
    n_chunks = starts.shape[0] - 1
    length = 0
    for chunk in range(n_chunks):
        length += offsets[starts[chunk + 1]] - firsts[chunk]
    cell_of = np.empty(length, dtype=np.int64)
    partial = np.empty(length)
    total = np.empty(length)
    partial_chunk = np.empty(length, dtype=np.int64)
    first = np.empty(length)
    last_ray = np.empty(length, dtype=np.int64)
    used = 0
    for chunk in range(n_chunks):
        for ray in range(starts[chunk], starts[chunk + 1]):
            begin = firsts[chunk] if ray == starts[chunk] else offsets[ray]
            clear = 1.0  # probability that nothing so far stopped the gaze
            for seg in range(begin, offsets[ray + 1]):
                flat = (np.int64(cells[seg, 0]) * n_theta + cells[seg, 1]) * n_phi + cells[seg, 2]
                slot = np.int64(slots[flat])
                if not (0 <= slot < used and cell_of[slot] == flat):
                    slot = used
                    used += 1
                    slots[flat] = slot
                    cell_of[slot] = flat
                    partial[slot] = 0.0
                    total[slot] = 0.0
                    partial_chunk[slot] = chunk
                    first[slot] = np.inf
                    last_ray[slot] = -1
                elif partial_chunk[slot] != chunk:
                    total[slot] += partial[slot]  # an earlier chunk's sum, in chunk order
                    partial[slot] = 0.0
                    partial_chunk[slot] = chunk
                first[slot] = min(first[slot], t_enter[seg])
                if fixation:
                    if t_exit[seg] <= min_distance:
                        continue  # not counted, and not seen: met again beyond, it counts there
                    if last_ray[slot] == ray:
                        continue  # re-entered: counted at its first entry
                    last_ray[slot] = ray
                    p = stop_probability(log_odds, cells, seg, n_theta, n_phi, unknown,
                                         free_below)
                    partial[slot] += weights[ray] * p * clear
                    clear *= 1.0 - p
                else:
                    partial[slot] += weights[ray] * (last_ray[slot] != ray)
                    last_ray[slot] = ray
    reached = 0
    for slot in range(used):
        reached += last_ray[slot] != -1
    keys = np.empty(reached, dtype=np.int64)
    rows = np.empty(reached, dtype=np.int64)
    at = 0
    for slot in range(used):
        if last_ray[slot] == -1:
            continue
        k = cell_of[slot] % n_phi
        j = (cell_of[slot] // n_phi) % n_theta
        i = cell_of[slot] // (n_phi * n_theta)
        keys[at] = (i * n_theta + shifted(j, j_shift, n_theta)) * n_phi + k  # box order
        rows[at] = slot
        at += 1
    out_cells = np.empty((reached, 3), dtype=np.int32)
    out_weight = np.empty(reached)
    out_first = np.empty(reached)
    for row in range(reached):
        slot = rows[row]
        out_cells[row, 0] = cell_of[slot] // (n_phi * n_theta)
        out_cells[row, 1] = (cell_of[slot] // n_phi) % n_theta
        out_cells[row, 2] = cell_of[slot] % n_phi
        out_weight[row] = total[slot] + partial[slot]
        out_first[row] = first[slot]
    return out_cells, out_weight, out_first, keys
