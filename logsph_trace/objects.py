"""Objects in the map and the object a gaze names.

The paper's question is which object a person is staring at; cells answer
"where". Here a map's cells carry object labels: voted in from a 2-D
detector's instance image (``integrate_depth(..., labels=...)``), or found as
connected components of occupied cells (:func:`label_objects`).
:func:`gaze_objects` sums a gaze's fixation probability over each object's
cells, and :class:`GazeAccumulator` keeps a decaying sum over time, so that
a held look beats a glance.
"""

import math
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from . import _validate as validate
from ._validate import WrongTypeError
from .kernels import objects as _kernels
from .occupancy import _check_occupancy as _check
from .occupancy import fixation_probability
from .sensor import gaze_pair


def label_objects(occupancy, threshold=0.6, exclude=None, min_cells=1, replace=False):
    """Label the connected groups of occupied cells as objects, in ``occupancy.labels``.

    Cells above ``threshold`` are occupied; two are connected when each of
    their indices differs by at most one (the 26-neighbourhood of index
    space), across the theta seam when the grid's azimuth is a full circle.

    By default the labels a detector voted in are kept: cells that carry
    one take no part, and the new components are numbered after the
    largest label the map holds, in the map's C order of their first cell.
    With ``replace=True`` every label is dropped first and the components
    are numbered 1, 2, ...

    Objects that stand on a floor touch it, and so each other: leave the
    floor out with ``exclude`` (:func:`fit_plane` finds it, and
    :meth:`Grid.count_points` puts its points in cells). A depth camera's
    pixels on a silhouette often fall between the object and what lies
    behind it, a few to a cell, and can chain the two together: leaving out
    cells that hold only a few points of a scan breaks such chains (the
    tutorial on the Motorcycle frame does both).

    Parameters
    ----------
    occupancy : OccupancyGrid
    threshold : float
        Probability above which a cell is occupied.
    exclude : array_like of bool, shape ``grid.shape``, optional
        Cells that belong to no object and connect none, occupied or not.
    min_cells : int
        Components with fewer cells are left unlabelled (0), as noise.
    replace : bool
        Drop the map's labels first, instead of keeping them.

    Returns
    -------
    int
        The number of objects found (not counting those the map kept).
    """
    _check(occupancy)
    min_cells = validate.count("min_cells", min_cells)
    grid = occupancy.grid
    occupied = np.zeros(grid.shape, dtype=bool)
    occupied[tuple(occupancy.occupied(threshold).T)] = True
    if exclude is not None:
        mask = np.asarray(exclude)
        if mask.shape != grid.shape or mask.dtype != np.bool_:
            raise ValueError(f"exclude must be a boolean array of shape {grid.shape}, got "
                             f"{mask.dtype} of shape {mask.shape}")
        occupied &= ~mask
    detected = None if replace else occupancy.labels
    if detected is not None:
        occupied &= detected == 0
    labels = np.zeros(grid.shape, dtype=np.int32)
    count = int(_kernels.components(occupied, grid.theta_full, labels))
    if min_cells > 1 and count:
        kept = np.bincount(labels.ravel(), minlength=count + 1) >= min_cells
        kept[0] = False
        renumber = np.where(kept, np.cumsum(kept), 0).astype(np.int32)
        labels = renumber[labels]
        count = int(kept.sum())
    if detected is not None and count:
        offset = int(detected.max())
        if offset + count > validate.LARGEST_LABEL:
            raise ValueError(f"the map's labels reach {offset:,}, so {count:,} more would pass "
                             f"{validate.LARGEST_LABEL:,}: pass replace=True")
        labels = np.where(labels > 0, labels + offset, detected).astype(np.int32)
    elif detected is not None:
        return 0
    occupancy.labels = labels
    return count


class Plane(NamedTuple):
    """A plane ``normal . p + offset = 0`` (unit ``normal``) and the points on it."""

    normal: np.ndarray
    offset: float
    inliers: np.ndarray  # bool, one per point given to fit_plane

    def distance(self, points):
        """Signed distance of each point from the plane (positive on the normal's side)."""
        array, single = validate.points("points", points)
        distances = array @ self.normal + self.offset
        return distances[0] if single else distances


# RANSAC scores its candidate planes on this many points; the best is then
# refitted to all of them.
_SCORED_POINTS = 20_000


