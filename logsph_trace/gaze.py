"""What a person looks at: three layers of one computation.

:func:`gaze_targets` lists the occupied cells on a gaze's axis, in order (the
paper's Fig. 5 rule). :func:`fixation_probability` gives each cell the
probability that a cone of rays around the gaze stops there first, so an
object hidden behind another is not reported as looked at.
:func:`gaze_objects` sums those probabilities over each object's cells and
ranks the objects: the answer. :class:`GazeAccumulator` keeps a decaying sum
over time, so that a held look beats a glance.
"""

import math
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from . import _validate as validate
from ._jit import interrupts_after
from ._validate import WrongTypeError
from .cone import aggregate_cone, cones_on_gpu, sample_rays
from .kernels import objects as _objects
from .occupancy import _check_occupancy
from .sensor import gaze_pair
from .trace import trace_many


@dataclass(frozen=True)
class GazeTargets:
    """Cells along a gaze, in order of distance, with a value each."""

    cells: np.ndarray
    values: np.ndarray
    t_enter: np.ndarray

    def __len__(self):
        return self.cells.shape[0]


def gaze_targets(occupancy, gaze, direction=None, threshold=0.6):
    """Find the cells on the gaze ray whose occupancy exceeds ``threshold`` (Fig. 5's rule).

    The first of three layers of one computation (see
    :func:`~logsph_trace.gaze_objects`): one ray, and every occupied cell
    on it, hidden or not.

    Parameters
    ----------
    occupancy : OccupancyGrid
    gaze : Gaze or array_like, shape (3,)
        A :class:`~logsph_trace.Gaze`, or the eyes' position in the map's
        frame, with ``direction``.
    direction : array_like, shape (3,), optional
        The gaze direction, when ``gaze`` is a position.
    threshold : float
        Probability above which a cell counts.

    Returns
    -------
    GazeTargets
        ``cells`` (u, 3), ``values`` their probabilities, ``t_enter`` the distance
        at which the gaze first enters each, in order of distance.

    Notes
    -----
    After :meth:`~logsph_trace.OccupancyGrid.move`, the gaze is traced
    through the cells as the map holds them (exactly, without resampling
    the map), and each cell is reported as the robot-frame cell that holds
    its centre.
    """
    _check_occupancy(occupancy)
    origin, direction = gaze_pair(gaze, direction)
    threshold = validate.probability("threshold", threshold)
    origin = validate.point("origin", origin, validate.reach(occupancy.grid))
    direction = validate.vector("direction", direction)
    with occupancy._lock:  # after a move: traced through the cells as the map holds them
        ray = trace_many(occupancy.grid, *occupancy._into_held(origin, direction),
                         parallel=False)[0]
        if len(ray) == 0:
            return GazeTargets(ray.cells, np.empty(0), np.empty(0))
        _, first = np.unique(ray.cells, axis=0, return_index=True)
        first = np.sort(first)  # each cell at its first entry, in order of distance
        cells = ray.cells[first]
        values = occupancy._held_values_at(cells)
        cells = occupancy._robot_cells(cells)
    probability = 1.0 / (1.0 + np.exp(-values.astype(np.float64)))
    above = (probability > threshold) & (cells[:, 0] >= 0)
    return GazeTargets(cells[above], probability[above], ray.t_enter[first][above])


