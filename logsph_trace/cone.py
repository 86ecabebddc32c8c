"""Gaze cones: the uncertainty of a gaze direction as a cone of rays (the paper's future work).

A gaze estimate is never a single exact ray. :func:`trace_cone` samples rays
inside a cone around it, traces them all (in parallel) and returns the cells
crossed, each with the weight of the rays that cross it and the distance at
which the cone first reaches it.
"""

import math
import threading
import time
from dataclasses import dataclass, field

import numpy as np

from . import _batching as batching
from . import _validate as validate
from ._jit import interrupts_after
from .grid import Grid
from .kernels import cone as _cone
from .trace import cuda_backend
from .traces import Traces

PATTERNS = ("fibonacci", "rings")
WEIGHTINGS = ("gaussian", "uniform")
MIN_DEFAULT_RAYS = 16
MAX_DEFAULT_RAYS = 1_000_000
# A cone's rays are traced and aggregated in chunks of at least this many, at
# most CONE_CHUNKS of them, whatever the thread count: the order of the weight
# sums, and so their last bits, do not depend on the machine. A chunk is one
# thread's work, so the count caps the threads a cone can use: 16 from 512
# rays on, 7 for the default 225-ray gaze cone (8 chunks of 64 rays held a
# 1,000-ray cone to 8 threads). Each chunk sums into its own copy of the
# cone's boxes (24 bytes a box: 70 kB for a 5-degree cone, 1 MB at 23 degrees).
CONE_CHUNK_RAYS = 32
CONE_CHUNKS = 16


@dataclass(frozen=True)
class ConeTrace:
    """The cells a gaze cone covers.

    Attributes
    ----------
    cells : numpy.ndarray, int32, shape (u, 3)
        Every cell crossed by at least one ray of the cone, in order of
        ``t_first``.
    weights : numpy.ndarray, float64, shape (u,)
        Summed weight of the rays crossing each cell (a ray counts once per
        cell), normalised to sum to 1.
    t_first : numpy.ndarray, float64, shape (u,)
        Distance from the cone's apex at which a ray of the cone first enters
        the cell.
    directions : numpy.ndarray, float64, shape (n, 3)
        The unit directions of the sampled rays.
    ray_weights : numpy.ndarray, float64, shape (n,)
        Their weights, summing to 1.
    origin : numpy.ndarray, float64, shape (3,)
        The cone's apex.
    grid : Grid
        The grid traced.
    traces : Traces
        The traces of the individual rays, in the order of ``directions``.
        :func:`trace_cone` does not keep them (storing every segment cost
        more than the aggregation); they are traced again on first access.
    """

    cells: np.ndarray
    weights: np.ndarray
    t_first: np.ndarray
    directions: np.ndarray
    ray_weights: np.ndarray
    origin: np.ndarray
    grid: Grid = field(repr=False)
    _traces: Traces = field(default=None, repr=False, compare=False)

    @property
    def traces(self):
        """The cone's rays traced one by one (:class:`Traces`), computed on first use."""
        if self._traces is None:
            traces = trace_given_rays(self.grid, self.origin, self.directions)
            object.__setattr__(self, "_traces", traces)  # a cache, not a change of value
        return self._traces

    def __len__(self):
        return self.cells.shape[0]

    def __repr__(self):
        return f"ConeTrace({len(self)} cells from {self.directions.shape[0]} rays)"


def cone_directions(axis, half_angle, n_rays, pattern="fibonacci"):
    """Sample unit directions inside a cone, with the angle of each from the axis.

    Parameters
    ----------
    axis : array_like, shape (3,)
        The cone's axis (any length).
    half_angle : float
        Radians, in ``[0, pi/2)``. Zero gives the axis alone.
    n_rays : int
        Rays wanted. ``"fibonacci"`` gives exactly this many, spread evenly
        over the spherical cap by a Fibonacci spiral (equal solid angle per
        ray). ``"rings"`` gives the axis and rings of 6k rays at angles
        ``k * half_angle / K``; the count is rounded up to fill the last ring.
    pattern : {"fibonacci", "rings"}

    Returns
    -------
    directions : numpy.ndarray, shape (n, 3)
    angles : numpy.ndarray, shape (n,)
    """
    axis = validate.unit("axis", axis)
    half_angle = validate.half_angle(half_angle)
    count, rings = _ray_total(half_angle, n_rays, pattern)
    directions, angles, _, _ = _sample(axis[None], np.array([half_angle]), [count], [rings],
                                       pattern, np.zeros(1))
    return directions, angles


