"""Rigid motions of the robot, and a map resampled into the robot's new frame.

:meth:`OccupancyGrid.move <logsph_trace.OccupancyGrid.move>` keeps the map's
cells where they were and the robot's pose within them, and resamples only
when the robot has walked far from the map's centre or when the map is read
(``docs/how-to/moving-robot.md`` says why). :func:`resample` is that step: each
cell of the robot-centred map takes the value and label of the old cell that
covers the most of its column's centre ray within its shell, traced exactly
through the old grid.
"""

import math
import sys

import numpy as np

from . import _validate as validate
from .kernels import resample as _resample
from .sensor import pose_of
from .trace import trace_many
from .traces import TraceBuffers

# Centre rays traced at a time: their segments (about 100 a ray on a
# 64 x 360 x 180 grid, 28 bytes each) stay under 30 MB, reused chunk to chunk.
COLUMNS_PER_CHUNK = 8192


def rigid_motion(motion, name="motion"):
    """Check a rigid motion: return ``(R (3, 3), t (3,))`` as float64.

    ``motion``: a 4 x 4 matrix with last row ``(0, 0, 0, 1)``, or a pair
    ``(R, t)``. ``R`` must be a rotation: orthonormal within 1e-6 and
    determinant +1 (no scaling, no reflection); all of it finite.
    """
    if motion is None:
        raise ValueError(f"{name} must be a 4 x 4 matrix or (R, t), got None")
    return pose_of(motion, name)


def compose(first, second):
    """Return the motion ``first`` then ``second`` (``second`` in ``first``'s frame).

    Each is ``(R, t)``.

    The product's rotation is made orthonormal again (to rounding), so that
    thousands of small motions do not drift into a scaled one.
    """
    rotation = first[0] @ second[0]
    u, _, vt = np.linalg.svd(rotation)
    return u @ vt, first[0] @ second[1] + first[1]


def column_directions(grid):
    """Return the centre ray's unit vector of each (theta, phi) column, (n_theta * n_phi, 3)."""
    theta = 0.5 * (grid.theta_edges[:-1] + grid.theta_edges[1:])
    phi = 0.5 * (grid.phi_edges[:-1] + grid.phi_edges[1:])
    cos_phi = np.cos(phi)
    directions = np.empty((grid.n_theta, grid.n_phi, 3))
    directions[..., 0] = np.sin(theta)[:, None] * cos_phi[None, :]
    directions[..., 1] = np.sin(phi)[None, :]
    directions[..., 2] = np.cos(theta)[:, None] * cos_phi[None, :]
    return directions.reshape(-1, 3)


def _near_seen(grid, seen, delta):
    """Old columns within ``delta`` radians of a column with a known cell, (n_theta, n_phi).

    A new column's centre ray, from a point at distance ``d < rho_min`` from
    the old centre, stays within ``asin(d / rho_min)`` of its direction
    wherever it is in the region (it leaves the old gap's sphere once, in
    front of that point, and the sine of its angle to its direction there
    is at most ``d / rho_min``): where its direction's old
    column is not near a known one, the whole column is unknown. In azimuth
    the reach widens towards the poles as ``1 / cos(phi)`` (the haversine
    bound), and a row within ``delta`` of a pole reaches all the way round.
    """
    seen = seen.reshape(grid.n_theta, grid.n_phi)
    half_pi = 0.5 * np.pi
    low = grid.phi_edges[:-1] - delta
    high = grid.phi_edges[1:] + delta
    whole = (low <= -half_pi) | (high >= half_pi)
    cosine = np.minimum(np.cos(np.clip(low, -half_pi, half_pi)),
                        np.cos(np.clip(high, -half_pi, half_pi)))
    ratio = math.sin(0.5 * delta) / np.where(whole, 1.0, cosine)
    whole |= ratio >= 1.0
    spread = 2.0 * np.arcsin(np.minimum(ratio, 1.0))
    reach = np.ceil(spread / np.diff(grid.theta_edges).min()).astype(np.int64) + 1
    reach[whole] = -1
    near = np.empty_like(seen)
    _resample.dilate(seen, reach, grid.theta_full, near)
    rows = math.ceil(delta / np.diff(grid.phi_edges).min()) + 1
    out = np.empty_like(seen.T)
    _resample.dilate(np.ascontiguousarray(near.T), np.full(grid.n_theta, rows), False, out)
    return out.T


def unshared(array):
    """Whether nothing but the caller holds ``array`` (and it owns its memory).

    A map's arrays that it replaces are kept as the next resampling's output
    only then: an array a user still holds is never written behind their back.
    """
    # The references: the caller's, this parameter, getrefcount's argument.
    return array is not None and array.base is None and sys.getrefcount(array) <= 3


