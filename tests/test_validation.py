"""Bad input is a ValueError naming the argument and the value, raised before any kernel runs."""

import numpy as np
import pytest

import logsph_trace as lt

PI = np.pi


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(rho_min=5.0, rho_max=5.0), "rho_min must be < rho_max"),
        (dict(rho_min=6.0, rho_max=5.0), "rho_min must be < rho_max"),
        (dict(rho_min=0.0), "log spacing needs rho_min > 0"),
        (dict(rho_min=-1.0, spacing="uniform"), "rho_min must be >= 0"),
        (dict(rho_min=1.0, rho_max=1.5, spacing="paper"),
         r"paper spacing needs rho_max - rho_min > 1"),
        (dict(spacing="cubic"), "spacing must be one of"),
        (dict(n_rho=0), "n_rho must be a positive integer"),
        (dict(n_theta=-3), "n_theta must be a positive integer"),
        (dict(n_phi=2.5), "n_phi must be a positive integer"),
        (dict(n_phi=True), "n_phi must be a positive integer"),
        (dict(rho_max=np.nan), "rho_max must be a finite number"),
        (dict(rho_max=np.inf), "rho_max must be a finite number"),
        (dict(theta_range=(1.0, 0.5)), "theta_range must be increasing"),
        (dict(theta_range=(0.0, 0.0)), "theta_range must be increasing"),
        (dict(theta_range=(-PI, PI + 0.1)), "an azimuth range is at most 2\\*pi"),
        (dict(theta_range=(0.0,)), "theta_range must be a pair"),
        (dict(phi_range=(-2.0, 0.0)), r"phi_range must lie in \[-pi/2, pi/2\]"),
        (dict(phi_range=(0.5, 0.5)), "phi_range must be increasing"),
        (dict(rho_max=1e155), r"rho_max must lie within \[1e-100, 1e\+100\]"),
    ],
)
def test_bad_grid(kwargs, match):
    args = dict(rho_min=0.3, rho_max=10.0, n_rho=4, n_theta=4, n_phi=4)
    args.update(kwargs)
    with pytest.raises(ValueError, match=match):
        lt.Grid(**args)


@pytest.mark.parametrize(
    "edges, match",
    [
        (([1, 2, 2], [0, 1], [0, 1]), r"rho_edges must be strictly increasing; edges\[1\]=2.0"),
        (([1, 2], [0, 1, 0.5], [0, 1]), "theta_edges must be strictly increasing"),
        (([1, 2], [0, 7], [0, 1]), "theta_edges spans"),
        (([1, 2], [0, 1], [0, 2]), "phi_edges must lie in"),
        (([1], [0, 1], [0, 1]), "at least 2 edges"),
        (([-1, 2], [0, 1], [0, 1]), r"rho_edges\[0\] must be >= 0"),
        (([1, np.nan], [0, 1], [0, 1]), "rho_edges must be finite"),
        (([1, 1e160], [0, 1], [0, 1]), "rho_edges must lie within"),
        (([[1, 2]], [0, 1], [0, 1]), "rho_edges must be 1-D"),
        ((["a", "b"], [0, 1], [0, 1]), "rho_edges must be a 1-D array of numbers"),
    ],
)
def test_bad_edges(edges, match):
    with pytest.raises(ValueError, match=match):
        lt.Grid.from_edges(*edges)


def test_bad_increments():
    with pytest.raises(ValueError, match="does not divide the range"):
        lt.Grid.from_increments(10, 80, 10, d_theta=7.0)
    with pytest.raises(ValueError, match="d_phi must be > 0 degrees"):
        lt.Grid.from_increments(10, 80, 10, d_phi=-1.0)


GRID = lt.Grid(0.3, 10.0, 4, 4, 4)


