"""The occupancy map, gaze targets and fixation probability."""

import numba
import numpy as np
import pytest
from oracle import first_occupied, reference_log_odds

import logsph_trace as lt
from logsph_trace._validate import row_norms
from logsph_trace.gaze import fixation_probability, gaze_targets
from logsph_trace.occupancy import OccupancyGrid

GRID = lt.Grid(0.3, 10.0, 32, 90, 45)


def _wall(z=4.0, n=120):
    xs, ys = np.meshgrid(np.linspace(-2, 2, n), np.linspace(-1, 2, n))
    return np.c_[xs.ravel(), ys.ravel(), np.full(xs.size, z)]


def test_integrate_recovers_surfaces_free_space_and_unknown():
    occupancy = OccupancyGrid(GRID)
    wall = _wall()
    occupancy.integrate(wall, [0.0, 0.0, 0.0])
    p = occupancy.probability
    hit = GRID.cell_of(wall)
    assert np.all(p[tuple(hit.T)] > 0.5)  # the surface is occupied
    in_front = GRID.cell_of(0.6 * wall)
    in_front = in_front[~np.any(np.all(in_front[:, None] == hit[None], axis=2), axis=1)]
    assert np.all(p[tuple(in_front.T)] < 0.5)  # the space the rays crossed is free
    behind = GRID.cell_of(1.5 * wall)
    assert np.all(occupancy.log_odds[tuple(behind.T)] == 0)  # never seen: unknown


def test_one_update_per_cell_per_scan_hit_wins_and_clamping():
    occupancy = OccupancyGrid(GRID)
    # Two rays: one ends in a cell the other crosses.
    points = np.array([[0.0, 0.0, 2.0], [0.0, 0.0, 4.0]])
    occupancy.integrate(points, [0.0, 0.0, 0.0])
    cell = tuple(GRID.cell_of(points[0]))
    assert occupancy.log_odds[cell] == pytest.approx(np.log(0.7 / 0.3), rel=1e-6)
    for _ in range(50):
        occupancy.integrate(points, [0.0, 0.0, 0.0])
    assert occupancy.probability[cell] == pytest.approx(0.971, rel=1e-5)
    free = tuple(GRID.cell_of([0.0, 0.0, 1.0]))
    assert occupancy.probability[free] == pytest.approx(0.1192, rel=1e-4)


def test_max_range_carves_without_marking():
    occupancy = OccupancyGrid(GRID)
    occupancy.integrate([[0.0, 0.0, 6.0]], [0.0, 0.0, 0.0], max_range=3.0)
    assert occupancy.log_odds[tuple(GRID.cell_of([0.0, 0.0, 6.0]))] == 0
    assert occupancy.log_odds[tuple(GRID.cell_of([0.0, 0.0, 2.0]))] < 0
    assert np.all(occupancy.log_odds <= 0)


@pytest.mark.parametrize("sensor", [[0.3, 1.2, -0.4], [0.0, 0.0, 0.0]])
def test_integrate_is_the_same_on_one_thread_and_many(sensor):
    # Every point three times, shuffled: rays of different threads end in
    # one cell, which must be updated once (the radial path's hit marks).
    wall = np.random.default_rng(7).permutation(np.repeat(_wall(3.0), 3, axis=0))
    before = numba.get_num_threads()
    try:
        numba.set_num_threads(1)
        one = OccupancyGrid(GRID).integrate(wall, sensor)
        numba.set_num_threads(before)
        many = OccupancyGrid(GRID).integrate(wall, sensor)
    finally:
        numba.set_num_threads(before)
    np.testing.assert_array_equal(one.log_odds, many.log_odds)
    np.testing.assert_array_equal(one.log_odds, _reference_log_odds(GRID, wall, sensor))


def test_decay_and_save_load(tmp_path):
    occupancy = OccupancyGrid(GRID).integrate(_wall(), [0.0, 0.0, 0.0])
    path = tmp_path / "map.npz"
    occupancy.save(path)
    loaded = OccupancyGrid.load(path)
    assert loaded.grid == GRID and loaded.grid.spacing == "log"
    np.testing.assert_array_equal(loaded.log_odds, occupancy.log_odds)
    before = occupancy.log_odds.copy()
    occupancy.decay(0.5)
    np.testing.assert_allclose(occupancy.log_odds, 0.5 * before)
    with pytest.raises(ValueError, match=r"factor must be in \[0, 1\]"):
        occupancy.decay(1.5)