def fit_plane(points, tolerance=0.02, iterations=200, seed=0):
    """Find the plane that most points lie on (RANSAC): the floor under a scene.

    Each of ``iterations`` candidates is the plane through three random
    points, scored by how many of (at most 20,000 of) the points lie within
    ``tolerance`` of it. The best is refitted by least squares to its
    inliers among all the points, which are then counted again. A fixed
    ``seed`` gives the same plane every time.

    Parameters
    ----------
    points : array_like, shape (M, 3)
        Finite points, e.g. ``depth_to_points(...).points``; M >= 3.
    tolerance : float
        How far from the plane a point may lie and still be on it (metres).
    iterations : int
        Candidate planes to try.
    seed : int
        Seed of the random choice of candidates.

    Returns
    -------
    Plane
        Its normal points to the side the map's origin is on (a floor's
        points up, towards a sensor above it), so the origin's distance
        ``offset`` is not negative; ``inliers`` marks the points within
        ``tolerance``.
    """
    array, _ = validate.points("points", points)
    tolerance = validate.finite("tolerance", tolerance)
    if not tolerance > 0:
        raise ValueError(f"tolerance must be a positive number, got {tolerance!r}")
    iterations = validate.count("iterations", iterations)
    if array.shape[0] < 3:
        raise ValueError(f"points must hold at least 3 points to fit a plane, got "
                         f"{array.shape[0]}")
    rng = np.random.default_rng(seed)
    scored = array
    if array.shape[0] > _SCORED_POINTS:
        scored = array[rng.choice(array.shape[0], _SCORED_POINTS, replace=False)]
    best_count, best = -1, None
    for _ in range(iterations):
        a, b, c = scored[rng.choice(scored.shape[0], 3, replace=False)]
        # Each side scaled to unit length first: at 1e200 the cross product of
        # the sides overflows, at 1e-200 it underflows to 0.
        sides = np.array([b - a, c - a])
        largest = np.max(np.abs(sides), axis=1)
        if not np.all(largest > 0):
            continue  # two points at one place: no plane
        sides /= largest[:, None]  # so that no square below under- or overflows
        normal = np.cross(*(sides / np.linalg.norm(sides, axis=1)[:, None]))
        length = np.linalg.norm(normal)
        if not length > 1e-12:
            continue  # three points on a line: no plane
        normal /= length
        count = np.count_nonzero(np.abs(scored @ normal - normal @ a) <= tolerance)
        if count > best_count:
            best_count, best = count, (normal, -(normal @ a))
    no_plane = ValueError("points lie on one line (or one point): they span no plane")
    if best is None:
        raise no_plane
    if best_count < 3:
        spread = float(np.max(np.ptp(array, axis=0)))
        raise ValueError(f"no plane has 3 points within tolerance={tolerance!r} of it: the "
                         f"points spread over {spread:.3g}, and the tolerance is in their unit")
    normal, offset = best
    inliers = np.abs(array @ normal + offset) <= tolerance
    # Least squares: the normal is the direction in which the inliers spread least.
    centre = array[inliers].mean(axis=0)
    _, spread, axes = np.linalg.svd(array[inliers] - centre, full_matrices=False)
    if not spread[1] > 1e-12 * spread[0]:
        raise no_plane  # on a line, up to rounding: every plane through it fits
    normal = axes[2]
    offset = -float(normal @ centre)
    if offset < 0:
        normal, offset = -normal, -offset
    return Plane(normal, offset, np.abs(array @ normal + offset) <= tolerance)


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
    _check(occupancy)
    unknown = sorted(set(fixation) - _FIXATION_OPTIONS)
    if unknown:
        raise TypeError(f"gaze_objects() takes no {', '.join(map(repr, unknown))}; it passes "
                        f"only {sorted(_FIXATION_OPTIONS)} to fixation_probability")
    if names is not None and not hasattr(names, "get"):
        raise WrongTypeError(f"names must be a mapping from label to name, got "
                             f"{type(names).__name__}")
    origin, direction = gaze_pair(gaze, direction)
    cells = fixation_probability(occupancy, origin, direction, half_angle=half_angle,
                                 n_rays=n_rays, **fixation)
    with occupancy._lock:
        labels = occupancy.labels[tuple(cells.cells.T)].astype(np.int64)
        labelled = labels > 0
        unlabelled = float(cells.values[~labelled].sum())
        if not np.any(labelled):
            return GazeObjects((), unlabelled)
        labels, values = labels[labelled], cells.values[labelled]
        first_cells, t_enter = cells.cells[labelled], cells.t_enter[labelled]
        ids, which = np.unique(labels, return_inverse=True)
        centroids, counts = _centroids(occupancy, ids)
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
        hits.append(ObjectHit(label, None if names is None else names.get(label),
                              float(sums[rank]), distance, origin + distance * axis,
                              tuple(first_cells[first[rank]].tolist()), centroids[rank],
                              int(counts[rank])))
    return GazeObjects(tuple(hits), unlabelled)


def _centroids(occupancy, ids):
    """Mean cell centre and cell count of each label in ``ids`` (sorted), in one pass."""
    flat = occupancy.labels.reshape(-1)
    where = np.flatnonzero(np.isin(flat, ids))
    which = np.searchsorted(ids, flat[where])
    cells = np.stack(np.unravel_index(where, occupancy.grid.shape), axis=1)
    centres = occupancy.grid.cell_centers(cells)
    counts = np.bincount(which, minlength=ids.shape[0])
    sums = np.stack([np.bincount(which, weights=centres[:, axis], minlength=ids.shape[0])
                     for axis in range(3)], axis=1)
    return sums / counts[:, None], counts


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