def _check_request(n_rays, pattern):
    """Raise ValueError unless ``pattern`` is known and ``n_rays`` a positive integer (or None)."""
    if pattern not in PATTERNS:
        raise ValueError(f"pattern must be one of {PATTERNS}, got {pattern!r}")
    if n_rays is not None and (isinstance(n_rays, (bool, np.bool_))
                               or not isinstance(n_rays, (int, np.integer)) or n_rays < 1):
        raise ValueError(f"n_rays must be a positive integer, got {n_rays!r}")


def _ray_total(half_angle, n_rays, pattern):
    """Return the rays a cone of ``n_rays`` gets, and its rings (0 for ``"fibonacci"``).

    One ray, the axis, if ``half_angle`` is 0 or one ray is asked for;
    ``"rings"`` rounds up to fill its last ring.
    """
    _check_request(n_rays, pattern)
    counts, rings = _ray_totals([half_angle], [n_rays], pattern)
    return counts[0], rings[0]


def _ray_totals(half_angles, n_rays, pattern):
    """:func:`_ray_total` of many cones, their ``n_rays`` and ``pattern`` checked (lists).

    Returns (counts, rings), lists.
    """
    counts, rings = [], []
    for half_angle, wanted in zip(half_angles, n_rays):
        if half_angle == 0.0 or wanted == 1:
            counts.append(1)
            rings.append(0)
        elif pattern == "fibonacci":
            counts.append(int(wanted))
            rings.append(0)
        else:
            ring = math.ceil((-3.0 + math.sqrt(9.0 + 12.0 * (int(wanted) - 1))) / 6.0)
            counts.append(1 + 3 * ring * (ring + 1))
            rings.append(ring)
    return counts, rings


def _sample(axes, half_angles, counts, rings, pattern, sigmas):
    """Sample cones of unit ``axes`` (c, 3): ``counts`` rays each (``_ray_total``).

    ``sigmas``: each cone's Gaussian width, 0 for uniform weights. Returns
    (directions (n, 3), angles (n,), weights (n,), ray_at (c + 1,)): cone
    ``c``'s rays are ``ray_at[c]:ray_at[c + 1]``, its weights summing to 1.
    """
    n_rays = sum(counts)  # a Python int: checked before numpy sums them in int64
    # The directions and their working arrays, then one trace each: at least 24
    # bytes more per ray for the origins and bounds, and 28 per segment.
    what = (f"a cone of {n_rays:,} rays" if len(counts) == 1
            else f"{len(counts):,} cones of {n_rays:,} rays in all")
    validate.fits("n_rays", n_rays * 256, what)
    ray_at = np.zeros(len(counts) + 1, dtype=np.int64)
    np.cumsum(counts, out=ray_at[1:])
    directions = np.empty((n_rays, 3))
    angles = np.empty(n_rays)
    weights = np.empty(n_rays)
    _cone.sample_cones(np.ascontiguousarray(axes), np.ascontiguousarray(half_angles), ray_at,
                       pattern == "fibonacci", np.asarray(rings, dtype=np.int64),
                       np.ascontiguousarray(sigmas, dtype=np.float64), directions, angles,
                       weights)
    return directions, angles, weights, ray_at


def default_ray_count(grid, origin, half_angle):
    """Rays needed so that neighbouring rays are closer than one cell at the far edge.

    The rule: the cone's rays, spread over its cap of solid angle
    ``Omega = 2 pi (1 - cos h)``, are about ``sqrt(Omega / n)`` apart; at the
    farthest the cone can reach inside the grid, ``L = |origin| + rho_max``,
    that angle is a distance, which must stay below the smallest angular cell
    width at the outer sphere, ``s = rho_max * min(d_theta, d_phi)``. Taking
    ``n = ceil(2 Omega (L / s)^2)`` puts neighbours about 0.7 of a cell apart
    there, so the rule holds even where the spiral is uneven and at the cap's
    rim; at least 16 rays, at most 1,000,000. Measured (tests/test_cone.py):
    the cells a 10x denser cone adds carry under 3% of its weight. Near the
    poles cells are narrower in theta than ``s``, so thin polar cells can
    still fall between rays.
    """
    return _ray_count(grid, validate.point("origin", origin, validate.reach(grid)),
                      validate.half_angle(half_angle))