def test_gaze_targets_in_order_of_distance():
    occupancy = OccupancyGrid(GRID)
    near, far = GRID.cell_of([0.0, 0.0, 2.0]), GRID.cell_of([0.0, 0.0, 5.0])
    occupancy.log_odds[tuple(near)] = 3.0
    occupancy.log_odds[tuple(far)] = 3.0
    targets = gaze_targets(occupancy, [0.05, 0.05, 0.5], [0.0, 0.0, 1.0])
    np.testing.assert_array_equal(targets.cells, [near, far])
    assert np.all(np.diff(targets.t_enter) > 0) and np.all(targets.values > 0.6)
    assert len(gaze_targets(occupancy, [0.05, 0.05, 0.5], [0.0, 0.0, 1.0], threshold=0.99)) == 0


def test_an_occluded_object_is_less_likely_looked_at_than_its_occluder():
    occupancy = OccupancyGrid(GRID)
    occluder, hidden = GRID.cell_of([0.0, 0.0, 2.0]), GRID.cell_of([0.0, 0.0, 5.0])
    occupancy.log_odds[tuple(occluder)] = 2.0
    occupancy.log_odds[tuple(hidden)] = 2.0
    for half_angle in (0.0, np.radians(2)):
        result = fixation_probability(occupancy, [0.05, 0.05, 0.5], [0.0, 0.0, 1.0],
                                      half_angle=half_angle, n_rays=50, dense=True)
        assert result[tuple(occluder)] > result[tuple(hidden)] > 0
        assert result.sum() <= 1.0 + 1e-12
    one_ray = fixation_probability(occupancy, [0.05, 0.05, 0.5], [0.0, 0.0, 1.0])
    p = 1 / (1 + np.exp(-2.0))
    assert one_ray.values[0] == pytest.approx(p)
    assert one_ray.values[1] == pytest.approx(p * (1 - p))


@pytest.mark.parametrize(
    "call, match",
    [
        (lambda o: o.integrate([[np.nan, 0, 1]], [0, 0, 0]), "points must be finite"),
        (lambda o: o.integrate(np.zeros((3, 2)), [0, 0, 0]), r"points must have shape \(m, 3\)"),
        (lambda o: o.integrate([[0, 0, 1]], [0, 0]), "sensor_origin must have shape"),
        (lambda o: o.integrate([[0, 0, 1]], [0, 0, 0], max_range=-1),
         "max_range must be a positive number"),
        (lambda o: OccupancyGrid(GRID, p_hit=0.4), r"p_hit must be in \(0.5, 1\)"),
        (lambda o: OccupancyGrid(GRID, p_miss=0.6), r"p_miss must be in \(0, 0.5\)"),
        (lambda o: OccupancyGrid(GRID, log_odds=np.zeros((2, 2, 2))), "log_odds has shape"),
        (lambda o: OccupancyGrid("grid"), "grid must be a logsph_trace.Grid"),
        (lambda o: gaze_targets(GRID, [0, 0, 0], [0, 0, 1]), "occupancy must be an OccupancyGrid"),
        (lambda o: fixation_probability(o, [0, 0, 0], [0, 0, 1], half_angle=2.0),
         r"half_angle must be in \[0, pi/2\)"),
        (lambda o: fixation_probability(o, [0, 0, 0], [0, 0, 1], unknown=2.0),
         "unknown must be a probability"),
    ],
)
def test_bad_occupancy_input(call, match):
    with pytest.raises(ValueError, match=match):
        call(OccupancyGrid(GRID))


def _reference_log_odds(grid, points, sensor, max_range=None):
    """One scan's log-odds, built in numpy (tests/oracle.py) from ``trace_many`` with t_max."""
    sensor = np.asarray(sensor, dtype=np.float64)
    offsets = points - sensor
    # The ray lengths integrate uses: np.linalg.norm can differ by an ulp,
    # which decides the end cell of a ray ending on a sphere.
    distances = row_norms(offsets)
    offsets, distances = offsets[distances > 0], distances[distances > 0]
    is_hit = np.ones(distances.shape[0], dtype=bool)
    if max_range is not None:
        is_hit = distances <= max_range
        distances = np.minimum(distances, max_range)
    traces = lt.trace_many(grid, np.broadcast_to(sensor, offsets.shape), offsets, t_max=distances)
    return reference_log_odds(grid.shape, traces.offsets, traces.cells, traces.t_exit, distances,
                              is_hit)


