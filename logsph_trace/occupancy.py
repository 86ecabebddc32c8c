"""The occupancy map (the paper's BVM, section 3.3).

:class:`OccupancyGrid` stores log-odds per cell of a :class:`~logsph_trace.Grid`
and integrates sensor scans as OctoMap does: each ray carves free space up to
its end point and marks the end cell occupied, every cell updated at most once
per scan (a hit wins over a miss), log-odds clamped so the map stays able to
change. What a gaze lands on in it is :mod:`logsph_trace.gaze`'s.
"""

import contextlib
import math
import threading
import time
import zipfile
from dataclasses import dataclass
from pathlib import Path

import numba
import numpy as np

from . import _validate as validate
from ._batching import lap
from ._files import atomic_write, npz_path, write_npz
from ._jit import interrupts_after
from .grid import Grid
from .kernels import coherent as _coherent
from .kernels import objects as _objects
from .kernels import radial as _radial
from .kernels import update as _update
from .kernels.geometry import AT_CENTRE
from .motion import FollowsTheRobot, compose, one_at_a_time, rigid_motion
from .sensor import depth_to_points, pose_of
from .trace import cuda_backend


@dataclass(frozen=True)
class ScanStats:
    """What a scan put into the map.

    Attributes
    ----------
    rays : int
        Rays integrated (points, or pixels with a depth).
    invalid : int
        Points or pixels skipped: NaN or infinite points, pixels without
        depth (0, NaN, infinite, negative).
    """

    rays: int
    invalid: int


def _logit(p):
    return float(np.log(p / (1.0 - p)))


# A scan from inside the egocentric gap with at least this many rays is marked
# coherently (``_mark_off_centre``); fewer are all walked whole.
COHERENT_MIN_RAYS = 20_000
# The direction bins of the coherent scan: about this many across the narrowest
# cell as seen from the sensor, and at most COHERENT_MAX_BINS per cube face side.
BINS_PER_CELL = 4
COHERENT_MAX_BINS = 1024
# A sample (the first ray of a coarse bin) for about this many rays, and the
# scan's extent, to size the coarse bins by, from every EXTENT_STRIDE-th ray.
RAYS_PER_SAMPLE = 80
EXTENT_STRIDE = 64


def _coherent_plan(grid, origin, n_rays):
    """Return the cube-map bins per face side for a coherent scan, or 0 where it does not apply.

    It applies to a sensor off the centre in the egocentric gap, a grid with
    full theta and phi ranges (a walk then never leaves the region) and
    enough rays.
    """
    # In Python floats: numpy's per-call cost is paid on one thread, before
    # the scan's parallel work (the same values: np.sum adds three in order).
    x, y, z = origin.tolist()
    distance = math.sqrt(x * x + y * y + z * z)
    rho_min, phi_range = grid.rho_min, grid.phi_range
    if (n_rays < COHERENT_MIN_RAYS or not 0.0 < distance < rho_min
            or not grid.theta_full or phi_range[0] > -np.pi / 2 or phi_range[1] < np.pi / 2):
        return 0
    # Bins a quarter of the narrowest cell as seen from the sensor, so that a
    # bin's limit, which all its rays share, follows the candidates' shadows
    # closely.
    step = grid._narrowest_angle * rho_min / (rho_min + distance) / BINS_PER_CELL
    if step * COHERENT_MAX_BINS <= 2.0:  # also a step that underflows to 0
        return COHERENT_MAX_BINS
    return max(math.ceil(2.0 / step), 8)


def _coarsening(per_side, n_rays, extent):
    """Return the bins across a coarse bin, so that one holds about ``RAYS_PER_SAMPLE`` rays.

    A coarse bin's first ray is a sample, walked whole: the more of the other
    rays share its cells, the more it saves them. The rays per bin are
    ``n_rays`` over the bins in the faces' boxes of ``extent``
    (``kernels.coherent.ray_extent``), at ``per_side`` bins a side. A coarse bin is
    at most ``BINS_PER_CELL`` bins across, about the narrowest cell, so that
    the samples cross most cells near the sensor: twice as wide, the table
    scan 10 cm off took 318 ms instead of 48. The real Motorcycle frame, dense
    (343,274 rays over 41 x 28 degrees), takes a sample per 3 x 3 bins; the
    table scan (304,000 over 60 x 45) per 4 x 4 (``python -m bench.occupancy``).
    """
    area = 0.0
    for low_u, high_u, low_v, high_v in extent.tolist():
        if high_u >= low_u:
            area += (high_u - low_u) * (high_v - low_v)
    per_bin = n_rays / max(area * (0.5 * per_side) ** 2, 1.0)
    return min(max(round(math.sqrt(RAYS_PER_SAMPLE / per_bin)), 1), BINS_PER_CELL)