@pytest.mark.parametrize(
    "origins, directions, match",
    [
        ([[0, 0, np.nan]], [[1, 0, 0]], r"origins must be finite; row 0 is \[0.0, 0.0, nan\]"),
        ([[0, 0, 0], [1, 2, 3]], [[1, 0, 0], [np.inf, 0, 0]], "directions must be finite; row 1"),
        ([[0, 0, 0]], [[0, 0, 0]], r"directions must be non-zero; row 0 is \[0.0, 0.0, 0.0\]"),
        ([[0, 0]], [[1, 0, 0]], r"origins must have shape \(m, 3\) or \(3,\)"),
        ([[0, 0, 0], [1, 1, 1]], [[1, 0, 0]] * 3, "directions has 3 rows but origins has 2"),
        ([[0, 0, 0]], [[1j, 0, 0]], "directions must be real, not complex"),
        (np.zeros((2, 5)), None, r"origins must be one \(m, 6\) array"),
        ([["x", 0, 0]], [[1, 0, 0]], "origins must be numeric"),
    ],
)
def test_bad_rays(origins, directions, match):
    with pytest.raises(ValueError, match=match):
        lt.trace_many(GRID, origins, directions)


@pytest.mark.parametrize("rows", [5, "many"])
def test_one_origin_or_one_direction_serves_every_ray(rows):
    # numpy's rule for a row of one: the result is that of the repeated rows,
    # on the serial and the one-pass parallel check (from PARALLEL_CHECK_ROWS).
    from logsph_trace import _validate

    n = _validate.PARALLEL_CHECK_ROWS + 7 if rows == "many" else rows
    rng = np.random.default_rng(21)
    origins = rng.uniform(-4, 4, (n, 3))
    directions = rng.normal(size=(n, 3))
    t_max = rng.uniform(0, 20, n)
    eye, gaze = origins[1], directions[2]
    for got, want in (
        (lt.trace_many(GRID, eye, directions, t_max=t_max),
         lt.trace_many(GRID, np.repeat(eye[None], n, axis=0), directions, t_max=t_max)),
        (lt.trace_many(GRID, origins, gaze[None]),
         lt.trace_many(GRID, origins, np.repeat(gaze[None], n, axis=0))),
    ):
        assert len(got) == n
        for name in ("offsets", "cells", "t_enter", "t_exit"):
            np.testing.assert_array_equal(getattr(got, name), getattr(want, name))
    with pytest.raises(ValueError, match=r"origins must be finite; row 0 is \[nan"):
        lt.trace_many(GRID, [np.nan, 0, 0], directions)
    assert len(lt.trace_many(GRID, eye, np.empty((0, 3)))) == 0


def test_one_eye_serves_every_cone():
    eye = [0.3, -0.2, 1.1]
    gazes = np.random.default_rng(22).normal(size=(4, 3))
    shared = lt.trace_cones(GRID, eye, gazes, [0.05, 0.1, 0.0, 0.2])
    for cone, gaze, angle in zip(shared, gazes, [0.05, 0.1, 0.0, 0.2]):
        alone = lt.trace_cone(GRID, eye, gaze, angle)
        np.testing.assert_array_equal(cone.cells, alone.cells)
        np.testing.assert_array_equal(cone.weights, alone.weights)
    with pytest.raises(ValueError, match="directions has 4 rows but origins has 2"):
        lt.trace_cones(GRID, [eye, eye], gazes, 0.1)


@pytest.mark.parametrize("call", [
    lambda: GRID.cell_of([[1 + 1j, 0, 0]]),
    lambda: lt.trace(GRID, [0, 0, 0], np.array([1, 0, 0], dtype=np.complex64)),
    lambda: lt.trace_many(GRID, [[0, 0, 0]], [[1, 0, 0]], t_max=[2j]),
    lambda: lt.trace_cones(GRID, [[0, 0, 0]], [[1, 0, 0]], [0.1 + 0j]),
    lambda: lt.OccupancyGrid(GRID).integrate(np.array([[1, 1, 1j]]), [0, 0, 0]),
    lambda: lt.depth_to_points(np.ones((2, 2)), [1 + 0j, 1, 1, 1]),
])
def test_complex_input_is_refused_not_cast(call):
    # numpy casts complex to float with only a warning, dropping the imaginary part.
    with pytest.raises(ValueError, match="must be real, not complex"):
        call()