@interrupts_after
def fixation_probability(occupancy, gaze, direction=None, half_angle=0.0, n_rays=None,
                         pattern="fibonacci", weighting="gaussian", sigma=None,
                         unknown=0.0, free_below=0.5, min_distance=0.0, dense=False):
    """Probability that each cell is the first occupied cell the gaze meets.

    For one ray, ``P(c) = p_c * prod(1 - p)`` over the cells in front of ``c``;
    for a cone (``half_angle > 0``), summed over its rays by weight. An object
    hidden behind another gets little: the gaze stops at the first one.
    The second of three layers of one computation (see
    :func:`~logsph_trace.gaze_objects`, which sums these over objects).

    Parameters
    ----------
    occupancy : OccupancyGrid
    gaze : Gaze or array_like, shape (3,)
        A :class:`~logsph_trace.Gaze`, or the eyes' position in the map's
        frame, with ``direction``.
    direction : array_like, shape (3,), optional
        The gaze direction, when ``gaze`` is a position.
    half_angle, n_rays, pattern, weighting, sigma :
        The gaze cone, as for :func:`~logsph_trace.trace_cone`; 0 is one ray.
    unknown : float
        Occupancy assumed for cells never observed (log-odds exactly 0). The
        default 0 lets the gaze pass through unobserved space instead of
        stopping there with probability 1/2.
    free_below : float
        Cells the map believes free (probability below this) do not stop the
        gaze. An OctoMap-style map keeps free cells at p = 0.12 to 0.4, never
        0, and with the literal formula (``free_below=0``) the dozen free
        cells in front of an object would absorb most of the gaze before it
        gets there.
    min_distance : float
        Cells the gaze leaves within this distance of its origin are ignored
        (the person's own head, hair, glasses in the map).
    dense : bool
        Return an array of shape ``grid.shape`` instead of sparse results.

    Returns
    -------
    GazeTargets or numpy.ndarray
        Sparse: cells with a non-zero probability, most probable first
        (``t_enter`` is where the gaze first reaches each). Dense: the map.

    Notes
    -----
    After :meth:`~logsph_trace.OccupancyGrid.move`, the cone is traced
    through the cells as the map holds them (exactly, without resampling
    the map), and each cell's probability is reported in the robot-frame
    cell that holds its centre (summed where two land in one).
    """
    _check_occupancy(occupancy)
    origin, direction = gaze_pair(gaze, direction)
    grid = occupancy.grid
    options = _fixation_options(unknown, free_below, min_distance)
    origin = validate.point("origin", origin, validate.reach(grid))
    with occupancy._lock:  # the map and its pose not changed by another thread meanwhile
        cells, values, t_first = _fixation_held(occupancy, origin, direction, half_angle,
                                                n_rays, pattern, weighting, sigma, options)
        if occupancy._pose is not None:
            cells, values, t_first = _merged(grid, occupancy._robot_cells(cells), values,
                                             t_first)
    if dense:
        out = np.zeros(grid.shape)
        out[tuple(cells.T)] = values
        return out
    keep = values > 0
    order = np.argsort(-values[keep], kind="stable")
    return GazeTargets(cells[keep][order], values[keep][order], t_first[keep][order])


def _fixation_options(unknown=0.0, free_below=0.5, min_distance=0.0):
    """Check ``fixation_probability``'s options; return (min_distance, unknown, free_below)."""
    unknown = validate.number("unknown", unknown, "a probability in [0, 1]")
    if not 0.0 <= unknown <= 1.0:
        raise ValueError(f"unknown must be a probability in [0, 1], got {unknown!r}")
    min_distance = validate.number("min_distance", min_distance, ">= 0")
    if not (np.isfinite(min_distance) and min_distance >= 0.0):
        raise ValueError(f"min_distance must be >= 0, got {min_distance!r}")
    free_below = validate.number("free_below", free_below, "a probability in [0, 1]")
    if not 0.0 <= free_below <= 1.0:
        raise ValueError(f"free_below must be a probability in [0, 1], got {free_below!r}")
    return min_distance, unknown, free_below


def _fixation_held(occupancy, origin, direction, half_angle, n_rays, pattern, weighting, sigma,
                   options):
    """Return ``fixation_probability``'s sparse cells, values and first distances.

    In the cells as the map holds them (the robot's frame until a move);
    call under the map's lock. ``options``: (min_distance, unknown, free_below), checked.
    """
    grid = occupancy.grid
    origin, direction = occupancy._into_held(origin, validate.vector("direction", direction))
    directions, ray_weights = sample_rays(grid, origin, direction, half_angle, n_rays, pattern,
                                          weighting, sigma)
    # Traced as trace_cone traces; each cell's first-occupied probability is
    # summed in the same chunked pass that sums a cone's weights.
    fixation = (occupancy._held_flat(), *options)
    if occupancy.device == "cuda":
        return cones_on_gpu(grid, origin[None], [(directions, ray_weights)], fixation)[0]
    return aggregate_cone(grid, origin, directions, ray_weights, fixation)


