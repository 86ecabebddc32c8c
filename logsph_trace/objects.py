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

import numpy as np

from . import _validate as validate
from .kernels import objects as _kernels
from .occupancy import _check_occupancy as _check
from .occupancy import fixation_probability


def label_objects(occupancy, threshold=0.6):
    """Label the connected groups of occupied cells as objects, in ``occupancy.labels``.

    Cells above ``threshold`` are occupied; two are connected when each of
    their indices differs by at most one (the 26-neighbourhood of index
    space), across the theta seam when the grid's azimuth is a full circle.
    Components are numbered 1, 2, ... in the map's C order; every other
    cell gets 0. The labels replace any the map had.

    Returns
    -------
    int
        The number of objects.
    """
    _check(occupancy)
    occupied = np.zeros(occupancy.grid.shape, dtype=bool)
    occupied[tuple(occupancy.occupied(threshold).T)] = True
    labels = np.zeros(occupancy.grid.shape, dtype=np.int32)
    count = _kernels.components(occupied, occupancy.grid.theta_full, labels)
    occupancy.labels = labels
    return int(count)


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
        self.half_life = validate.finite("half_life", half_life)
        if not self.half_life > 0:
            raise ValueError(f"half_life must be positive, got {half_life!r}")
        self._scores = {}
        self._time = None

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