@pytest.mark.parametrize("call, match", [
    (lambda: lt.Grid(np.complex128(0.3), 10.0, 4, 4, 4), "rho_min must be a finite number"),
    (lambda: lt.trace_cone(GRID, [0, 0, 0], [1, 0, 0], 0.1 + 0j), "half_angle must be a number"),
    (lambda: lt.trace_cone(GRID, [0, 0, 0], [1, 0, 0], 0.1, sigma="wide"),
     "sigma must be a positive number of radians, got 'wide'"),
    (lambda: lt.OccupancyGrid(GRID).decay(np.complex64(0.5)), r"factor must be in \[0, 1\]"),
    (lambda: lt.fixation_probability(lt.OccupancyGrid(GRID), [0, 0, 0], [1, 0, 0], 0.05,
                                     unknown=None), "unknown must be a probability in"),
    (lambda: lt.fixation_probability(lt.OccupancyGrid(GRID), [0, 0, 0], [1, 0, 0], 0.05,
                                     min_distance="far"), "min_distance must be >= 0, got 'far'"),
])
def test_a_number_that_is_not_one_names_its_argument(call, match):
    with pytest.raises(ValueError, match=match):
        call()


def test_bad_method_and_grid():
    with pytest.raises(ValueError, match="method must be one of"):
        lt.trace(GRID, [0, 0, 0], [1, 0, 0], method="magic")
    with pytest.raises(ValueError, match="grid must be a logsph_trace.Grid"):
        lt.trace("grid", [0, 0, 0], [1, 0, 0])
    with pytest.raises(ValueError, match=r"origin must have shape \(3,\)"):
        lt.trace(GRID, [[0, 0, 0]], [1, 0, 0])


def test_bad_points():
    with pytest.raises(ValueError, match="points must be finite"):
        GRID.cell_of([[0, 0, np.nan]])
    with pytest.raises(ValueError, match=r"points must have shape \(M, 3\)"):
        GRID.cell_of(np.zeros((4, 2)))


def test_inputs_are_coerced():
    # Integer, non-contiguous and float32 inputs are accepted and give the float64 answer.
    origins = np.arange(12, dtype=np.int64).reshape(4, 3)[:, ::-1]
    directions = np.ones((4, 3), dtype=np.float32)
    got = lt.trace_many(GRID, origins, directions)
    want = lt.trace_many(GRID, origins.astype(float).copy(), np.ones((4, 3)))
    np.testing.assert_array_equal(got.cells, want.cells)


def test_empty_batch():
    traces = lt.trace_many(GRID, np.empty((0, 3)), np.empty((0, 3)))
    assert len(traces) == 0 and traces.offsets.tolist() == [0]


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_a_large_batch_is_checked_for_finite_values(bad):
    # Above PARALLEL_CHECK_ROWS the lengths are taken on all threads; one bad
    # value near the end is still found, named by its row, or skipped as a
    # sensor's.
    from logsph_trace import _validate

    rows = _validate.PARALLEL_CHECK_ROWS + 4099
    points = np.random.default_rng(3).uniform(-3, 3, (rows, 3))
    points[rows - 2, 1] = bad
    with pytest.raises(ValueError, match=f"points must be finite; row {rows - 2} is"):
        lt.OccupancyGrid(GRID_FOR_SCANS).integrate(points, [0.0, 0.0, 0.0])
    with pytest.raises(ValueError, match=f"points must be finite; row {rows - 2} is"):
        GRID.cell_of(points)
    occupancy = lt.OccupancyGrid(GRID_FOR_SCANS).integrate(points, [0.0, 0.0, 0.0],
                                                          invalid="skip")
    assert occupancy.last_scan.invalid == 1 and occupancy.last_scan.rays == rows - 1
    points[rows - 2, 1] = 0.5
    kept, mask = _validate.finite_rows("points", points)
    assert mask is None and kept.shape == points.shape