def _merged(grid, cells, values, t_first):
    """Sum ``values`` of equal ``cells`` (rows of -1 dropped).

    Each keeps its least ``t_first``.
    """
    inside = cells[:, 0] >= 0
    flat = np.ravel_multi_index(tuple(cells[inside].T), grid.shape)
    unique, which = np.unique(flat, return_inverse=True)
    first = np.full(unique.shape[0], np.inf)
    np.minimum.at(first, which, t_first[inside])
    merged = np.stack(np.unravel_index(unique, grid.shape), axis=1).astype(cells.dtype)
    return merged, np.bincount(which, weights=values[inside], minlength=unique.shape[0]), first


class ObjectHit(NamedTuple):
    """One object a gaze may stop at.

    Attributes
    ----------
    id : int
        The object's label in the map (never 0).
    name : str or None
        Its name, from the ``names`` given to :func:`gaze_objects`.
    probability : float
        The probability that the gaze stops at this object first: its
        cells' fixation probabilities summed (see
        :func:`~logsph_trace.fixation_probability`).
    distance : float
        How far from the eyes the gaze first reaches one of its cells, in
        the map's unit.
    point : numpy.ndarray, float64, shape (3,)
        The point on the gaze's axis at ``distance``: where the look lands,
        in the map's frame.
    cell : tuple of int
        The object's cell the gaze reaches first.
    centroid : numpy.ndarray, float64, shape (3,)
        The mean of the centres of all the map's cells with this label, in
        the map's frame.
    n_cells : int
        How many of the map's cells carry this label.
    """

    id: int
    name: object
    probability: float
    distance: float
    point: np.ndarray
    cell: tuple
    centroid: np.ndarray
    n_cells: int


@dataclass(frozen=True)
class GazeObjects:
    """The objects a gaze may stop at, most probable first.

    A sequence of :class:`ObjectHit`: ``objects[0]`` (or ``objects.top``)
    is the answer, and ``for hit in objects`` ranks them all.

    Attributes
    ----------
    hits : tuple of ObjectHit
        The objects, most probable first.
    unlabelled : float
        The probability of stopping at occupied cells that carry no label.
    """

    hits: tuple
    unlabelled: float

    def __len__(self):
        return len(self.hits)

    def __getitem__(self, index):
        return self.hits[index]

    def __iter__(self):
        return iter(self.hits)

    @property
    def top(self):
        """The most probable :class:`ObjectHit`, or ``None`` if the gaze reaches no object."""
        return self.hits[0] if self.hits else None

    @property
    def ids(self):
        """The objects' labels, most probable first (int64 array)."""
        return np.array([hit.id for hit in self.hits], dtype=np.int64)

    @property
    def probabilities(self):
        """The objects' probabilities, in the same order (float64 array)."""
        return np.array([hit.probability for hit in self.hits], dtype=np.float64)


DEFAULT_HALF_ANGLE = math.radians(5.0)


# What gaze_objects passes on to fixation_probability (``dense`` would change
# the result's type under it).
_FIXATION_OPTIONS = frozenset(
    ("pattern", "weighting", "sigma", "unknown", "free_below", "min_distance"))


