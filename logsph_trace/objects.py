"""Objects in the map: connected groups of occupied cells, and the floor they stand on.

The paper's question is which object a person is staring at; cells answer
"where". A map's cells carry object labels: voted in from a 2-D detector's
instance image (``integrate_depth(..., labels=...)``), or found as connected
components of occupied cells (:func:`label_objects`), with the floor
(:func:`fit_plane`) left out. :func:`~logsph_trace.gaze_objects` ranks them.
"""

import math
import mmap
from typing import NamedTuple

import numpy as np

from . import _validate as validate
from .kernels import objects as _kernels
from .occupancy import _check_occupancy as _check
from .occupancy import _logit


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
    threshold = validate.probability("threshold", threshold)
    grid = occupancy.grid
    if exclude is not None:
        mask = np.asarray(exclude)
        if mask.shape != grid.shape or mask.dtype != np.bool_:
            raise ValueError(f"exclude must be a boolean array of shape {grid.shape}, got "
                             f"{mask.dtype} of shape {mask.shape}")
    with occupancy._lock:
        if exclude is not None:
            occupancy.recentre()  # the mask is in the robot's frame
        # Components are the same in any frame: they are found in the cells
        # as the map holds them, so a moved map is not resampled for them.
        log_odds, held = occupancy._held()
        labels, count = _components(log_odds > _logit(threshold),
                                    None if exclude is None else mask,
                                    None if replace else held, grid.theta_full, min_cells)
        if labels is not None:
            occupancy._hold_labels(labels)
    return count


# Arrays of zeros at least this large come from fresh pages (``_untouched_zeros``).
ZEROS_FROM_SYSTEM = 1 << 20


def _untouched_zeros(shape, dtype):
    """``np.zeros(shape, dtype)`` in fresh pages from the system, zero until written.

    A map's labels are mostly 0, and ``label_objects`` writes a few
    thousand of its millions; numpy's zeros of the same 16 MB, once the
    allocator keeps such blocks, clears every byte first (1.7 ms against
    0.2 in a replay without a label topic; ``python -m bench.replay``
    A/Bs the two).
    """
    size = math.prod(shape) * np.dtype(dtype).itemsize
    if size < ZEROS_FROM_SYSTEM:
        return np.zeros(shape, dtype=dtype)
    return np.frombuffer(mmap.mmap(-1, size), dtype=dtype).reshape(shape)


def _components(occupied, exclude, detected, theta_full, min_cells):
    """``label_objects`` on the arrays: return (labels or None to keep the map's, count)."""
    if exclude is not None:
        occupied &= ~exclude
    if detected is not None:
        occupied &= detected == 0
    labels = _untouched_zeros(occupied.shape, np.int32)
    count = int(_kernels.components(occupied, theta_full, np.flatnonzero(occupied), labels))
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
        return None, 0
    return labels, count


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