@pytest.mark.parametrize("length", [1, 7, 8, 9, 4095, 4096, 4097, 3 * 4096 + 13])
def test_the_finite_check_finds_one_bad_value_at_any_place(length):
    # The finite check every input goes through: a bad value is found at the
    # start, the end and throughout, and the largest, smallest and
    # signed-zero finite values pass.
    from logsph_trace import _validate

    values = np.random.default_rng(length).normal(size=length)
    values[::5] = 1.7976931348623157e308
    values[1::7] = -5e-324
    values[2::11] = -0.0
    assert _validate._all_finite(values)
    places = sorted({0, length - 1, *range(0, length, max(1, length // 40)),
                     *range(max(0, length - 17), length)})
    for place in places:
        for bad in (np.nan, np.inf, -np.inf):
            changed = values.copy()
            changed[place] = bad
            assert not _validate._all_finite(changed), (place, bad)
    assert _validate._all_finite(np.empty(0))


def _rays_step_by_step(origins, directions):
    """What ``_validate.rays`` does for a small batch: each check in turn."""
    from logsph_trace import _validate

    origins = _validate.origin_size("origins", _validate.vectors("origins", origins))
    directions = _validate.vectors("directions", directions)
    return origins, _validate.unit_directions(directions)


def test_a_large_batch_of_rays_is_checked_in_one_pass_with_the_same_result():
    # From PARALLEL_CHECK_ROWS rays one kernel checks every row and scales
    # the directions; its units are bit for bit those of the checks in turn,
    # also for directions so long or short that norm3 rescales them.
    from logsph_trace import _validate

    rows = _validate.PARALLEL_CHECK_ROWS + 4099
    rng = np.random.default_rng(11)
    origins = rng.normal(size=(rows, 3)) * 10.0 ** rng.uniform(-200, 150, (rows, 1))
    directions = rng.normal(size=(rows, 3)) * 10.0 ** rng.uniform(-300, 300, (rows, 1))
    directions[::97, 1:] = 0.0  # along an axis
    got = _validate.rays(origins, directions)
    want = _rays_step_by_step(origins, directions)
    for a, b in zip(got, want):
        assert a.flags.c_contiguous and a.dtype == np.float64
        np.testing.assert_array_equal(a.view(np.uint64), b.view(np.uint64))
    packed = _validate.rays(np.hstack([origins, directions]), None)  # the (m, 6) form
    np.testing.assert_array_equal(packed[1].view(np.uint64), want[1].view(np.uint64))


@pytest.mark.parametrize("which, column, bad, match", [
    ("origins", 0, np.nan, "origins must be finite"),
    ("origins", 2, 2e154, "origins must be shorter than about 1e154"),
    ("directions", 1, -np.inf, "directions must be finite"),
    ("directions", None, 0.0, "directions must be non-zero"),
])
def test_a_large_batch_of_rays_names_its_first_faulty_row(which, column, bad, match):
    from logsph_trace import _validate

    rows = _validate.PARALLEL_CHECK_ROWS + 4099
    rng = np.random.default_rng(12)
    arrays = {"origins": rng.normal(size=(rows, 3)), "directions": rng.normal(size=(rows, 3))}
    for row in (rows - 3, 5000, rows - 1):  # the first of them is named
        if column is None:
            arrays[which][row] = bad
        else:
            arrays[which][row, column] = bad
    with pytest.raises(ValueError, match=match) as error:
        _validate.rays(arrays["origins"], arrays["directions"])
    assert "row 5000 is" in str(error.value)


GRID_FOR_SCANS = lt.Grid(0.3, 10.0, 8, 12, 6)