SCANS = [  # (grid, sensor): where the rays start decides the path and the cases met
    (GRID, [0.0, 0.0, 0.0]),  # radial fast path
    (GRID, [0.06, 0.08, 0.0]),  # in the gap, off the centre
    (GRID, [0.0, 0.12, 0.0]),  # on the y axis: every ray's theta is its direction's
    (GRID, [0.0, 0.0, 0.1]),  # on the theta = 0 half-plane
    (GRID, [1.3, -0.4, 2.2]),  # inside the region: inward then outward rays
    (GRID, [9.0, 6.0, -4.0]),  # beyond rho_max
    (lt.Grid(0.5, 6.0, 20, 24, 12, theta_range=(-1.0, 2.5), phi_range=(-0.6, 1.1),
             spacing="uniform"), [0.2, 0.1, -0.1]),  # partial ranges, uniform shells
    (lt.Grid(1.0, 30.0, 12, 36, 18, spacing="paper"), [1.5, 2.0, -0.5]),
    # over 64 shells: a column's flags span three 64-bit words
    (lt.Grid(0.2, 12.0, 150, 36, 18), [0.05, -0.1, 0.08]),
    (lt.Grid(0.2, 12.0, 150, 36, 18), [2.5, 0.7, -1.9]),
]


@pytest.mark.parametrize("grid, sensor", SCANS)
def test_integrate_equals_the_exact_trace(grid, sensor):
    rng = np.random.default_rng(61)
    points = rng.normal(size=(3000, 3)) * 4.0
    points[:40] *= 5.0  # some beyond rho_max, cut by max_range
    points[40:80] = np.asarray(sensor) + 0.01 * rng.normal(size=(40, 3))  # short rays
    points[80:100] = np.asarray(sensor) * rng.uniform(-2.0, 3.0, size=(20, 1))  # through the centre
    fast = OccupancyGrid(grid).integrate(points, sensor, max_range=12.0)
    np.testing.assert_array_equal(fast.log_odds,
                                  _reference_log_odds(grid, points, sensor, max_range=12.0))


@pytest.mark.parametrize("half_angle, unknown, free_below, min_distance",
                         [(0.0, 0.0, 0.5, 0.0), (np.radians(4), 0.0, 0.5, 0.0),
                          (np.radians(4), 0.3, 0.0, 0.0), (np.radians(6), 0.1, 0.5, 1.0)])
def test_fixation_probability_equals_the_numpy_reference(half_angle, unknown, free_below,
                                                         min_distance):
    rng = np.random.default_rng(71)
    occupancy = OccupancyGrid(GRID)
    occupancy.integrate(_wall(3.0, 60), [0.0, 0.0, 0.0])
    occupancy.log_odds[rng.random(GRID.shape) < 0.01] = 1.5  # scattered occupied cells
    origin, gaze = [0.2, 0.3, -0.4], [0.1, -0.05, 1.0]
    got = fixation_probability(occupancy, origin, gaze, half_angle=half_angle, n_rays=60,
                               unknown=unknown, free_below=free_below,
                               min_distance=min_distance, dense=True)
    cone = lt.trace_cone(GRID, origin, gaze, half_angle, n_rays=60) if half_angle else None
    directions = cone.directions if cone else np.array([gaze])
    weights = cone.ray_weights if cone else np.ones(1)
    traces = lt.trace_many(GRID, np.broadcast_to(origin, directions.shape), directions)
    want = first_occupied([(one.cells, one.t_exit) for one in traces], weights,
                          occupancy.log_odds, unknown, free_below, min_distance)
    assert set(map(tuple, np.argwhere(got > 0).tolist())) == {c for c, v in want.items() if v > 0}
    for cell, value in want.items():
        assert got[cell] == pytest.approx(value, rel=1e-12, abs=1e-15)