def resample(grid, log_odds, labels, rotation, translation, directions=None, out=None):
    """Return the map seen from a frame at ``(rotation, translation)`` in the map's frame.

    Parameters
    ----------
    grid : Grid
    log_odds : numpy.ndarray, float32, shape ``grid.shape``
    labels : numpy.ndarray, int32, shape ``grid.shape``
    rotation, translation : numpy.ndarray, (3, 3) and (3,)
        The new frame in the old one: an old point ``p`` is ``R^T (p - t)``
        in the new frame.
    directions : numpy.ndarray, optional
        ``column_directions(grid)``, when the caller keeps it.
    out : (numpy.ndarray, numpy.ndarray), optional
        Arrays of the result's shapes and dtypes to write it into, so that
        a map resampled often reuses its memory.

    Returns
    -------
    (numpy.ndarray, numpy.ndarray)
        The new frame's log-odds (float32) and labels (int32), shape ``grid.shape``.

    Notes
    -----
    New cell ``(i, j, k)`` takes the log-odds and label of the old cell that
    covers the most of column ``(j, k)``'s centre ray between
    ``rho_edges[i]`` and ``rho_edges[i+1]`` (traced exactly through the old
    grid; the first of equals). Not a mean: a mean spreads each occupied
    cell into the next shell, which is unknown behind a surface, and
    thickens the map at each resampling. A new cell whose ray never enters
    the old region there is unknown (0), and so is a column no known old
    cell (log-odds not 0) is near: a label on a cell never observed does
    not move. With no translation
    the ray is radial and the shells are the same: each new column is one
    old column, copied, so a rotation by whole azimuth cells of a
    full-circle grid is an index roll, bit for bit.
    """
    if out is None:
        validate.fits("log_odds", log_odds.nbytes + labels.nbytes,
                      f"resampling a map of {grid.shape} cells")
        out = np.empty(grid.shape, dtype=np.float32), np.empty(grid.shape, dtype=np.int32)
    if directions is None:
        directions = column_directions(grid)
    flat_log_odds, flat_labels = log_odds.reshape(-1), labels.reshape(-1)
    out_log_odds, out_labels = out[0].reshape(-1), out[1].reshape(-1)
    distance = math.hypot(*translation.tolist())
    if distance == 0.0:
        turn = whole_cell_turn(grid, rotation)
        if turn is not None:
            _resample.roll_columns(flat_log_odds, flat_labels, turn * grid.n_phi, grid.n_rho,
                                   out_log_odds, out_labels)
            return out
    plane = grid.n_theta * grid.n_phi
    aimed = np.empty((plane, 3))
    source = np.empty(plane, dtype=np.int64)
    _resample.aim_columns(directions, np.ascontiguousarray(rotation), grid.kernel_args(), aimed,
                          source)
    if distance == 0.0:
        _resample.gather_columns(flat_log_odds, flat_labels, source, grid.n_rho, out_log_odds,
                                 out_labels)
        return out
    if distance < grid.rho_min:
        seen = np.empty(plane, dtype=np.uint32)
        _resample.seen_columns(flat_log_odds.view(np.uint32), grid.n_rho, seen)
        near = _near_seen(grid, seen, math.asin(distance / grid.rho_min)).reshape(-1)
        columns = np.flatnonzero((source < 0) | (near[np.maximum(source, 0)] != 0))
    else:
        columns = np.arange(plane)
    values = np.empty((columns.shape[0], grid.n_rho), dtype=np.float32)
    value_labels = np.empty((columns.shape[0], grid.n_rho), dtype=np.int32)
    buffers = TraceBuffers()
    for first in range(0, columns.shape[0], COLUMNS_PER_CHUNK):
        chunk = columns[first:first + COLUMNS_PER_CHUNK]
        traces = trace_many(grid, translation, aimed[chunk], out=buffers)
        _resample.copy_along_columns(first, traces.offsets, traces.cells, traces.t_enter,
                                     traces.t_exit, grid.rho_edges, flat_log_odds, flat_labels,
                                     grid.n_phi, values, value_labels)
    slot = np.full(plane, -1, dtype=np.int64)
    slot[columns] = np.arange(columns.shape[0])
    _resample.place_columns(slot, values, value_labels, out_log_odds, out_labels)
    return out


def whole_cell_turn(grid, rotation):
    """Return ``n`` when ``rotation`` turns by ``n`` whole azimuth cells about +y, else None.

    Only on a full-circle grid with equal azimuth cells: there such a turn
    maps each column onto another, ``n`` cells on (``0 <= n < n_theta``).
    """
    if not grid.theta_full or not np.allclose(rotation[1], (0.0, 1.0, 0.0), rtol=0.0,
                                              atol=1e-12):
        return None
    widths = np.diff(grid.theta_edges)
    cell = 2.0 * np.pi / grid.n_theta
    if np.max(np.abs(widths - cell)) > 1e-12:
        return None
    angle = math.atan2(rotation[0, 2], rotation[0, 0])
    turn = round(angle / cell)
    expected = np.array([[math.cos(turn * cell), 0.0, math.sin(turn * cell)], [0.0, 1.0, 0.0],
                         [-math.sin(turn * cell), 0.0, math.cos(turn * cell)]])
    if np.max(np.abs(rotation - expected)) > 1e-12:
        return None
    return turn % grid.n_theta