# Votes are sorted by one key, cell * (largest label + 1) + label, where it
# fits in this; by two (``lexsort``) where it would not.
SORT_KEY_MAX = np.iinfo(np.int64).max


# A scan's flags (a byte per cell, shared by the threads) are kept zero for
# this Python thread's next scan up to this size; a larger set is freed
# after its scan.
KEEP_FLAG_BYTES = 1 << 27
_flags = threading.local()


@contextlib.contextmanager
def _zeroed_scratch(kind, shape, dtype):
    """Yield a zero array of ``shape`` that the block must leave zero; one per ``kind``.

    The kernels that read a scan's flags clear them as they go
    (``apply_scan``, ``apply_radial``), so the next scan in this Python thread
    reuses them instead of zeroing fresh memory on one thread (a 4 MB
    ``np.zeros`` per scan on the benchmark's map). Held per Python
    thread, so concurrent scans never share them; an exception drops them.
    """
    held = getattr(_flags, kind, None)
    setattr(_flags, kind, None)  # taken: kept again only when the block ends cleanly
    if held is None or held.shape != shape or held.dtype != dtype:
        held = None  # the old set is freed before the new one is made
        held = np.zeros(shape, dtype=dtype)
    yield held
    if held.nbytes <= KEEP_FLAG_BYTES:
        setattr(_flags, kind, held)