def test_load_restores_the_grid_through_its_constructor(tmp_path):
    for grid in (GRID, lt.Grid(1.0, 30.0, 12, 36, 18, spacing="paper"),
                 lt.Grid(0.5, 6.0, 20, 24, 12, theta_range=(-1.0, 2.5), spacing="uniform"),
                 lt.Grid.from_edges([0.5, 1.0, 3.0], [0.0, 0.4, 1.1], [-0.3, 0.2])):
        path = tmp_path / "map.npz"
        OccupancyGrid(grid).save(path)
        loaded = OccupancyGrid.load(path).grid
        assert loaded == grid and loaded.spacing == grid.spacing
        assert (loaded.rho_kind, loaded.theta_kind, loaded.phi_kind) == (
            grid.rho_kind, grid.theta_kind, grid.phi_kind)
    with pytest.raises(ValueError, match="not the edges of 'log' spacing"):
        lt.Grid.from_edges([0.5, 1.0, 3.0], [0.0, 1.0], [0.0, 1.0], spacing="log")


@pytest.mark.parametrize("sensor", [[0.0, 0.0, 0.0], [0.06, 0.08, 0.0], [1.3, -0.4, 2.2]])
@pytest.mark.parametrize("grid", [GRID, lt.Grid(0.2, 12.0, 150, 36, 18),
                                  lt.Grid(0.5, 6.0, 20, 24, 12, spacing="uniform")])
def test_end_points_on_and_beside_every_shell_edge(grid, sensor):
    # End points on a shell's sphere, and one ulp either side: the radial path
    # finds their shell by a closed-form guess corrected against the edges,
    # the column walk by comparing squared radii.
    rng = np.random.default_rng(83)
    edges = grid.rho_edges
    radii = np.concatenate([edges, np.nextafter(edges, 0.0), np.nextafter(edges, np.inf)])
    radii = np.repeat(radii, 8)
    directions = rng.normal(size=(radii.shape[0], 3))
    directions /= np.linalg.norm(directions, axis=1)[:, None]
    points = directions * radii[:, None]
    fast = OccupancyGrid(grid).integrate(points, sensor)
    np.testing.assert_array_equal(fast.log_odds, _reference_log_odds(grid, points, sensor))


def test_fixation_probability_counts_a_re_entered_cell_once():
    # A ray that leaves a cell and comes back (the dip at its closest approach,
    # or a cone cell's concave side): the second entry adds nothing and does
    # not dim the cells behind it again.
    rng = np.random.default_rng(97)
    origins = rng.uniform(-4.0, 4.0, size=(20000, 3))
    directions = rng.normal(size=(20000, 3))
    traces = lt.trace_many(GRID, origins, directions)
    re_entering = [r for r in range(20000)
                   if len(np.unique(traces[r].cells, axis=0)) < len(traces[r].cells)]
    assert len(re_entering) >= 5
    occupancy = OccupancyGrid(GRID)
    occupancy.log_odds[...] = rng.uniform(-2.0, 2.0, size=GRID.shape).astype(np.float32)
    for row in re_entering[:20]:
        ray = traces[row]
        got = fixation_probability(occupancy, origins[row], directions[row], free_below=0.3,
                                   min_distance=0.5, dense=True)
        want = first_occupied([(ray.cells, ray.t_exit)], np.ones(1), occupancy.log_odds,
                              free_below=0.3, min_distance=0.5)
        assert {c for c, v in want.items() if v > 0} == set(map(tuple, np.argwhere(got > 0)))
        for cell, value in want.items():
            assert got[cell] == pytest.approx(value, rel=1e-12, abs=1e-15)


@pytest.mark.parametrize("sensor", [[0.0, 0.0, 0.0], [0.06, 0.08, 0.0], [0.3, 1.2, -0.4]])
def test_a_scan_leaves_its_flags_zero_for_the_next(sensor):
    # The flags are reused by this thread's next scan: each scan must leave
    # them zero, and a second scan must come out as it would on fresh ones.
    from logsph_trace import occupancy as module

    def drop():
        for kind in ("flags", "extents", "hit_mask"):
            setattr(module._flags, kind, None)

    first, second = _wall(3.0), np.repeat(_wall(5.0, 90), 2, axis=0) * [1.0, -0.5, 1.0]
    drop()
    reused = OccupancyGrid(GRID).integrate(first, sensor)
    kept = [getattr(module._flags, kind) for kind in ("flags", "extents", "hit_mask")]
    assert any(a is not None for a in kept)
    assert not any(a.any() for a in kept if a is not None)
    reused.integrate(second, sensor)
    fresh = OccupancyGrid(GRID).integrate(first, sensor)
    drop()
    fresh.integrate(second, sensor)
    np.testing.assert_array_equal(reused.log_odds, fresh.log_odds)