def _ray_count(grid, origin, half_angle):
    """:func:`default_ray_count` for a checked ``origin`` and ``half_angle``."""
    return _ray_counts(grid, origin[None], [half_angle])[0]


def _ray_counts(grid, origins, half_angles):
    """:func:`default_ray_count` of many cones: checked ``origins`` (c, 3), a list of angles.

    In Python floats, one cone at a time (a list): the same arithmetic for
    one cone and for many, so :func:`trace_cone` and :func:`trace_cones`
    give a cone the same rays.
    """
    rho_max = grid.rho_max
    cell_width = rho_max * grid._narrowest_angle  # the least theta or phi width
    counts = []
    for (x, y, z), half_angle in zip(origins.tolist(), half_angles):
        if half_angle == 0.0:
            counts.append(1)
            continue
        reach = math.sqrt(x * x + y * y + z * z) + rho_max
        solid_angle = 2.0 * math.pi * (1.0 - math.cos(half_angle))
        ratio = reach / cell_width  # inf for a cell of 1e-200 rad: then the cap
        needed = 2.0 * solid_angle * ratio * ratio
        counts.append(MAX_DEFAULT_RAYS if not needed < MAX_DEFAULT_RAYS
                      else max(math.ceil(needed), MIN_DEFAULT_RAYS))
    return counts


def _sigma(half_angle, weighting, sigma):
    """Return a cone's Gaussian width for ``sample_cones``: 0 for uniform weights."""
    if weighting not in WEIGHTINGS:
        raise ValueError(f"weighting must be one of {WEIGHTINGS}, got {weighting!r}")
    if weighting == "uniform" or half_angle == 0.0:
        return 0.0
    if sigma is None:
        return half_angle / 2.0  # the cone's edge at two standard deviations
    sigma = validate.number("sigma", sigma, "a positive number of radians")
    if not (math.isfinite(sigma) and sigma > 0.0):
        raise ValueError(f"sigma must be a positive number of radians, got {sigma!r}")
    return sigma


def sample_rays(grid, origin, direction, half_angle, n_rays, pattern, weighting, sigma):
    """Directions and weights of a cone's rays (``n_rays=None``: the default count)."""
    half_angle = validate.half_angle(half_angle)
    origin = validate.point("origin", origin, validate.reach(grid))
    direction = validate.unit("direction", direction)
    if n_rays is None:
        n_rays = _ray_count(grid, origin, half_angle)
    count, rings = _ray_total(half_angle, n_rays, pattern)
    sigmas = np.array([_sigma(half_angle, weighting, sigma)])
    directions, _, weights, _ = _sample(direction[None], np.array([half_angle]), [count],
                                        [rings], pattern, sigmas)
    return directions, weights