def _mark_off_centre(grid, origin, points, max_range, free, hits, words, view, workers):
    """Flag the cells the rays from ``origin`` cross (``kernels.coherent.mark_scan``).

    From inside the egocentric gap (``_coherent_plan``), most crossings lie
    near the sensor, where neighbouring rays cross the same cells. There the
    scan is marked coherently, with the same cells as walking every ray:

    1. Rays are binned by direction (a cube map, bins about a quarter of a
       cell wide as seen from the sensor); the first ray of each coarse bin
       (``_coarsening`` bins across, about ``RAYS_PER_SAMPLE`` rays), a
       sample, is walked whole.
    2. A cell the samples did not flag that another ray's walk could meet
       first is a shell-0 cell (its first) or a neighbour of a flagged one:
       a candidate. Each direction bin gets a limit, the lowest shell of a
       candidate that a direction in it meets (``kernels.coherent.mark_candidates``).
    3. The other rays start on the inner sphere of their bin's limit, or the
       last one below it they cross: every cell they cross below it was
       flagged by a sample. Near the sensor that is most cells; a ray far
       from the silhouettes of nearer things starts close to its end. One
       that ends below its limit adds only its hit cell, and one that stays
       in one column from there adds that column's shells: when its end
       point is clear of the cell's faces, neither is walked.

    ``free`` and ``words``: the scan's flags (``apply_scan``), shared by the
    ``workers`` (one per thread); ``hits``
    gets each ray's hit cell; ``view`` (a byte per column) the columns some
    ray may meet (``kernels.coherent.columns_in_view``; all of them when the scan
    is walked ray by ray), the only ones ``apply_scan`` reads. Returns how
    many rays were let start beyond the gap's sphere, how many of those
    ended below it and how many stayed in one column (the last two not
    walked; 0, 0, 0 when the scan was walked ray by ray).
    """
    args = grid.kernel_args()
    no_rows = np.empty(0, dtype=np.int64)
    no_marks = np.empty(0, dtype=np.uint8)
    per_side = _coherent_plan(grid, origin, points.shape[0])
    if per_side == 0:
        view[:] = 1
        _coherent.mark_scan(origin, points, max_range, args, free, hits, _coherent.WALK_ALL,
                           no_rows, no_rows, no_rows, no_marks, 0, workers)
        return 0, 0, 0
    n_bins = 6 * per_side * per_side
    bins = np.empty(points.shape[0], dtype=np.int64)
    coarse_bins = np.empty(points.shape[0], dtype=np.int64)
    boxes = np.empty((6, 4))
    _coherent.ray_extent(origin, points, EXTENT_STRIDE, boxes)
    coarse = max(per_side // _coarsening(per_side, points.shape[0], boxes), 1)
    first = np.empty(6 * coarse * coarse, dtype=np.int64)
    _coherent.bin_rays(origin, points, per_side, coarse, bins, coarse_bins, first, boxes)
    _coherent.mark_scan(origin, points, max_range, args, free, hits, _coherent.WALK_SAMPLES,
                       coarse_bins, first, bins, no_marks, 0, workers)
    rays = np.empty(4)
    # Every ray's coarse bin holds a sample: the cone of those bins holds every ray.
    _coherent.ray_cone(first, points.shape[0], coarse, workers, rays)
    _coherent.columns_in_view(origin, args, rays, view)
    skip = min(grid.n_rho - 1, 63)  # the masks' 64 bits
    masks = np.empty(grid.n_theta * grid.n_phi, dtype=np.uint64)
    _coherent.near_masks(words, grid.n_rho, skip, view, masks, workers)
    limit = np.empty(n_bins, dtype=np.uint8)
    _coherent.mark_candidates(origin, args, masks, skip, per_side, rays, view, boxes, limit,
                             workers)
    started, ended, straight = _coherent.mark_scan(origin, points, max_range, args, free, hits,
                                                   _coherent.WALK_OTHERS, coarse_bins, first,
                                                   bins, limit, skip, workers)
    return int(started), int(ended), int(straight)


def _warn_nothing_inside(grid, points):
    """Warn when no point of a scan landed in a cell and most lie beyond the grid's radii.

    That is a mistake of units (millimetres as metres) or of frames; a scan
    whose points lie within the radii but outside a partial grid's angles,
    or beyond ``max_range``, is not.
    """
    reach = np.linalg.norm(points, axis=1)
    median = float(np.median(reach))
    if grid.rho_min <= median <= grid.rho_max:
        return
    validate.warn(
        f"none of the scan's {points.shape[0]:,} points lies in the map: they lie "
        f"{median:.3g} from its centre (median), and the map reaches from {grid.rho_min:g} to "
        f"{grid.rho_max:g}. Are the points and the grid in one unit (depth_scale) and one "
        f"frame (pose)?", validate.DepthUnitWarning)


class _Probability:
    """An attribute that holds a probability in (low, high), checked on every assignment.

    The kernels take its logit: a value outside the range would turn the
    whole map into NaN without an error.
    """

    def __init__(self, low, high):
        self.low, self.high = low, high

    def __set_name__(self, owner, name):
        self.name = name

    def __get__(self, obj, owner=None):
        return self if obj is None else obj.__dict__[self.name]

    def __set__(self, obj, value):
        obj.__dict__[self.name] = validate.probability(self.name, value, self.low, self.high)


class OccupancyGrid(FollowsTheRobot):
    """Log-odds occupancy over a grid, updated OctoMap-style.

    Parameters
    ----------
    grid : Grid
    p_hit, p_miss : float
        Probability a cell is occupied given a ray ended in it (> 0.5), or
        crossed it (< 0.5). OctoMap's defaults: 0.7 and 0.4.
    p_min, p_max : float
        Clamping bounds (OctoMap: 0.1192 and 0.971), so a cell can always
        change again within a few scans.

    log_odds : array_like, shape ``grid.shape``, optional
        A starting map (e.g. one from elsewhere); default all unknown.
    device : {"cpu", "cuda"}
        ``"cuda"``: the map lives on an NVIDIA GPU (numba-cuda, ``pip install
        "logsph_trace[cuda]"``), and ``integrate``, ``decay``,
        :func:`gaze_targets` and :func:`fixation_probability` run there, with
        the CPU's per-ray code. Saving and loading go through the host.

    Attributes
    ----------
    grid : Grid
        Read-only: a map's cells are fixed when it is made.
    log_odds : numpy.ndarray, float32, C-contiguous, shape ``grid.shape``
        0 is unknown (p = 0.5), in the robot's frame (after a :meth:`move`,
        read it again). Its values may be changed in place, its
        shape and dtype may not (the next use raises ValueError), and it must
        stay writeable for the calls that use it in a kernel.
        Assigning an array checks its shape and values and stores a
        C-contiguous float32 copy (an assigned array that is already one is
        used as it is). On a GPU map, a numba-cuda device array (CUDA Array
        Interface); assigning a host array copies it to the device.
    device : str
        ``"cpu"`` or ``"cuda"``.
    p_hit, p_miss, p_min, p_max : float
        As the parameters; assigning one checks its range, and the next
        scan uses it.

    Raises
    ------
    RuntimeError
        ``device="cuda"`` without a usable GPU or numba-cuda.

    Notes
    -----
    The map is egocentric: :meth:`move` tells it the robot moved, and every
    later input, answer and array is in the robot's new frame.

    A map may be shared by threads: its methods, the assignments above and
    the gaze functions that read it take turns on a lock of the map's own,
    so each scan is applied whole. Changing ``log_odds`` in place, outside
    those calls, is not guarded.
    """

    p_hit = _Probability(0.5, 1.0)
    p_miss = _Probability(0.0, 0.5)
    p_min = _Probability(0.0, 0.5)
    p_max = _Probability(0.5, 1.0)

    def __init__(self, grid, p_hit=0.7, p_miss=0.4, p_min=0.1192, p_max=0.971, log_odds=None,
                 device="cpu"):
        validate.grid(grid)
        self._device = validate.device(device)
        self._cuda = cuda_backend() if device == "cuda" else None
        # log_odds and labels (4 bytes a cell each), and in integrate a byte per cell
        validate.fits("grid", int(np.prod(grid.shape, dtype=np.float64)) * 9,
                      f"an occupancy map of {grid.shape} cells")
        self._grid = grid
        self._lock = threading.RLock()  # one thread at a time changes or reads the map
        self._last_scan = None
        self._labels = np.zeros(grid.shape, dtype=np.int32)
        # The robot's pose in the frame the arrays are held in (None: the
        # same frame), and the arrays resampled into the robot's frame for
        # it (None until a call needs them); see move.
        self._pose = None
        self._view = None
        self._directions = None
        self.p_hit, self.p_miss, self.p_min, self.p_max = p_hit, p_miss, p_min, p_max
        if log_odds is None:
            log_odds = np.zeros(grid.shape, dtype=np.float32)
        self.log_odds = log_odds

    def __getstate__(self):
        state = self.__dict__.copy()
        del state["_lock"]  # a lock is not copied: each copy gets its own
        state["_view"] = None  # a cache, made again when needed
        return state

    def __setstate__(self, state):
        self.__dict__.update(state)
        self._lock = threading.RLock()

    @property
    def grid(self):
        """The map's grid (read-only)."""
        return self._grid

    @property
    def log_odds(self):
        """Log-odds per cell, float32, shape ``grid.shape`` (see the class docstring).

        After a :meth:`move` reading it resamples the map into the robot's
        frame first (:meth:`recentre`).
        """
        with self._lock:
            self.recentre()
            return self._log_odds

    @log_odds.setter
    def log_odds(self, value):
        # The kernels index this array as a flat C-ordered block of grid.shape:
        # any other shape, layout or a read-only buffer would be written out of
        # bounds, lost in a copy, or refused by Numba.
        value = validate.log_odds(value, self._grid.shape)
        with self._lock:
            self.recentre()  # the labels into the frame the new values are in
            self._log_odds = value if self._cuda is None else self._cuda.to_device(value)
            self._drop_view()

    @property
    def device(self):
        """Where the map lives: ``"cpu"`` or ``"cuda"``."""
        return self._device

    def _host_log_odds(self):
        """Return the log-odds in the robot's frame as a numpy array (a copy from a GPU map)."""
        return self._frame()[0] if self._cuda is None else self._log_odds.copy_to_host()

    def _checked(self, write=True):
        """Return the host map, after checking it is still what the kernels index.

        The kernels index it as ``grid.size`` float32 cells (``validate.held``).
        ``write=False``: for numpy reads, which need not write.
        """
        validate.held("log_odds", self._log_odds, np.float32, self._grid.shape,
                      "assign a new array to log_odds instead", write)
        return self._log_odds

    def to_host(self):
        """Return the map on the CPU: ``self`` for a CPU map, else a copy."""
        if self._cuda is None:
            return self
        host = OccupancyGrid(self.grid, self.p_hit, self.p_miss, self.p_min, self.p_max,
                             log_odds=self._host_log_odds())
        host.labels = self._labels
        return host

    def __repr__(self):
        occupied = int(np.count_nonzero(self._host_log_odds() > 0))
        where = "" if self._cuda is None else ", on the GPU"
        return f"OccupancyGrid({self.grid}, {occupied} cells above p = 0.5{where})"

    @property
    def probability(self):
        """Occupancy probability per cell, float64, shape ``grid.shape`` (on the host)."""
        return 1.0 / (1.0 + np.exp(-self._host_log_odds().astype(np.float64)))

    def occupied(self, threshold=0.6):
        """Cells whose probability exceeds ``threshold``, shape (u, 3) (on the host)."""
        threshold = validate.probability("threshold", threshold)
        return np.argwhere(self._host_log_odds() > _logit(threshold)).astype(np.int32)

    @interrupts_after
    @one_at_a_time
    def integrate(self, points, sensor_origin, max_range=None, invalid="raise", labels=None):
        """Integrate one scan: free space along each sensor ray, its end cell occupied.

        Parameters
        ----------
        points : array_like, shape (M, 3)
            End points of the sensor rays (a point cloud), in the grid's frame.
        sensor_origin : array_like, shape (3,)
            Where the rays start.
        max_range : float, optional
            Points farther than this from the sensor carve free space up to
            ``max_range`` and mark nothing occupied (OctoMap's maxrange, for
            unreliable far returns).
        invalid : {"raise", "skip"}
            What a NaN or infinite point means. ``"raise"`` (default): a
            mistake, a ``ValueError``. ``"skip"``: a sensor's "no return"
            (organised point clouds mark missing pixels with NaN): the row is
            skipped and counted in :attr:`last_scan`. A point at the sensor
            itself is no ray and changes nothing.
        labels : array_like of int, shape (M,), optional
            The object each point lies on (0 = none), e.g. from a 2-D
            detector. Each cell a ray ends in takes the label most of this
            scan's hits in it carry (ties: the smaller label); other cells
            keep theirs (see :attr:`labels`).

        Returns
        -------
        self

        Notes
        -----
        A scan's flags (for a sensor off the centre, a byte per cell,
        shared by the threads: 4 MB for a 64 x 360 x 180 map) are kept for
        the next scan in the same Python thread, up to 128 MB, so that
        repeated scans do not zero fresh memory each time.
        """
        return self._integrate(points, sensor_origin, max_range, invalid, labels, self._pose)

    def _integrate(self, points, sensor_origin, max_range, invalid, labels, pose):
        """Integrate as ``integrate`` does, after taking the scan through ``pose``.

        ``pose`` ((R, t) or None): into the frame the map is held in.
        """
        start = time.perf_counter()
        validate.choice("invalid", invalid, ("raise", "skip"))
        rows = np.shape(points)[0] if np.ndim(points) == 2 else 1  # labels must match these
        if invalid == "skip":
            points, keep = validate.finite_rows("points", points)
            skipped = 0 if keep is None else int(keep.size - points.shape[0])
        else:
            points, keep, skipped = validate.vectors("points", points), None, 0
        if labels is not None:
            labels = validate.labels("labels", labels, (rows,))
            if keep is not None:
                labels = labels[keep]
        origin = validate.point("sensor_origin", sensor_origin, validate.reach(self.grid))
        if pose is not None:
            points = points @ pose[0].T + pose[1]
            origin = pose[0] @ origin + pose[1]
        if math.hypot(*origin.tolist()) < AT_CENTRE * self.grid.rho_max:
            origin = np.zeros(3)  # at the centre, as a trace from there is (AT_CENTRE)
        at_centre = not any(origin.tolist())  # every ray radial: the egocentric case
        if max_range is None:
            max_range = np.inf
        else:
            max_range = validate.finite("max_range", max_range)
            if not max_range > 0:
                raise ValueError(f"max_range must be a positive number, got {max_range!r}")
        # Each ray's hit (8 bytes) and, off the centre, its set-up in the kernels
        # (16 more; measured: 39 and 118 MB for 5,000,000 points).
        validate.fits("points", points.shape[0] * (8 if at_centre else 24),
                      f"integrating {points.shape[0]:,} points")
        log_odds = self._log_odds if self._cuda is not None else self._checked()
        log_odds = log_odds.reshape(log_odds.size)
        self._drop_view()
        self._last_scan = ScanStats(points.shape[0], skipped)
        grid = self.grid
        n_cells = math.prod(grid.shape)
        threads = numba.get_num_threads()
        update = (_logit(self.p_hit), _logit(self.p_miss), _logit(self.p_min), _logit(self.p_max))
        if self._cuda is not None:
            hits = self._cuda.integrate(grid, log_odds, points, origin, max_range, update,
                                        labels is not None)
        elif at_centre:  # hits are map indices
            hits = np.empty(points.shape[0], dtype=np.int64)
            with _zeroed_scratch("extents", (grid.n_theta * grid.n_phi,),
                                 np.int64) as free_extent, \
                    _zeroed_scratch("hit_mask", (n_cells,), np.uint8) as hit_mask:
                start = lap("prepare", start)
                _radial.mark_radial(points, max_range, grid.kernel_args(), free_extent, hits,
                                    threads)
                start = lap("mark", start)
                _radial.apply_radial(log_odds, free_extent, hits, hit_mask,
                                     grid.n_theta, grid.n_phi, *update, threads)
                lap("apply", start)
        else:
            # Each ray's direction, length and hit are set up in the kernels, in
            # parallel. Hits are column-major (see apply_scan).
            hits = np.empty(points.shape[0], dtype=np.int64)
            with _zeroed_scratch("flags", (-(-n_cells // 8),), np.uint64) as words:
                free = words.view(np.uint8)  # the same memory, a byte per cell
                view = np.empty(grid.n_theta * grid.n_phi, dtype=np.uint8)
                start = lap("prepare", start)
                _mark_off_centre(grid, origin, points, max_range, free, hits, words, view,
                                 threads)
                start = lap("mark", start)
                _update.apply_scan(log_odds, free, words, hits, grid.n_rho,
                                   view, *update, threads)
                lap("apply", start)
        if points.shape[0] and isinstance(hits, np.ndarray) and hits.max() < 0:
            _warn_nothing_inside(grid, points)
        if labels is not None:  # the walk's hits are column-major (see apply_scan)
            self._vote(hits, labels, 0 if at_centre else grid.n_rho)
        return self

    @property
    def labels(self):
        """The object of each cell, int32, shape ``grid.shape``; 0 is none (on the host).

        Voted in by :meth:`integrate` and :meth:`integrate_depth` with
        ``labels``, or found by :func:`label_objects`. Assigning checks the
        shape and that the values are integers >= 0. After a :meth:`move`,
        reading or assigning it resamples the map into the robot's frame
        first (:meth:`recentre`).
        """
        with self._lock:
            self.recentre()
            return self._labels

    @labels.setter
    def labels(self, value):
        labels = validate.labels("labels", value, self.grid.shape)
        with self._lock:
            self.recentre()
            self._labels = labels.astype(np.int32)

    def _vote(self, hits, labels, n_rho):
        """Give each cell hit in this scan the label most of its hits carry (ties: the smaller).

        ``hits`` as ``kernels.objects.hit_runs`` takes them (column-major when
        ``n_rho`` > 0). Consecutive rays' equal votes are counted as one run
        first (a 640 x 480 frame's votes become a few tens of thousands of
        runs), then the runs are sorted by cell and label and each cell's
        winner found in numpy. ``python -m bench.replay`` A/Bs it against
        sorting every ray's vote, on a replay with a label topic.
        """
        n_cells = math.prod(self.grid.shape)
        cells = np.empty(hits.shape[0], dtype=np.int64)
        votes = np.empty(hits.shape[0], dtype=np.int64)
        counts = np.empty(hits.shape[0], dtype=np.int64)
        runs = _objects.hit_runs(hits, labels, n_rho, n_cells // self.grid.n_rho, cells, votes,
                                 counts)
        if runs == 0:
            return
        cells, votes, counts = cells[:runs], votes[:runs], counts[:runs]
        span = int(votes.max()) + 1
        if n_cells <= SORT_KEY_MAX // span:  # one key: three times faster
            order = np.argsort(cells * span + votes)
        else:
            order = np.lexsort((votes, cells))
        cells, votes, counts = cells[order], votes[order], counts[order]
        # Each (cell, label) pair's votes, then each cell's most, the first
        # (smallest) label among those with that many.
        pair = np.flatnonzero(np.r_[True, (cells[1:] != cells[:-1])
                                    | (votes[1:] != votes[:-1])])
        cells, votes, counts = cells[pair], votes[pair], np.add.reduceat(counts, pair)
        starts = np.flatnonzero(np.r_[True, cells[1:] != cells[:-1]])
        most = np.maximum.reduceat(counts, starts)
        best = np.flatnonzero(counts == np.repeat(most, np.diff(np.r_[starts, cells.shape[0]])))
        winners = best[np.r_[True, cells[best][1:] != cells[best][:-1]]]
        self._labels.reshape(-1)[cells[winners]] = votes[winners]

    @property
    def last_scan(self):
        """What the last :meth:`integrate` or :meth:`integrate_depth` put in (:class:`ScanStats`).

        ``None`` before the first.
        """
        return self._last_scan

    @interrupts_after
    @one_at_a_time
    def integrate_depth(self, depth, intrinsics, pose=None, max_range=None, depth_scale=1.0,
                        labels=None):
        """Integrate one depth image from a camera at ``pose``.

        The image is back-projected by :func:`~logsph_trace.depth_to_points`
        and integrated as :meth:`integrate` does, from the camera's centre.

        Parameters
        ----------
        depth : array_like, shape (rows, columns)
            Z along the optical axis per pixel (any numeric dtype, times
            ``depth_scale``); 0, NaN, infinite and negative pixels have no
            depth: they are skipped and counted in :attr:`last_scan`.
        intrinsics : array_like
            A 3 x 3 camera matrix (OpenCV's) or ``(fx, fy, cx, cy)``, pixels.
        pose : None, array_like (4, 4), or (R, t)
            Camera (OpenCV frame: x right, y down, z forward) to map (the
            robot's frame, after a :meth:`move`).
            ``None``: the camera at the map's origin looking along +z with
            image-up along +y, so OpenCV's (x, y, z) is the map's (-x, -y, z).
            ``docs/how-to/frames.md`` draws it.
        max_range : float, optional
            As for :meth:`integrate`: farther returns clear free space up to
            ``max_range`` and mark no hit.
        depth_scale : float
            The map's length unit per depth unit (0.001 for millimetres).
        labels : array_like of int, shape (rows, columns), optional
            An instance image aligned with ``depth`` (0 = no object), e.g.
            from a 2-D detector or segmenter; voted into the cells the hits
            land in, as :meth:`integrate` does.

        Returns
        -------
        self
        """
        if self._pose is not None:  # the camera in the frame the map is held in
            pose = compose(self._pose, pose_of(pose))
        scan = depth_to_points(depth, intrinsics, pose, depth_scale)
        if labels is not None:
            labels = validate.labels("labels", labels, np.shape(depth))
            labels = labels[scan.pixels[:, 0], scan.pixels[:, 1]]
        self._integrate(scan.points, scan.origin, max_range, "skip", labels, None)
        self._last_scan = ScanStats(self._last_scan.rays, self._last_scan.invalid + scan.invalid)
        return self

    @one_at_a_time
    def decay(self, factor):
        """Fade the map towards unknown: ``log_odds *= factor`` (a short-term memory).

        ``factor`` in [0, 1]: 1 keeps everything, 0 forgets everything.
        """
        factor = validate.number("factor", factor, "in [0, 1]")
        if not 0.0 <= factor <= 1.0:
            raise ValueError(f"factor must be in [0, 1], got {factor!r}")
        if self._cuda is None:
            log_odds = self._checked()
            np.multiply(log_odds, np.float32(factor), out=log_odds)
            self._drop_view()
        else:
            self._cuda.decay(self._held_flat(), np.float32(factor))
        return self

    @one_at_a_time
    def save(self, path):
        """Write the map and its grid to a ``.npz`` file; return the path written.

        As :func:`numpy.savez`, ``.npz`` is added to a name without it. The
        write is atomic: if it fails or is interrupted, an existing file of
        that name is left as it was and no partial file remains. A GPU map
        is copied to the host first. A map the robot has moved in since it
        was last centred is saved as it is held, with the robot's pose in
        it, so that loading it and moving on resamples no more than
        before.
        """
        grid = self.grid
        path = npz_path(path)
        pose = np.eye(4)
        if self._pose is not None:
            pose[:3, :3], pose[:3, 3] = self._pose
        log_odds = self._checked(write=False) if self._cuda is None else self._host_log_odds()
        with atomic_write(path) as stream:
            write_npz(
                stream, compress=True, log_odds=log_odds, labels=self._labels, pose=pose,
                rho_edges=grid.rho_edges,
                theta_edges=grid.theta_edges, phi_edges=grid.phi_edges,
                spacing=np.array(grid.spacing),
                probabilities=np.array([self.p_hit, self.p_miss, self.p_min, self.p_max]),
            )
        return path

    @classmethod
    def load(cls, path, device="cpu"):
        """Read a map written by :meth:`save`, onto ``device`` ("cpu" or "cuda").

        The grid is rebuilt through :meth:`Grid.from_edges`, so a file is
        checked like new input.

        Raises
        ------
        FileNotFoundError, PermissionError, IsADirectoryError
            As ``open`` does.
        ValueError
            The file is not a valid map (corrupt, truncated, missing or bad
            arrays); the message names the file.
        """
        path = Path(path)
        validate.device(device)
        try:
            _check_headers(path)
            with np.load(path, allow_pickle=False) as data:
                missing = _SAVED_ARRAYS.difference(data.files)
                if missing:
                    raise ValueError(f"missing arrays {sorted(missing)}")
                grid = Grid.from_edges(data["rho_edges"], data["theta_edges"],
                                       data["phi_edges"], spacing=str(data["spacing"]))
                probabilities = np.asarray(data["probabilities"], dtype=np.float64)
                if probabilities.shape != (4,):
                    raise ValueError(f"probabilities must hold 4 numbers, got {probabilities}")
                log_odds = data["log_odds"]
                labels = data["labels"] if "labels" in data.files else None  # older files
                pose = rigid_motion(data["pose"], "pose") if "pose" in data.files else None
        except (FileNotFoundError, PermissionError, IsADirectoryError):
            raise
        except (ValueError, TypeError, KeyError, IndexError, EOFError, OSError, OverflowError,
                zipfile.BadZipFile) as error:
            raise ValueError(f"{path} is not a valid OccupancyGrid file: {error}") from None
        try:
            occupancy = cls(grid, *probabilities.tolist(), log_odds=log_odds, device=device)
            if labels is not None:
                occupancy.labels = labels
            if pose is not None and (not np.array_equal(pose[0], np.eye(3)) or np.any(pose[1])):
                if device == "cuda":
                    raise ValueError("the map was saved after a move, which a GPU map cannot "
                                     "hold; load it on the CPU")
                occupancy._pose = pose
            return occupancy
        except ValueError as error:
            raise ValueError(f"{path} is not a valid OccupancyGrid file: {error}") from None


def _array_headers(path):
    """Return {name: (shape, dtype)} of the arrays of a ``.npz`` file, from their headers.

    Only the first bytes of each array are decompressed, so a small file
    that declares a huge array costs nothing to read.
    """
    headers = {}
    with zipfile.ZipFile(path) as archive:
        for member in archive.namelist():
            if not member.endswith(".npy"):
                continue
            with archive.open(member) as stream:
                version = np.lib.format.read_magic(stream)
                read = (np.lib.format.read_array_header_1_0 if version == (1, 0)
                        else np.lib.format.read_array_header_2_0)
                shape, _, dtype = read(stream)
            headers[member[:-4]] = (tuple(int(n) for n in shape), dtype)
    return headers


def _check_headers(path):
    """Refuse a map file whose arrays do not fit its grid, before reading any of them.

    The edges give the grid's shape; ``log_odds`` and ``labels`` must have
    that shape, the edges must be 1-D, and all of it must fit in memory.
    """
    headers = _array_headers(path)
    missing = _SAVED_ARRAYS.difference(headers)
    if missing:
        raise ValueError(f"missing arrays {sorted(missing)}")
    shape = []
    for name in ("rho_edges", "theta_edges", "phi_edges"):
        edges, dtype = headers[name]
        if len(edges) != 1 or edges[0] < 2 or dtype.kind not in "iuf":
            raise ValueError(f"{name} must be 1-D with at least 2 numbers, got shape {edges} "
                             f"of {dtype}")
        shape.append(edges[0] - 1)
    if "pose" in headers and headers["pose"][0] != (4, 4):
        raise ValueError(f"pose must have shape (4, 4), got {headers['pose'][0]}")
    for name, kinds in (("log_odds", "iuf"), ("labels", "iub")):
        if name not in headers:
            continue
        declared, dtype = headers[name]
        if declared != tuple(shape) or dtype.kind not in kinds:
            raise ValueError(f"{name} must have the grid's shape {tuple(shape)}, got "
                             f"{declared} of {dtype}")
    total = sum(math.prod(declared) * dtype.itemsize for declared, dtype in headers.values())
    validate.fits("path", total, f"reading {path}")


# What OccupancyGrid.save must have written; it also writes "labels" (older files
# lack them: no objects), and older files hold "kinds", which load ignores.
_SAVED_ARRAYS = frozenset(
    ("log_odds", "rho_edges", "theta_edges", "phi_edges", "spacing", "probabilities")
)


def _check_occupancy(occupancy):
    if not isinstance(occupancy, OccupancyGrid):
        raise ValueError(f"occupancy must be an OccupancyGrid, got {type(occupancy).__name__}")
