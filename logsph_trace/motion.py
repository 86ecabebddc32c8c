"""Rigid motions of the robot, and a map resampled into the robot's new frame.

:meth:`OccupancyGrid.move <logsph_trace.OccupancyGrid.move>` keeps the map's
cells where they were and the robot's pose within them, and resamples only
when the robot has walked far from the map's centre or when the map is read
(``docs/how-to/moving-robot.md`` says why). :func:`resample` is that step: each
cell of the robot-centred map takes the value and label of the old cell that
covers the most of its column's centre ray within its shell, traced exactly
through the old grid.
"""

import functools
import math

import numpy as np

from . import _validate as validate
from ._jit import interrupts_after
from .kernels import resample as _resample
from .sensor import pose_of
from .trace import trace_many
from .traces import TraceBuffers

# ``move`` resamples the map once the robot is this far from the map's centre,
# as a fraction of rho_min (see OccupancyGrid.move).
RECENTRE_DISTANCE = 0.5
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
    Tracing only those columns pays: a 2-degree, 1.3 cm move then reading
    ``log_odds`` took 13.6 ms against 128.0 ms with every column traced, on
    a 64 x 360 x 180 map seen in one view (22.4 against 137.3 ms seen over
    140 degrees; ``python -m bench.egomotion``, same run).
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


def resample(grid, log_odds, labels, rotation, translation, directions=None):
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
    validate.fits("log_odds", log_odds.nbytes + labels.nbytes,
                  f"resampling a map of {grid.shape} cells")
    # np.empty, not np.zeros: every cell is written, and fresh zero pages are
    # faulted in one by one (a gather took 13-34 ms instead of 3).
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
    maps each column onto another, ``n`` cells on (``0 <= n < n_theta``),
    and ``resample`` copies each shell as two blocks instead of gathering
    columns: 2.1 against 4.1 ms (a 2-cell turn and reading ``log_odds``, 64 x
    360 x 180; ``python -m bench.egomotion``, same run).
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


def one_at_a_time(method):
    """Run ``method`` under its map's lock, so that threads sharing a map take turns."""

    @functools.wraps(method)
    def locked(self, *args, **kwargs):
        with self._lock:
            return method(self, *args, **kwargs)

    return locked