def gaze_objects(occupancy, gaze, direction=None, half_angle=DEFAULT_HALF_ANGLE, n_rays=None,
                 names=None, **fixation):
    """Rank the map's objects by the probability that the gaze reaches them first.

    The last of three layers of one computation: :func:`~logsph_trace.gaze_targets`
    lists the occupied cells on a single ray (the paper's Fig. 5),
    :func:`~logsph_trace.fixation_probability` gives each cell the probability
    that a cone of rays stops there first, and this sums those probabilities
    over each object's cells.

    Parameters
    ----------
    occupancy : OccupancyGrid
        A map with object labels (:attr:`OccupancyGrid.labels`).
    gaze : Gaze or array_like, shape (3,)
        A :class:`~logsph_trace.Gaze` (from :func:`~logsph_trace.gaze_from_pitch_yaw`
        or :func:`~logsph_trace.gaze_from_vector`), or the eyes' position
        in the map's frame, with ``direction``.
    direction : array_like, shape (3,), optional
        The gaze direction in the map's frame, when ``gaze`` is a position.
    half_angle : float
        The gaze cone's half-angle, radians: the gaze estimator's angular
        error (see :func:`~logsph_trace.gaze_from_pitch_yaw`). Default 5 degrees.
    n_rays : int, optional
        Rays in the cone (default: :func:`~logsph_trace.default_ray_count`,
        enough that neighbouring rays are under a cell apart where the cone
        leaves the grid).
    names : mapping of int to str, optional
        The detector's name for each label; labels it lacks get ``None``.
    **fixation
        Passed to :func:`~logsph_trace.fixation_probability` (``pattern``,
        ``weighting``, ``sigma``, ``unknown``, ``free_below``, ``min_distance``).

    Returns
    -------
    GazeObjects
        A sequence of :class:`ObjectHit`, most probable first; empty when
        the gaze reaches no labelled cell.

    Notes
    -----
    Beyond the cone, this reads every cell's label once, to find the
    centroid and size of the objects it returns (a few milliseconds for a
    4-million-cell map).
    """
    _check_occupancy(occupancy)
    unknown = sorted(set(fixation) - _FIXATION_OPTIONS)
    if unknown:
        raise TypeError(f"gaze_objects() takes no {', '.join(map(repr, unknown))}; it passes "
                        f"only {sorted(_FIXATION_OPTIONS)} to fixation_probability")
    if names is not None and not hasattr(names, "get"):
        raise WrongTypeError(f"names must be a mapping from label to name, got "
                             f"{type(names).__name__}")
    origin, direction = gaze_pair(gaze, direction)
    cone = {name: fixation.pop(name) for name in ("pattern", "weighting", "sigma")
            if name in fixation}
    options = _fixation_options(**fixation)
    origin = validate.point("origin", origin, validate.reach(occupancy.grid))
    return _ranked(occupancy, origin, direction, half_angle, n_rays, names, cone, options)


def _ranked(occupancy, origin, direction, half_angle, n_rays, names, cone, options,
            centroids=True):
    """Rank the objects as ``gaze_objects`` does, on checked input.

    ``centroids=False`` leaves each hit's ``centroid`` and ``n_cells`` None
    and skips the pass over every label that finds them (half of a gaze's
    time on a 64 x 360 x 180 map, which a replay, whose events do not carry
    them, need not pay).
    """
    with occupancy._lock:  # the cone and the labels in the cells as the map holds them
        cells, values, t_enter = _fixation_held(
            occupancy, origin, direction, half_angle, n_rays, cone.get("pattern", "fibonacci"),
            cone.get("weighting", "gaussian"), cone.get("sigma"), options)
        reached = values > 0
        cells, values, t_enter = cells[reached], values[reached], t_enter[reached]
        labels = occupancy._held_labels()[tuple(cells.T)].astype(np.int64)
        labelled = labels > 0
        unlabelled = float(values[~labelled].sum())
        if not np.any(labelled):
            return GazeObjects((), unlabelled)
        labels, values = labels[labelled], values[labelled]
        first_cells, t_enter = cells[labelled], t_enter[labelled]
        ids, which = np.unique(labels, return_inverse=True)
        if centroids:
            centres, counts = _centroids(occupancy, ids)
        else:
            centres = counts = [None] * ids.shape[0]
        first_cells = occupancy._robot_cells(first_cells)
    sums = np.bincount(which, weights=values)
    # Each object's first-reached cell: the smallest distance among its cells.
    order = np.lexsort((t_enter, which))
    first = order[np.searchsorted(which[order], np.arange(ids.shape[0]))]
    origin = validate.vector("origin", origin)
    axis = validate.unit("direction", direction)
    hits = []
    for rank in np.argsort(-sums, kind="stable").tolist():
        label = int(ids[rank])
        distance = float(t_enter[first[rank]])
        point = origin + distance * axis
        cell = first_cells[first[rank]]
        if cell[0] < 0:  # after a move, a held cell whose centre is outside the region
            cell = np.atleast_2d(occupancy.grid.cell_of(point))[0]
        hits.append(ObjectHit(label, None if names is None else names.get(label),
                              float(sums[rank]), distance, point, tuple(cell.tolist()),
                              centres[rank], None if counts[rank] is None
                              else int(counts[rank])))
    return GazeObjects(tuple(hits), unlabelled)