def chunk_starts(n_rays):
    """Boundaries of a cone's chunks of rays (see ``CONE_CHUNKS``), an int64 array.

    Chunk ``i`` of ``n`` starts at ray ``i * n_rays // n``, as
    :func:`chunk_bounds` cuts each of many cones.
    """
    chunks = max(1, min(CONE_CHUNKS, n_rays // CONE_CHUNK_RAYS))
    return np.arange(chunks + 1, dtype=np.int64) * n_rays // chunks


def chunk_bounds(counts):
    """:func:`chunk_starts` of cones of ``counts`` rays laid end to end.

    Returns (bounds, cone_bounds): cone ``c``'s chunks are cut at
    ``bounds[cone_bounds[c]:cone_bounds[c + 1]]``, ray indices counted from
    the first cone's first ray (its own first and end included). Chunk ``i``
    of ``n`` of a cone of ``r`` rays starts at ``i * r // n``: integers, the
    same however many cones are cut at once (``chunk_starts``, one cone).
    """
    counts = np.asarray(counts, dtype=np.int64)
    chunks = np.clip(counts // CONE_CHUNK_RAYS, 1, CONE_CHUNKS)
    cone_bounds = np.zeros(counts.shape[0] + 1, dtype=np.int64)
    np.cumsum(chunks + 1, out=cone_bounds[1:])
    cone = np.repeat(np.arange(counts.shape[0]), chunks + 1)
    index = np.arange(cone_bounds[-1]) - cone_bounds[cone]
    first_ray = np.cumsum(counts) - counts
    return first_ray[cone] + index * counts[cone] // chunks[cone], cone_bounds


def aggregate_cells(grid, offsets, cells, t_enter, origin, axis, weights, chunks=None,
                    fixation=None):
    """Weighted cells of a cone's traces, ordered by first reach.

    ``offsets``, ``cells``, ``t_enter``: packed CSR, or the unpacked regions
    of :func:`~logsph_trace._batching.trace_regions` with ``chunks = (starts,
    regions)``. ``weights`` are per ray; ``origin`` is the cone's apex and
    ``axis`` a direction near its axis (they place the boxes' seam:
    :func:`theta_shifts`). Each cell gets the summed weight of the rays crossing it,
    normalised to sum to 1; or, with ``fixation = (t_exit, log_odds,
    min_distance, unknown, free_below)`` (``log_odds`` flat), the weighted
    probability that it is the first occupied cell each ray meets (see
    :func:`~logsph_trace.fixation_probability`), not normalised. The rays
    are aggregated in chunks (see ``CONE_CHUNKS``), in parallel.
    """
    if chunks is None:
        starts = chunk_starts(offsets.shape[0] - 1)
        firsts = offsets[starts[:-1]]
    else:
        starts, firsts = chunks[0], chunks[1][:-1]
    firsts = np.ascontiguousarray(firsts)
    j_shift = theta_shift(grid, origin, axis)
    if _towards_the_centre(origin, axis):
        if fixation is None:
            t_exit, log_odds, min_distance, unknown, free_below = t_enter, _NO_MAP, 0.0, 0.0, 0.0
        else:
            t_exit, log_odds, min_distance, unknown, free_below = fixation
        cells, weights, t_first, keys = _cone.sparse_cone(
            offsets, starts, firsts, cells, t_enter, t_exit, weights, log_odds, grid.n_theta,
            grid.n_phi, j_shift, fixation is not None, min_distance, unknown, free_below,
            _slots(grid))
        in_boxes = np.argsort(keys)  # the boxes' order: ties by first reach keep it
        cells, weights, t_first = np.take(cells, in_boxes, axis=0), weights[in_boxes], \
            t_first[in_boxes]
        return by_first_reach(cells, weights, t_first, normalise=fixation is None)
    pool, ray_pool = batching.box_pools()
    if fixation is None:
        cells, weights, t_first, needed = _cone.aggregate_boxes(
            offsets, starts, firsts, cells, t_enter, weights, grid.n_rho, grid.n_theta, j_shift,
            pool, ray_pool)
    else:
        t_exit, log_odds, min_distance, unknown, free_below = fixation
        cells, weights, t_first, needed = _cone.fixation_boxes(
            offsets, starts, firsts, cells, t_enter, t_exit, weights, log_odds, grid.n_theta,
            grid.n_phi, min_distance, unknown, free_below, j_shift, pool, ray_pool)
    batching.keep_box_pools(int(needed))
    return by_first_reach(cells, weights, t_first, normalise=fixation is None)


_NO_MAP = np.zeros(1, dtype=np.float32)
_slot_scratch = threading.local()


def _towards_the_centre(origin, axis):
    """Whether a cone's axis heads back past its apex's side of the map's centre.

    Such a cone (eyes that face the robot) crosses the shells near its apex
    twice, far apart in azimuth and elevation, and its per-shell boxes are
    mostly empty: ``kernels.cone.sparse_cone`` sums it without boxes, to the
    same results bit for bit. ``python -m bench.cone_sums`` forces each way
    in one run (2 threads): the README's gaze, facing the robot, took 6.0 ms
    cell by cell against 21.9 ms in boxes (``fixation_probability``); a gaze
    away from the robot took 0.75 ms in boxes against 0.82 ms cell by cell,
    so it keeps them.
    """
    origin = np.asarray(origin, dtype=np.float64)
    return float(origin @ np.asarray(axis, dtype=np.float64)) < 0.0


def _slots(grid):
    """Return this thread's slot per map cell for ``sparse_cone`` (int32, never cleared)."""
    size = grid.n_rho * grid.n_theta * grid.n_phi
    held = getattr(_slot_scratch, "slots", None)
    if held is None or held.shape[0] < size:
        validate.fits("grid", 4 * size, f"a gaze cone's scratch of {size:,} cells")
        held = _slot_scratch.slots = np.empty(size, dtype=np.int32)
    return held


def theta_shift(grid, origin, axis):
    """Return the azimuth shift that puts a cone's cells mid-seam (``kernels.cone``)."""
    return int(theta_shifts(grid, np.reshape(origin, (1, 3)), np.reshape(axis, (1, 3)))[0])


def theta_shifts(grid, origins, axes):
    """:func:`theta_shift` of cones from ``origins`` (c, 3) around ``axes`` (c, 3), int64.

    A cone's cells are summed in one box per shell, (theta, phi) extents
    after an azimuth shift, so the seam must fall where the cone has no
    cells. From the centre, that is opposite the axis. From elsewhere, the
    axis's line sweeps the azimuths from the origin's to the direction's
    (less than a half turn, the way the line turns about the y axis), and
    the seam goes opposite the middle of that arc. With the seam opposite
    the axis instead, a gaze from the eyes towards the robot (a face the
    robot's camera sees) puts the cells near the eyes across the seam, and
    every shell's box goes round the whole circle: ``trace_cones`` of 16
    such gazes took 318 ms with that rule against 221 ms with this one, in
    one run (``python -m bench.cone_sums``). Only the boxes' layout depends
    on it: the cells, sums and first reaches are the same for any shift.
    """
    axes = np.asarray(axes, dtype=np.float64).reshape(-1, 3)
    origins = np.broadcast_to(np.asarray(origins, dtype=np.float64).reshape(-1, 3), axes.shape)
    dx, dz = axes[:, 0], axes[:, 2]
    theta = np.arctan2(dx, dz)
    if grid.theta_full:
        ox, oz = origins[:, 0], origins[:, 2]
        theta_origin = np.arctan2(ox, oz)
        turns_up = oz * dx - ox * dz >= 0.0  # the azimuth grows along the line
        arc = np.where(turns_up, np.mod(theta - theta_origin, 2.0 * np.pi),
                       -np.mod(theta_origin - theta, 2.0 * np.pi))
        arc = np.where(np.hypot(dx, dz) > 0.0, arc, 0.0)  # a vertical axis keeps its azimuth
        off_axis = np.hypot(ox, oz) > 1e-9 * grid.rho_max
        theta = np.where(off_axis, theta_origin + 0.5 * arc, theta)
    low = grid.theta_edges[0]
    theta = low + np.mod(theta - low, 2.0 * np.pi)
    j = np.clip(np.searchsorted(grid.theta_edges, theta, side="right") - 1, 0, grid.n_theta - 1)
    return ((grid.n_theta // 2 - j) % grid.n_theta).astype(np.int64)


def by_first_reach(cells, weights, t_first, normalise):
    """Sort a cone's aggregated cells by first reach (ties stay in the order given).

    The weights are normalised to sum to 1 if ``normalise``.
    """
    # A radix sort: 30 us against numpy's stable argsort's 68 us for 2,000
    # cells, 2.7% of bench.cone's 1,000-ray cone (7 against 3 us at 300 cells).
    order = _cone.first_reach_order(t_first)
    weights = weights[order]
    if normalise:
        _cone.normalise(weights)
    # ``np.take`` along the rows: indexing an (n, 3) array by ``order`` costs 4x more.
    return np.take(cells, order, axis=0), weights, t_first[order]


def aggregate_cone(grid, origin, directions, ray_weights, fixation=None):
    """Trace a cone's rays and aggregate them into weighted cells.

    The rays from ``origin`` are traced in chunks, each into its own region
    of reused scratch, then aggregated by :func:`aggregate_cells`;
    ``fixation`` is as there, without ``t_exit``, which the trace supplies.
    """
    n_rays = directions.shape[0]
    origins = np.ascontiguousarray(np.broadcast_to(origin, directions.shape))
    starts, regions, _, offsets, cells, t_enter, t_exit = batching.trace_regions(
        grid, origins, directions, np.full(n_rays, np.inf), grid.kernel_args(),
        chunk_starts(n_rays), batching.scratch_segments)
    start = time.perf_counter()
    if fixation is not None:
        fixation = (t_exit, *fixation)
    aggregated = aggregate_cells(grid, offsets, cells, t_enter, origin, directions[0],
                                 ray_weights, chunks=(starts, regions), fixation=fixation)
    batching.lap("aggregate", start)
    return aggregated


def trace_given_rays(grid, origin, directions):
    """Trace cone rays exactly as given, on all threads.

    They are already unit: renormalising could move them by an ulp.
    ``origin`` is (3,) or one per ray.
    """
    origins = np.ascontiguousarray(np.broadcast_to(origin, directions.shape))
    return batching.run_exact(grid, origins, directions, np.full(directions.shape[0], np.inf), True)


def cones_on_gpu(grid, origins, samples, fixation=None):
    """Aggregate cones on the GPU: (cells, weights, t_first) of each, by first reach.

    ``samples`` are the cones' (directions, ray weights), ``origins`` their
    apexes (c, 3); ``fixation`` as for :func:`aggregate_cone`, with the map
    flat on the device.
    """
    backend = cuda_backend()
    counts = [sample[0].shape[0] for sample in samples]
    unsorted = backend.aggregate_cones(
        grid, np.repeat(origins, counts, axis=0), np.concatenate([s[0] for s in samples]),
        np.concatenate([s[1] for s in samples]), counts,
        theta_shifts(grid, origins, [s[0][0] for s in samples]), fixation)
    return [by_first_reach(*cone, normalise=fixation is None) for cone in unsorted]


@interrupts_after
def trace_cone(grid, origin, direction, half_angle, n_rays=None, pattern="fibonacci",
               weighting="gaussian", sigma=None, device="cpu"):
    """Trace a gaze cone through ``grid``.

    Parameters
    ----------
    grid : Grid
    origin : array_like, shape (3,)
        The cone's apex (the eyes), in the grid's frame and length unit.
    direction : array_like, shape (3,)
        The gaze direction, the cone's axis (any non-zero length).
    half_angle : float
        Radians, in ``[0, pi/2)``; 0 traces the axis alone.
    n_rays : int, optional
        Rays to sample. ``None`` picks enough that neighbouring rays are
        closer than one cell at the far edge of the grid
        (:func:`default_ray_count` states the rule).
    pattern : {"fibonacci", "rings"}
        How rays are spread over the cone (see :func:`cone_directions`).
    weighting : {"gaussian", "uniform"}
        ``"gaussian"`` weights a ray by ``exp(-angle^2 / (2 sigma^2))`` of its
        angle from the axis; ``"uniform"`` weights all rays equally.
    sigma : float, optional
        Radians, for ``"gaussian"``; default ``half_angle / 2``.
    device : {"cpu", "cuda"}
        ``"cuda"``: trace and aggregate on an NVIDIA GPU (see
        :func:`~logsph_trace.trace_many`); the result is on the host. The
        cells and first reaches are the CPU's; the weights are summed in the
        order the GPU runs the rays, so their last bits may differ.

    Returns
    -------
    ConeTrace

    Raises
    ------
    ValueError
        ``half_angle`` negative, NaN or ``>= pi/2``; wrong shapes; NaN or
        infinite origin or direction; zero direction; bad ``n_rays``,
        ``pattern``, ``weighting``, ``sigma`` or ``device``; ``grid`` not a
        Grid.
    RuntimeError
        ``device="cuda"`` without a usable GPU or numba-cuda.
    """
    validate.grid(grid)
    validate.device(device)
    origin = validate.point("origin", origin, validate.reach(grid))
    directions, ray_weights = sample_rays(grid, origin, direction, half_angle, n_rays, pattern,
                                      weighting, sigma)
    if device == "cuda":
        cells, weights, t_first = cones_on_gpu(grid, origin[None], [(directions, ray_weights)])[0]
    else:
        cells, weights, t_first = aggregate_cone(grid, origin, directions, ray_weights)
    traces = None  # traced again if read: storing every segment cost more than aggregating
    return ConeTrace(cells, weights, t_first, directions, ray_weights, origin, grid, traces)


@interrupts_after
def trace_cones(grid, origins, directions, half_angles, n_rays=None, pattern="fibonacci",
                weighting="gaussian", sigma=None, device="cpu"):
    """Trace many gaze cones at once (a batch of gaze samples); all rays in one parallel call.

    Parameters
    ----------
    grid : Grid
    origins, directions : array_like, shape (c, 3) or (3,)
        One origin (or one direction) is every cone's, as in :func:`trace_many`.
    half_angles : float or array_like, shape (c,)
    n_rays, pattern, weighting, sigma, device :
        As for :func:`trace_cone`, the same for every cone. On the CPU each
        result keeps its rays' traces; with ``device="cuda"`` they are traced
        again (on the CPU) if read.

    Returns
    -------
    list of ConeTrace
    """
    validate.grid(grid)
    validate.device(device)
    origins, directions = validate.shared_rows(validate.vectors("origins", origins),
                                               validate.vectors("directions", directions))
    origins = validate.origin_size("origins", origins, validate.reach(grid))
    n_cones = origins.shape[0]
    half_angles = validate.half_angles("half_angles", half_angles, n_cones)
    directions = validate.unit_directions(directions)
    if n_cones == 0:
        return []
    _check_request(n_rays, pattern)
    angles = half_angles.tolist()
    counts, rings = _ray_totals(
        angles, _ray_counts(grid, origins, angles) if n_rays is None else [n_rays] * n_cones,
        pattern)
    sigmas = [_sigma(angle, weighting, sigma) for angle in angles]
    all_directions, _, all_weights, cone_rays = _sample(directions, half_angles, counts, rings,
                                                        pattern, sigmas)
    rays = cone_rays.tolist()  # Python ints for the per-cone slices below
    if device == "cuda":
        samples = [(all_directions[first:end], all_weights[first:end])
                   for first, end in zip(rays[:-1], rays[1:])]
        return [ConeTrace(*cone, *sample, origin, grid, None) for cone, sample, origin
                in zip(cones_on_gpu(grid, origins, samples), samples, origins)]
    traces = trace_given_rays(grid, np.repeat(origins, counts, axis=0), all_directions)
    # Every cone aggregated in one parallel call, each in the chunks trace_cone
    # cuts it into: the same cells and sums as one at a time, bit for bit.
    bounds, cone_bounds = chunk_bounds(counts)
    pool, ray_pool = batching.box_pools()
    cells, weights, t_first, at, found, needed = _cone.aggregate_cones(
        traces.offsets, cone_rays, bounds, cone_bounds, traces.cells, traces.t_enter, all_weights,
        grid.n_rho, grid.n_theta, theta_shifts(grid, origins, all_directions[cone_rays[:-1]]),
        pool, ray_pool)
    batching.keep_box_pools(int(needed))
    # The per-cone views, with Python ints for bounds: this loop runs on one
    # thread, so it is kept to slicing.
    results = []
    offsets = traces.offsets
    segments = offsets[cone_rays].tolist()
    rows = at.tolist()
    for cone, count in enumerate(found.tolist()):
        first, end = rays[cone], rays[cone + 1]
        lo, hi = segments[cone], segments[cone + 1]
        own = Traces(offsets[first:end + 1] - lo, traces.cells[lo:hi], traces.t_enter[lo:hi],
                     traces.t_exit[lo:hi])
        row = rows[cone]
        results.append(ConeTrace(cells[row:row + count], weights[row:row + count],
                                 t_first[row:row + count], all_directions[first:end],
                                 all_weights[first:end], origins[cone], grid, own))
    return results