class FollowsTheRobot:
    """What lets :class:`~logsph_trace.OccupancyGrid` follow a moving robot.

    The map keeps its cells where they are (``_log_odds``, ``_labels``) and
    the robot's pose within them (``_pose``, None until a move); answers read
    those cells through the pose, and arrays are resampled into the robot's
    frame (``_view``) only when read. Its methods are ``OccupancyGrid``'s;
    they live here, beside the resampling they use.
    """

    def _column_directions(self):
        """Return ``column_directions(self.grid)``, kept."""
        if self._directions is None:
            self._directions = column_directions(self.grid)
        return self._directions

    def _frame(self, write=False):
        """Return (log_odds, labels) on the host, in the robot's frame.

        Held as they are when the robot has not moved since the map was last
        centred on it; otherwise resampled (:func:`~logsph_trace.motion.resample`)
        and kept until the map or the pose changes. Neither is to be written;
        ``write``: check that the held log-odds are writeable all the same
        (a kernel is compiled for writeable arrays only).
        """
        log_odds = self._checked(write)
        if self._pose is None:
            return log_odds, self._labels
        if self._view is None:
            self._view = resample(self.grid, log_odds, self._labels, *self._pose,
                                  self._column_directions())
        return self._view

    def _drop_view(self):
        """Forget the resampled arrays: the map or the pose changed."""
        self._view = None

    def _into_held(self, origin, direction):
        """Return a gaze (origin, direction) in the robot's frame as the map holds its cells."""
        if self._pose is None:
            return origin, direction
        rotation, translation = self._pose
        return rotation @ origin + translation, rotation @ direction

    def _to_robot(self, points):
        """Return points (n, 3) given as the map holds its cells, in the robot's frame."""
        if self._pose is None:
            return points
        rotation, translation = self._pose
        return (np.asarray(points) - translation) @ rotation

    def _robot_cells(self, cells):
        """Return the robot-frame cells that hold the centres of ``cells`` (held).

        Rows of -1 where a centre lies outside the region.
        """
        if self._pose is None or not len(cells):
            return cells
        return np.atleast_2d(self.grid.cell_of(self._to_robot(self.grid.cell_centers(cells))))

    def _held_flat(self):
        """Return the log-odds as the map holds them, flat, where they live."""
        log_odds = self._log_odds if self._cuda is not None else self._checked()
        return log_odds.reshape(log_odds.size)

    def _held_values_at(self, cells):
        """Return the held log-odds of ``cells`` ((u, 3) held indices) on the host."""
        if self._cuda is None:
            return self._checked(write=False)[tuple(np.asarray(cells).T)]
        flat = np.ravel_multi_index(tuple(np.asarray(cells).T), self.grid.shape)
        return self._cuda.values_at(self._held_flat(), flat.astype(np.int64))

    def _held(self):
        """Return (log_odds, labels) on the host as the map holds them (see :meth:`move`).

        A GPU map's log-odds are copied: for the labels alone, :meth:`_held_labels`.
        """
        if self._cuda is None:
            return self._checked(write=False), self._labels
        return self._log_odds.copy_to_host(), self._labels

    def _held_labels(self):
        """Return the labels as the map holds them (on the host, for a GPU map too)."""
        return self._labels

    def _hold_labels(self, labels):
        """Replace the labels as the map holds them (int32, ``grid.shape``, checked)."""
        self._labels = labels
        self._drop_view()

    def _frame_labels(self):
        """Return the labels in the robot's frame, on the host (not to be written)."""
        return self._labels if self._pose is None else self._frame()[1]

    @interrupts_after
    @one_at_a_time
    def move(self, motion):
        """Tell the map the robot moved: later inputs, answers and arrays are in its new frame.

        Parameters
        ----------
        motion : array_like (4, 4), or (R, t)
            The robot's new pose in its old frame, as odometry gives it
            (ROS's ``T_old_new``): a point ``p`` in the old frame is
            ``R^T (p - t)`` in the new one. ``R`` must be a rotation
            (orthonormal within 1e-6, determinant +1).

        Returns
        -------
        self

        Raises
        ------
        ValueError
            ``motion`` is not a rigid motion (scaled, reflected, not
            finite, wrong shape); the map is left as it was.
        NotImplementedError
            On a GPU map (``device="cuda"``): move a host copy
            (:meth:`to_host`) instead.

        Notes
        -----
        The map keeps its cells where they are and the robot's pose within
        them: a scan or a gaze is taken into the map's cells through that
        pose, exactly, so moving costs nothing by itself. The map is
        resampled onto cells centred on the robot (:meth:`recentre`) when
        the robot has walked ``RECENTRE_DISTANCE`` (half) of ``rho_min``
        from the map's centre, or when ``log_odds`` or ``labels`` are read.
        Gazes (:func:`~logsph_trace.gaze_objects` and the others) are
        traced through the held cells, exactly; :meth:`occupied` and
        :attr:`probability` read a resampled copy, kept until the map or the
        pose changes. Each resampling blurs a little; this way a map
        is resampled about once per ``rho_min / 2`` walked, not once per
        frame (``python -m bench.egomotion`` measures both).
        ``docs/how-to/moving-robot.md`` shows the loop.
        """
        if self._cuda is not None:
            raise NotImplementedError("move is not implemented for a GPU map; move a host copy "
                                      "(to_host()) instead")
        motion = rigid_motion(motion)
        pose = motion if self._pose is None else compose(self._pose, motion)
        if np.array_equal(pose[0], np.eye(3)) and not np.any(pose[1]):
            pose = None
        self._pose = pose
        self._drop_view()
        if pose is not None and (math.hypot(*pose[1].tolist())
                                 >= RECENTRE_DISTANCE * self.grid.rho_min):
            self.recentre()
        return self

    @interrupts_after
    @one_at_a_time
    def recentre(self):
        """Resample the map onto cells centred on the robot now; return self.

        :meth:`move` does it when the robot has walked far from the map's
        centre, and reading ``log_odds`` or ``labels`` does it; otherwise
        there is no need. Each new cell takes the value and label of the
        old cell that covers the most of its column's centre ray within
        its shell, traced exactly through the old cells
        (:func:`~logsph_trace.motion.resample`); cells from outside the old
        region are unknown.
        """
        if self._pose is not None:
            self._frame()
            (self._log_odds, self._labels), self._view = self._view, None
            self._pose = None
        return self
