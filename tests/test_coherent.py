"""The coherent scan: from a sensor in the egocentric gap, most rays are walked
from a sphere near their end, once samples have flagged the cells below it and
the rays that could add a cell there are found (``occupancy._mark_off_centre``).
The flags must be exactly those of walking every ray.
"""

import numba
import numpy as np
import pytest
from singular import OFFSETS, aim, unit_at
from test_occupancy import _reference_log_odds

import logsph_trace as lt
from logsph_trace import occupancy as occ
from logsph_trace.kernels import coherent, update


def _camera_scan(rng, sensor, forward, up=(0.0, 1.0, 0.0), shape=(120, 160), focal=180.0,
                 depth=(1.0, 4.0)):
    """End points of a pinhole camera at ``sensor``: a smooth random depth image
    with blocks of missing pixels, and a few rays ending near the sensor."""
    forward = np.asarray(forward, dtype=np.float64) / np.linalg.norm(forward)
    right = np.cross(up, forward)
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    rows, cols = np.mgrid[0:shape[0], 0:shape[1]]
    u = (cols - shape[1] / 2 + rng.uniform(-0.5, 0.5)) / focal
    v = (rows - shape[0] / 2 + rng.uniform(-0.5, 0.5)) / focal
    directions = forward + u[..., None] * right + v[..., None] * down
    directions /= np.linalg.norm(directions, axis=-1, keepdims=True)
    low, high = depth
    waves = np.sin(cols / rng.uniform(7, 19)) * np.cos(rows / rng.uniform(5, 13))
    distance = low + (high - low) * (0.5 + 0.5 * waves) * rng.uniform(0.8, 1.0, shape)
    keep = np.ones(shape, dtype=bool)
    for _ in range(6):  # holes: pixels without depth
        r, c = rng.integers(0, shape[0]), rng.integers(0, shape[1])
        keep[r:r + rng.integers(3, 30), c:c + rng.integers(3, 30)] = False
    near = rng.random(shape) < 0.01  # some rays end near the sensor, some in the gap
    distance[near] = rng.uniform(0.01, 1.0, np.count_nonzero(near))
    points = sensor + distance[..., None] * directions
    return points[keep]


SCANS = [  # (grid, sensor, the camera's forward direction, its focal length in pixels)
    (lt.Grid(0.3, 8.0, 64, 360, 180), (0.06, 0.08, 0.0), (0.0, 0.0, 1.0), 180.0),
    # looking up at the +y axis: rays cross the polar row's columns
    (lt.Grid(0.3, 8.0, 64, 360, 180), (0.05, -0.1, 0.12), (0.1, 1.0, 0.05), 180.0),
    # across the theta seam (-z) and with coarse cells
    (lt.Grid(0.5, 6.0, 16, 36, 18), (0.2, -0.1, 0.15), (0.05, -0.2, -1.0), 180.0),
    (lt.Grid(0.4, 5.0, 40, 180, 90, spacing="uniform"), (-0.1, 0.1, 0.1), (-1.0, 0.3, 0.2),
     180.0),
    # uneven edges: the narrowest cell sets the bins, so a long focal length
    (lt.Grid.from_edges(np.geomspace(0.25, 6.0, 30),
                        np.sort(np.r_[-np.pi, np.pi, np.random.default_rng(5).uniform(-3, 3, 70)]),
                        np.sort(np.r_[-np.pi / 2, np.pi / 2,
                                      np.random.default_rng(6).uniform(-1.5, 1.5, 40)])),
     (0.1, 0.0, -0.05), (0.3, -0.4, 1.0), 900.0),
    # on the y axis: every ray keeps its direction's azimuth, a face's to the bit
    # for those ending on a theta face
    (lt.Grid(0.3, 8.0, 64, 360, 180), (0.0, 0.12, 0.0), (0.3, 0.2, 1.0), 180.0),
]


@pytest.fixture
def coherent_from_1000_rays(monkeypatch):
    monkeypatch.setattr(occ, "COHERENT_MIN_RAYS", 1000)