def _centroids(occupancy, ids):
    """Mean cell centre (robot frame) and cell count of each label in ``ids`` (sorted).

    In one pass over the labels as the map holds them.
    """
    grid = occupancy.grid
    sums = np.zeros((grid.n_rho, ids.shape[0], 4))
    radii = 0.5 * (grid.rho_edges[:-1] + grid.rho_edges[1:])
    _objects.label_sums(occupancy._held_labels().reshape(-1), ids, radii,
                        occupancy._column_directions(), sums)
    sums = sums.sum(axis=0)
    counts = sums[:, 0].astype(np.int64)
    return occupancy._to_robot(sums[:, 1:] / counts[:, None]), counts


class GazeAccumulator:
    """A short-term memory of gazes: a decaying sum of each object's probability.

    ``add`` first fades what is held by ``0.5 ** (elapsed / half_life)``,
    then adds the new gaze's object probabilities, so a look held for a few
    gaze samples outweighs a glance, and an object looked at long ago fades.

    Parameters
    ----------
    half_life : float
        Time for a held score to halve, in the unit of ``add``'s ``time``
        (seconds, say); without times each ``add`` is one unit.
    """

    def __init__(self, half_life=1.0):
        self.half_life = half_life
        self._scores = {}
        self._time = None

    @property
    def half_life(self):
        """Time for a held score to halve (checked when assigned: positive, finite)."""
        return self._half_life

    @half_life.setter
    def half_life(self, value):
        half_life = validate.finite("half_life", value)
        if not half_life > 0:
            raise ValueError(f"half_life must be positive, got {value!r}")
        self._half_life = half_life

    def add(self, objects, time=None):
        """Fade the scores to ``time`` and add a gaze's :class:`GazeObjects`; return self."""
        if not isinstance(objects, GazeObjects):
            raise ValueError(f"objects must be GazeObjects, got {type(objects).__name__}")
        if time is None:
            time = 0.0 if self._time is None else self._time + 1.0
        time = validate.finite("time", time)
        if self._time is not None:
            if time < self._time:
                raise ValueError(f"time must not go back: {time!r} after {self._time!r}")
            fade = 0.5 ** ((time - self._time) / self.half_life)
            self._scores = {label: score * fade for label, score in self._scores.items()}
        self._time = time
        for hit in objects:
            self._scores[hit.id] = self._scores.get(hit.id, 0.0) + hit.probability
        return self

    def scores(self):
        """(labels, scores) held now, highest first."""
        if not self._scores:
            return np.empty(0, dtype=np.int64), np.empty(0)
        labels = np.array(list(self._scores), dtype=np.int64)
        scores = np.array(list(self._scores.values()))
        order = np.lexsort((labels, -scores))
        return labels[order], scores[order]

    @property
    def top(self):
        """The object held highest, or 0 before any gaze reached one."""
        labels, _ = self.scores()
        return int(labels[0]) if labels.size else 0
