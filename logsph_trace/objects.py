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
from .kernels import objects as _kernels
from .occupancy import _check_occupancy as _check
from .occupancy import fixation_probability


def label_objects(occupancy, threshold=0.6, exclude=None, min_cells=1):
    """Label the connected groups of occupied cells as objects, in ``occupancy.labels``.

    Cells above ``threshold`` are occupied; two are connected when each of
    their indices differs by at most one (the 26-neighbourhood of index
    space), across the theta seam when the grid's azimuth is a full circle.
    Components are numbered 1, 2, ... in the map's C order of their first
    cell; every other cell gets 0. The labels replace any the map had.

    Objects that stand on a floor touch it, and so each other: leave the
    floor out with ``exclude`` (:func:`fit_plane` finds it, and
    :meth:`Grid.count_points` puts its points in cells). A depth camera's
    pixels on a silhouette often fall between the object and what lies
    behind it, a few to a cell, and can chain the two together: leaving out
    cells that hold only a few points of a scan breaks such chains (see the
    README's motorcycle example).

    Parameters
    ----------
    occupancy : OccupancyGrid
    threshold : float
        Probability above which a cell is occupied.
    exclude : array_like of bool, shape ``grid.shape``, optional
        Cells that belong to no object and connect none, occupied or not.
    min_cells : int
        Components with fewer cells are left unlabelled (0), as noise.

    Returns
    -------
    int
        The number of objects.
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
    labels = np.zeros(grid.shape, dtype=np.int32)
    count = int(_kernels.components(occupied, grid.theta_full, labels))
    if min_cells > 1 and count:
        kept = np.bincount(labels.ravel(), minlength=count + 1) >= min_cells
        kept[0] = False
        renumber = np.where(kept, np.cumsum(kept), 0).astype(np.int32)
        labels = renumber[labels]
        count = int(kept.sum())
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


@dataclass(frozen=True)
class GazeObjects:
    """The objects a gaze may stop at, most probable first.

    Attributes
    ----------
    labels : numpy.ndarray, int, shape (k,)
        Object labels (never 0).
    probabilities : numpy.ndarray, float64, shape (k,)
        The probability that the gaze stops at the object first: its cells'
        fixation probabilities summed (see :func:`fixation_probability`).
    first_cells : numpy.ndarray, int32, shape (k, 3)
        Each object's cell the gaze reaches first.
    first_distances : numpy.ndarray, float64, shape (k,)
        The distance from the eyes at which the gaze reaches that cell.
    unlabelled : float
        The probability of stopping at occupied cells that carry no label.
    """

    labels: np.ndarray
    probabilities: np.ndarray
    first_cells: np.ndarray
    first_distances: np.ndarray
    unlabelled: float

    def __len__(self):
        return self.labels.shape[0]

    @property
    def top(self):
        """The most probable object's label, or 0 if the gaze stops at none."""
        return int(self.labels[0]) if len(self) else 0


DEFAULT_HALF_ANGLE = math.radians(5.0)


# What gaze_objects passes on to fixation_probability (``dense`` would change
# the result's type under it).
_FIXATION_OPTIONS = frozenset(
    ("pattern", "weighting", "sigma", "unknown", "free_below", "min_distance"))


def gaze_objects(occupancy, origin, direction, half_angle=DEFAULT_HALF_ANGLE, n_rays=None,
                 **fixation):
    """Rank the map's objects by the probability that the gaze reaches them first.

    Parameters
    ----------
    occupancy : OccupancyGrid
        A map with object labels (:attr:`OccupancyGrid.labels`).
    origin, direction : array_like, shape (3,)
        The eyes and the gaze direction, in the map's frame.
    half_angle : float
        The gaze cone's half-angle, radians: the gaze estimator's angular
        error (see :func:`gaze_from_pitch_yaw`). Default 5 degrees.
    n_rays : int, optional
        Rays in the cone (default: :func:`~logsph_trace.default_ray_count`'s rule).
    **fixation
        Passed to :func:`fixation_probability` (``pattern``, ``weighting``,
        ``sigma``, ``unknown``, ``free_below``, ``min_distance``).

    Returns
    -------
    GazeObjects
    """
    _check(occupancy)
    unknown = sorted(set(fixation) - _FIXATION_OPTIONS)
    if unknown:
        raise TypeError(f"gaze_objects() takes no {', '.join(map(repr, unknown))}; it passes "
                        f"only {sorted(_FIXATION_OPTIONS)} to fixation_probability")
    cells = fixation_probability(occupancy, origin, direction, half_angle=half_angle,
                                 n_rays=n_rays, **fixation)
    labels = occupancy.labels[tuple(cells.cells.T)].astype(np.int64)
    labelled = labels > 0
    unlabelled = float(cells.values[~labelled].sum())
    if not np.any(labelled):
        return GazeObjects(np.empty(0, dtype=np.int64), np.empty(0),
                           np.empty((0, 3), dtype=np.int32), np.empty(0), unlabelled)
    labels, values = labels[labelled], cells.values[labelled]
    first_cells, t_enter = cells.cells[labelled], cells.t_enter[labelled]
    names, which = np.unique(labels, return_inverse=True)
    sums = np.bincount(which, weights=values)
    # Each object's first-reached cell: the smallest distance among its cells.
    order = np.lexsort((t_enter, which))
    first = order[np.searchsorted(which[order], np.arange(names.shape[0]))]
    rank = np.argsort(-sums, kind="stable")
    return GazeObjects(names[rank], sums[rank], first_cells[first][rank],
                       t_enter[first][rank], unlabelled)


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
        for label, probability in zip(objects.labels.tolist(), objects.probabilities.tolist()):
            self._scores[label] = self._scores.get(label, 0.0) + probability
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