def _flags(grid, sensor, points, max_range=np.inf, workers=None):
    """Run ``_mark_off_centre`` (one worker per thread by default); return its
    flags, hits, and its counts of rays let start beyond the gap, ending below
    that and staying in a column."""
    n_cells = int(np.prod(grid.shape))
    words = np.zeros(-(-n_cells // 8), dtype=np.uint64)
    free = words.view(np.uint8)
    hits = np.empty(points.shape[0], dtype=np.int64)
    view = np.empty(grid.n_theta * grid.n_phi, dtype=np.uint8)
    counts = occ._mark_off_centre(grid, np.asarray(sensor, dtype=np.float64), points,
                                  max_range, free, hits, words, view,
                                  workers or numba.get_num_threads())
    return free[:n_cells] != 0, hits, *counts


@pytest.mark.parametrize("grid, sensor, forward, focal", SCANS)
def test_coherent_scan_equals_walking_every_ray(grid, sensor, forward, focal,
                                                coherent_from_1000_rays):
    rng = np.random.default_rng(41)
    points = _camera_scan(rng, np.asarray(sensor), forward, focal=focal)
    for max_range in (None, 2.5):
        got = lt.OccupancyGrid(grid).integrate(points, sensor, max_range=max_range)
        np.testing.assert_array_equal(got.log_odds,
                                      _reference_log_odds(grid, points, sensor, max_range))
    # The scan took the shortcut for most rays, the same way on any thread
    # count: all workers flag one shared array, 1 to 7 of them on 1 thread
    # and on all.
    flags, hits, skipped, ended, straight = _flags(grid, sensor, points)
    assert skipped > 0.25 * points.shape[0]
    assert ended > 0.02 * points.shape[0]  # and some were not walked at all
    assert straight > 0.02 * points.shape[0]
    threads = numba.get_num_threads()
    for using in (1, threads):
        numba.set_num_threads(using)
        try:
            for workers in (1, 2, 7):
                other = _flags(grid, sensor, points, workers=workers)
                np.testing.assert_array_equal(other[0], flags)
                np.testing.assert_array_equal(other[1], hits)
                assert other[2:] == (skipped, ended, straight)
        finally:
            numba.set_num_threads(threads)


@pytest.mark.parametrize("kind", ["centre", "y_axis", "corner"])
def test_near_singular_rays_in_a_coherent_scan(kind, coherent_from_1000_rays):
    grid, sensor, forward, _ = SCANS[0]
    rng = np.random.default_rng(43)
    sensor = np.asarray(sensor)
    # Rays at (and 1e-15 ... 1e-3 x rho_max beside) the set, ending before it,
    # on it and beyond it, among a camera's rays passing by.
    camera = _camera_scan(rng, sensor, forward)
    targets = np.array([aim(rng, grid, kind, offset, sensor) for offset in OFFSETS
                        for _ in range(60)])
    aimed = sensor + rng.uniform(0.3, 2.5, (len(targets), 1)) * (targets - sensor)
    points = np.concatenate([camera, aimed])
    got = lt.OccupancyGrid(grid).integrate(points, sensor)
    np.testing.assert_array_equal(got.log_odds, _reference_log_odds(grid, points, sensor))
    assert _flags(grid, sensor, points)[2] > 0


@pytest.mark.parametrize("scan", [0, 2, 3])
def test_lines_along_faces_in_a_coherent_scan(scan, coherent_from_1000_rays):
    """The sensor at a power of two times a unit vector on an edge's cone and
    half-plane, and rays among a camera's along its own line through the
    centre and across the y axis in its own vertical plane: lines that lie on
    a cone or in a plane of the grid (``test_singular``'s face rays). Walked
    from a sphere near their end, the rays' start points lie on those faces
    too, and the walk must plan them from the sensor, as the trace does."""
    grid, _, forward, _ = SCANS[scan]
    rng = np.random.default_rng(53)
    phi = grid.phi_edges[rng.integers(1, grid.phi_edges.size - 1)]
    theta = grid.theta_edges[rng.integers(0, grid.theta_edges.size)]
    unit = unit_at(phi, theta)
    sensor = 2.0 ** np.floor(np.log2(grid.rho_min / 2)) * unit
    reach = rng.uniform(0.2, 1.3, (2000, 1)) * grid.rho_max
    along = unit * rng.choice([-1.0, 1.0], (1000, 1))
    across = np.tile([-sensor[0], 0.0, -sensor[2]], (1000, 1))
    across[:, 1] = rng.normal(size=1000) * np.linalg.norm(sensor)
    across /= np.linalg.norm(across, axis=1, keepdims=True)
    points = np.concatenate([_camera_scan(rng, sensor, forward),
                             sensor + reach * np.concatenate([along, across])])
    got = lt.OccupancyGrid(grid).integrate(points, sensor)
    np.testing.assert_array_equal(got.log_odds, _reference_log_odds(grid, points, sensor))
    assert _flags(grid, sensor, points)[2] > 0


def _ending_at_faces(rng, grid, camera, face, offsets):
    """The end points of 1,500 of ``camera``'s rays moved onto the nearest edge
    of ``face`` (rho, theta or phi) and then by one of ``offsets`` (times rho_max
    for rho, radians for the angles), so a ray ends on the face or beside it."""
    picked = camera[rng.choice(camera.shape[0], 1500, replace=False)]
    rho = np.linalg.norm(picked, axis=1)
    theta = np.arctan2(picked[:, 0], picked[:, 2])
    phi = np.arcsin(picked[:, 1] / rho)
    edges = {"rho": grid.rho_edges, "theta": grid.theta_edges, "phi": grid.phi_edges}[face]
    values = {"rho": rho, "theta": theta, "phi": phi}[face]
    nearest = edges[np.clip(np.searchsorted(edges, values), 1, edges.size - 2)]
    scale = grid.rho_max if face == "rho" else 1.0
    values[:] = nearest + rng.choice(offsets, picked.shape[0]) * scale
    flat = rho * np.cos(phi)
    return np.stack([flat * np.sin(theta), rho * np.sin(phi), flat * np.cos(theta)], axis=1)


def _check_ends(face, offsets, scan=0):
    grid, sensor, forward, focal = SCANS[scan]
    rng = np.random.default_rng(47)
    sensor = np.asarray(sensor)
    camera = _camera_scan(rng, sensor, forward, focal=focal)
    points = np.concatenate([camera, _ending_at_faces(rng, grid, camera, face, offsets)])
    for max_range in (None, 2.5):
        got = lt.OccupancyGrid(grid).integrate(points, sensor, max_range=max_range)
        np.testing.assert_array_equal(got.log_odds,
                                      _reference_log_odds(grid, points, sensor, max_range))
    counts = _flags(grid, sensor, points)[3:]
    return counts[0] > 0.1 * points.shape[0] and counts[1] > 0.02 * points.shape[0]


@pytest.mark.parametrize("face", ["rho", "theta", "phi"])
def test_rays_ending_beside_a_cell_face(face, coherent_from_1000_rays):
    # A ray that ends below its limit is not walked when its end point is
    # clear of its cell's faces: end points 1e-15 ... 1e-3 beside a face, on
    # either side, must come out as the walk has them.
    beside = np.array(OFFSETS[1:])
    assert _check_ends(face, np.r_[beside, -beside])  # rays were left unwalked


@pytest.mark.parametrize("scan", range(len(SCANS)))
@pytest.mark.parametrize("face", ["rho", "theta", "phi"])
@pytest.mark.parametrize("coherent", [True, False], ids=["coherent", "walk"])
def test_rays_ending_on_a_cell_face(face, scan, coherent, monkeypatch):
    # The walk times every crossing on the trace's clock, from the sensor, not
    # from where it starts (the gap's exit, or a sphere beyond it): a ray
    # ending on a face to the last bit then ends, hit or not, where the trace
    # ends it. Timed from the gap's exit, crossings differed by an ulp, enough
    # to decide whether the end cell was a hit: 13 of the first 30 cases
    # failed, by 1-145 cells. From the y axis, a ray ending on a theta face
    # lies in it: the trace once took it to sweep to the face and never
    # reach it (see test_singular), and the walk to start on it.
    monkeypatch.setattr(occ, "COHERENT_MIN_RAYS", 1000 if coherent else 10**9)
    unwalked = _check_ends(face, np.array([0.0]), scan)
    if scan == 0 or not coherent:  # the first scan leaves rays unwalked, the plain walk none
        assert unwalked == coherent


def test_the_real_frame_off_the_centre_equals_walking_every_ray(monkeypatch):
    pytest.importorskip("skimage")
    from logsph_trace import datasets
    from logsph_trace.sensor import DEFAULT_ROTATION

    frame = datasets.motorcycle()
    grid = lt.Grid(0.3, 8.0, 64, 360, 180)
    sensor = np.array([0.06, 0.08, 0.0])
    points = lt.depth_to_points(frame.depth, frame.intrinsics, (DEFAULT_ROTATION, sensor)).points
    coherent = lt.OccupancyGrid(grid).integrate(points, sensor).log_odds
    monkeypatch.setattr(occ, "COHERENT_MIN_RAYS", points.shape[0] + 1)
    plain = lt.OccupancyGrid(grid).integrate(points, sensor).log_odds
    np.testing.assert_array_equal(coherent, plain)
    assert _flags(grid, sensor, points)[2:] == (0, 0, 0)  # the plain walk
    monkeypatch.setattr(occ, "COHERENT_MIN_RAYS", 1000)
    assert _flags(grid, sensor, points)[2] > 0.8 * points.shape[0]


@pytest.mark.parametrize("scan", [0, 2, 5])
def test_points_at_the_sensor_are_no_rays_in_a_coherent_scan(scan, coherent_from_1000_rays):
    # A point at the sensor is no ray: its hit is -1, whatever the hits array
    # held before (it once kept that, and the map update wrote there).
    grid, sensor, forward, focal = SCANS[scan]
    rng = np.random.default_rng(47)
    sensor = np.asarray(sensor)
    points = _camera_scan(rng, sensor, forward, focal=focal)
    at_sensor = rng.random(points.shape[0]) < 0.05
    at_sensor[:3] = True  # the first ray of the scan, and so of its bin
    points[at_sensor] = sensor
    got = lt.OccupancyGrid(grid).integrate(points, sensor)
    np.testing.assert_array_equal(got.log_odds, _reference_log_odds(grid, points, sensor))
    n_cells = int(np.prod(grid.shape))
    words = np.zeros(-(-n_cells // 8), dtype=np.uint64)
    hits = np.full(points.shape[0], 2 * n_cells, dtype=np.int64)
    view = np.empty(grid.n_theta * grid.n_phi, dtype=np.uint8)
    skipped = occ._mark_off_centre(grid, sensor, points, np.inf, words.view(np.uint8), hits,
                                   words, view, numba.get_num_threads())[0]
    assert skipped > 0  # the coherent scan
    assert np.all(hits[at_sensor] == -1)
    assert np.all(hits < n_cells)


def _inside(rng, grid, i, j, k, n):
    """``n`` points of cell (i, j, k): random, its corners and its edges' middles."""
    rho = np.r_[rng.uniform(grid.rho_edges[i], grid.rho_edges[i + 1], n),
                np.repeat(grid.rho_edges[i:i + 2], 9)]
    theta_pick = np.r_[0.0, 0.5, 1.0]
    theta = np.r_[rng.uniform(grid.theta_edges[j], grid.theta_edges[j + 1], n),
                  np.tile(np.repeat(grid.theta_edges[j] + theta_pick * (grid.theta_edges[j + 1]
                                                                        - grid.theta_edges[j]),
                                    3), 2)]
    phi = np.r_[rng.uniform(grid.phi_edges[k], grid.phi_edges[k + 1], n),
                np.tile(grid.phi_edges[k] + theta_pick * (grid.phi_edges[k + 1]
                                                          - grid.phi_edges[k]), 6)]
    return np.stack([rho * np.cos(phi) * np.sin(theta), rho * np.sin(phi),
                     rho * np.cos(phi) * np.cos(theta)], axis=1)


@pytest.mark.parametrize("grid, sensor", [scan[:2] for scan in SCANS])
def test_a_cells_shadow_holds_every_direction_meeting_it(grid, sensor):
    # The proof's geometric step: the bins a cell lowers to its shell hold
    # every direction from the sensor to a point of it.
    rng = np.random.default_rng(47)
    origin = np.asarray(sensor, dtype=np.float64)
    args = grid.kernel_args()
    q = occ._coherent_plan(grid, origin, 10**9)
    corners = np.empty((3, coherent.MAX_CORNERS))
    everywhere = np.array([0.0, 0.0, 1.0, np.pi])
    polar = [(rng.integers(0, 4), rng.integers(0, grid.n_theta), k) for k in (0, grid.n_phi - 1)]
    cells = [(rng.integers(0, min(grid.n_rho, 64)), rng.integers(0, grid.n_theta),
              rng.integers(0, grid.n_phi)) for _ in range(60)] + polar
    for i, j, k in cells:
        points = _inside(rng, grid, i, j, k, 300)
        bins = np.empty(points.shape[0], dtype=np.int64)
        boxes = np.empty((6, 4))
        coherent.bin_rays(origin, points, q, 1, bins, np.empty_like(bins), np.empty(6, np.int64),
                         boxes)
        directions = points - origin
        directions /= np.linalg.norm(directions, axis=1)[:, None]
        axis = directions.mean(axis=0) / np.linalg.norm(directions.mean(axis=0))
        tight = np.r_[axis, np.arccos(np.clip(directions @ axis, -1, 1)).max()]
        for rays in (everywhere, tight):
            limit = np.full(6 * q * q, 200, dtype=np.uint8)
            coherent._mark_shadow(*origin, args, i, j, k, q, rays, boxes, corners, limit)
            assert (limit[bins] == i).all(), (i, j, k)
        # Directions of the cone around another axis do not meet the cell: nothing lowered.
        limit = np.full(6 * q * q, 200, dtype=np.uint8)
        coherent._mark_shadow(*origin, args, i, j, k, q, np.r_[-axis, 0.1], boxes, corners,
                             limit)
        assert (limit == 200).all() or tight[3] > 1.0


@pytest.mark.parametrize("scan", [0, 1, 2])
def test_the_bins_limits_are_the_same_on_any_number_of_threads(scan, monkeypatch,
                                                              coherent_from_1000_rays):
    # All workers lower one shared limit per bin (an atomic minimum): 1 and 2
    # threads, 1 to 7 workers, the same limits as one worker alone.
    grid, sensor, forward, focal = SCANS[scan]
    points = _camera_scan(np.random.default_rng(71), np.asarray(sensor), forward, focal=focal)
    calls = []
    mark_candidates = coherent.mark_candidates

    def recording(*args):
        mark_candidates(*args)
        calls.append(tuple(a.copy() if isinstance(a, np.ndarray) else a for a in args))

    monkeypatch.setattr(occ._coherent, "mark_candidates", recording)
    _flags(grid, sensor, points)
    monkeypatch.undo()
    (origin, args, masks, skip, q, rays, view, boxes, limit, _), = calls
    want = limit.copy()
    assert 0 < np.count_nonzero(want < skip) < want.size
    limit[:] = 0  # every bin set again
    coherent.mark_candidates(origin, grid.kernel_args(), masks, skip, q, rays, view, boxes, limit,
                            1)
    np.testing.assert_array_equal(limit, want)
    for threads in (1, min(2, numba.config.NUMBA_NUM_THREADS)):
        numba.set_num_threads(threads)
        try:
            for workers in (1, 2, 7):
                limit[:] = 0
                coherent.mark_candidates(origin, grid.kernel_args(), masks, skip, q, rays, view,
                                        boxes, limit, workers)
                np.testing.assert_array_equal(limit, want)
        finally:
            numba.set_num_threads(numba.config.NUMBA_NUM_THREADS)


def _bin_cone(bins, q, workers=None):
    """``coherent.ray_cone`` of a list of cube-map bins (one worker per thread by default)."""
    first = np.ones(6 * q * q, dtype=np.int64)  # 1 row, in none of the bins
    first[bins] = 0  # but in these
    cone = np.empty(4)
    coherent.ray_cone(first, 1, q, workers or numba.get_num_threads(), cone)
    return cone


def _cube_uv(offsets):
    """Plain cube-map face and (u, v) of directions ``offsets`` (none zero): the
    face of the largest |component| (ties to the earlier axis; 1 more for the
    negative half), the two other components over it."""
    size = np.abs(offsets)
    axis = np.where((size[:, 0] >= size[:, 1]) & (size[:, 0] >= size[:, 2]), 0,
                    np.where(size[:, 1] >= size[:, 2], 1, 2))
    rows = np.arange(offsets.shape[0])
    major = offsets[rows, axis]
    others = np.array([[1, 2], [0, 2], [0, 1]])[axis]
    return (2 * axis + (major <= 0), offsets[rows, others[:, 0]] / np.abs(major),
            offsets[rows, others[:, 1]] / np.abs(major))


def _cube_bins(offsets, q):
    """``_cube_uv``'s u and v each cut into ``q`` bins."""
    face, u, v = _cube_uv(offsets)
    index = [np.clip(((w + 1.0) * 0.5 * q).astype(np.int64), 0, q - 1) for w in (u, v)]
    return (face * q + index[0]) * q + index[1]


def _cube_boxes(offsets):
    """Per face, the lowest and highest u, then v, of the non-zero ``offsets``."""
    face, u, v = _cube_uv(offsets[np.any(offsets != 0.0, axis=1)])
    boxes = np.tile([np.inf, -np.inf, np.inf, -np.inf], (6, 1))
    for f in np.unique(face):
        on = face == f
        boxes[f] = u[on].min(), u[on].max(), v[on].min(), v[on].max()
    return boxes


def test_rays_are_binned_by_their_cube_map_face_and_position():
    # Random directions, and ties of the largest components (the face of the
    # earlier axis), signed zeros, the axes and the cube's corners and edges.
    rng = np.random.default_rng(61)
    origin = np.zeros(3)  # the offsets as given: ties stay ties
    offsets = rng.normal(size=(3000, 3))
    ties = rng.choice([-1.0, 1.0], size=(600, 3)) * rng.uniform(0.1, 2.0, (600, 1))
    ties[:200, 2] *= rng.uniform(0.0, 1.0, 200)  # |x| = |y| > |z|
    ties[200:400, 0] *= rng.uniform(0.0, 1.0, 200)  # |y| = |z| > |x|
    axes = np.vstack([np.eye(3), -np.eye(3), [[-0.0, 0.0, 2.0], [0.0, -0.0, -3.0]]])
    offsets = np.vstack([offsets, ties, axes])
    points = origin + offsets
    for q, coarse_q in ((306, 153), (7, 3), (1, 1)):
        bins, coarse = (np.empty(points.shape[0], dtype=np.int64) for _ in range(2))
        boxes = np.empty((6, 4))
        coherent.bin_rays(origin, points, q, coarse_q, bins, coarse,
                         np.empty(6 * coarse_q * coarse_q, dtype=np.int64), boxes)
        np.testing.assert_array_equal(bins, _cube_bins(offsets, q))
        np.testing.assert_array_equal(coarse, _cube_bins(offsets, coarse_q))
        np.testing.assert_array_equal(boxes, _cube_boxes(offsets))


def test_each_coarse_bins_first_ray_is_its_sample_on_any_number_of_threads():
    rng = np.random.default_rng(67)
    origin = np.array([0.06, 0.08, 0.0])
    points = _camera_scan(rng, origin, (1.0, 0.2, 0.4))
    points[rng.random(points.shape[0]) < 0.03] = origin  # no rays: in no bin
    for threads in (1, min(2, numba.config.NUMBA_NUM_THREADS)):
        numba.set_num_threads(threads)
        try:
            for q, coarse_q in ((306, 153), (8, 1)):
                bins, coarse = (np.empty(points.shape[0], dtype=np.int64) for _ in range(2))
                first = np.full(6 * coarse_q * coarse_q, -7, dtype=np.int64)
                boxes = np.empty((6, 4))
                coherent.bin_rays(origin, points, q, coarse_q, bins, coarse, first, boxes)
                np.testing.assert_array_equal(boxes, _cube_boxes(points - origin))
                want = np.full(first.shape[0], points.shape[0])
                ray = np.flatnonzero(coarse >= 0)
                np.minimum.at(want, coarse[ray], ray)
                np.testing.assert_array_equal(first, want)
                assert np.all((coarse == -1) == np.all(points == origin, axis=1))
                sample = np.array([coherent.is_sample(coarse, first, r)
                                   for r in range(points.shape[0])])
                assert np.count_nonzero(sample) == np.count_nonzero(want < points.shape[0])
        finally:
            numba.set_num_threads(numba.config.NUMBA_NUM_THREADS)


def test_the_ray_cone_holds_every_ray():
    rng = np.random.default_rng(53)
    origin = np.array([0.06, 0.08, 0.0])
    for forward in ((0, 0, 1), (1, 1, 1), (0, -1, 0.01)):
        points = _camera_scan(rng, origin, forward, up=(0.3, 0.1, 1.0) if forward[2] == 0
                              else (0.0, 1.0, 0.0))
        for q in (8, 101, 306):
            bins = np.empty(points.shape[0], dtype=np.int64)
            coherent.bin_rays(origin, points, q, 1, bins, np.empty_like(bins),
                             np.empty(6, np.int64), np.empty((6, 4)))
            cone = _bin_cone(np.unique(bins), q)
            directions = points - origin
            directions /= np.linalg.norm(directions, axis=1)[:, None]
            assert np.arccos(np.clip(directions @ cone[:3], -1, 1)).max() <= cone[3]


def test_the_scans_extent_is_the_box_of_every_strideth_ray():
    rng = np.random.default_rng(59)
    origin = np.array([0.06, 0.08, 0.0])
    points = _camera_scan(rng, origin, (1.0, 1.0, 1.0))  # rays on three faces
    points[::5] = origin  # no rays
    for stride in (1, 7, 64):
        boxes = np.empty((6, 4))
        coherent.ray_extent(origin, points, stride, boxes)
        np.testing.assert_array_equal(boxes, _cube_boxes(points[::stride] - origin))


def test_a_sample_stands_for_about_rays_per_sample_rays_and_a_coarse_bin_is_at_most_a_cell():
    # A 0.5 x 0.5 square of one face at 100 bins a side: 625 bins.
    extent = np.tile([np.inf, -np.inf, np.inf, -np.inf], (6, 1))
    extent[4] = -0.25, 0.25, 0.0, 0.5
    per_sample = occ.RAYS_PER_SAMPLE
    assert occ._coarsening(100, 625 * per_sample // 4, extent) == 2  # 2 x 2 bins a sample
    assert occ._coarsening(100, 625 * per_sample, extent) == 1
    assert occ._coarsening(100, 625 * per_sample * 100, extent) == 1
    # Sparse rays: as wide as the narrowest cell, no wider.
    assert occ._coarsening(100, 625, extent) == occ.BINS_PER_CELL
    # Rays in one direction (no area) or on several faces.
    extent[4] = 0.1, 0.1, 0.2, 0.2
    assert occ._coarsening(100, 10**6, extent) == 1
    extent[4] = -0.25, 0.25, 0.0, 0.5
    extent[0] = -0.25, 0.25, 0.0, 0.5
    assert occ._coarsening(100, 2 * 625 * per_sample // 4, extent) == 2


def test_the_ray_cone_is_the_same_on_any_number_of_threads():
    # Its axis is a sum over the bins, taken in fixed blocks: many blocks,
    # spread over every face, summed on 1 and 2 threads by 1 to 7 workers.
    rng = np.random.default_rng(59)
    q = 64
    bins = np.unique(rng.integers(0, 6 * q * q, 30 * coherent.CONE_BLOCK))
    cones = []
    for threads in (1, min(2, numba.config.NUMBA_NUM_THREADS)):
        numba.set_num_threads(threads)
        for workers in (1, 2, 7):
            cones.append(_bin_cone(bins, q, workers))
    numba.set_num_threads(numba.config.NUMBA_NUM_THREADS)
    for cone in cones[1:]:
        np.testing.assert_array_equal(cone, cones[0])
    centres = np.array([coherent._bin_corner(b, q, 0.5, 0.5) for b in bins[:50]])
    assert np.all(np.arccos(np.clip(centres @ cones[0][:3], -1, 1)) <= cones[0][3])


@pytest.mark.parametrize("q", [1, 2, 3, 4, 9])
def test_a_ray_cone_wider_than_a_half_space_is_the_sphere(q):
    # Every bin of the cube: the centres sum to zero, or to rounding noise in
    # a random direction. The corners' largest angle from that axis (2.97 rad
    # for q = 3) would leave out a cap round its opposite, inside one bin and
    # clear of its corners: beyond a half-space the corners no longer bound
    # the bins. Every direction must be held (and never NaN).
    cone = _bin_cone(np.arange(6 * q * q), q)
    assert np.all(np.isfinite(cone)) and cone[3] >= np.pi
    # More than a half-space but not all round: one face's worth short.
    assert _bin_cone(np.arange(q * q, 6 * q * q), q)[3] >= np.pi
    # Within a half-space the cone stays tight.
    assert _bin_cone(np.arange(q * q), q)[3] < np.pi / 2


@pytest.mark.parametrize("grid, sensor", [scan[:2] for scan in SCANS])
def test_a_column_with_a_ray_in_it_is_in_view(grid, sensor):
    # Points of random cells at rho >= rho_min: a cone around their
    # directions from the sensor leaves every one of their columns in view.
    rng = np.random.default_rng(61)
    origin = np.asarray(sensor, dtype=np.float64)
    for _ in range(20):
        i, j, k = (rng.integers(0, grid.n_rho), rng.integers(0, grid.n_theta),
                   rng.integers(0, grid.n_phi))
        points = _inside(rng, grid, i, j, k, 50)
        directions = points - origin
        directions /= np.linalg.norm(directions, axis=1)[:, None]
        axis = directions.mean(axis=0) / np.linalg.norm(directions.mean(axis=0))
        cone = np.r_[axis, np.arccos(np.clip(directions @ axis, -1, 1)).max()]
        view = np.empty(grid.n_theta * grid.n_phi, dtype=np.uint8)
        coherent.columns_in_view(origin, grid.kernel_args(), cone, view)
        assert view[j * grid.n_phi + k] == 1
        assert view.mean() < 1.0 or cone[3] > 1.0  # and it does pass some columns over


@pytest.mark.parametrize("n_rho, skip", [(5, 4), (8, 7), (13, 12), (13, 5), (64, 63), (150, 63),
                                         (150, 17)])
def test_near_masks_name_every_flagged_cell_below_skip(n_rho, skip):
    # Against a plain reading of the flags: columns that start anywhere in
    # a word, sparse and dense flags (free and hit), columns out of view, 1
    # to 3 workers.
    rng = np.random.default_rng(n_rho * 100 + skip)
    n_columns = 37
    n_cells = n_rho * n_columns
    for workers, density in ((1, 0.3), (2, 0.02), (3, 0.6)):
        words = np.zeros(-(-n_cells // 8), dtype=np.uint64)
        free = words.view(np.uint8)
        free[:n_cells] = (rng.random(n_cells) < density) * rng.integers(1, 3, n_cells)
        view = (rng.random(n_columns) < 0.8).astype(np.uint8)
        masks = np.empty(n_columns, dtype=np.uint64)
        coherent.near_masks(words, n_rho, skip, view, masks, workers)
        flagged = (free[:n_cells] != 0).reshape(n_columns, n_rho)[:, :skip]
        want = (flagged * (1 << np.arange(skip, dtype=np.uint64))).sum(axis=1, dtype=np.uint64)
        np.testing.assert_array_equal(masks, np.where(view != 0, want, 0).astype(np.uint64))


@pytest.mark.parametrize("n_rho", [3, 5, 8, 13, 64])
def test_apply_scan_updates_each_flagged_cell_in_view_once_and_clears_the_flags(n_rho):
    # Against a plain reading: words that span two or more columns (n_rho not
    # a multiple of 8), in and out of view, 1 to 3 workers, hits on flagged
    # and unflagged cells, several hits in one cell.
    rng = np.random.default_rng(n_rho)
    n_columns = 41
    n_cells = n_rho * n_columns
    log_hit, log_miss, log_min, log_max = 0.85, -0.4, -2.0, 3.5
    for workers, density in ((1, 0.3), (2, 0.05), (3, 0.6)):
        view = (rng.random(n_columns) < 0.6).astype(np.uint8)
        in_view = np.repeat(view != 0, n_rho)  # column-major: a column's cells in a row
        words = np.zeros(-(-n_cells // 8), dtype=np.uint64)
        free = words.view(np.uint8)
        free[:n_cells] = (rng.random(n_cells) < density) * in_view
        hits = np.where(rng.random(300) < 0.5, rng.choice(np.flatnonzero(in_view), 300), -1)
        start = rng.normal(0.0, 1.5, n_cells).astype(np.float32)
        # The map is row-major, (i, column); the flags column-major, (column, i).
        flagged = (free[:n_cells] != 0).reshape(n_columns, n_rho).T.ravel()
        hit = np.zeros(n_cells, dtype=bool)
        column, i = np.divmod(hits[hits >= 0], n_rho)
        hit[i * n_columns + column] = True
        # OctoMap's update, summed in float64 and rounded once: a hit wins.
        wide = start.astype(np.float64)
        want = wide.copy()
        want[flagged] = np.maximum(wide[flagged] + log_miss, log_min)
        want[hit] = np.minimum(wide[hit] + log_hit, log_max)
        want = want.astype(np.float32)
        got = start.copy()
        update.apply_scan(got, free, words, hits, n_rho, view, log_hit, log_miss, log_min,
                           log_max, workers)
        np.testing.assert_array_equal(got, want)
        assert not words.any()  # ready for the next scan
