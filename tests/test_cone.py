"""Gaze cones: sampling, weights, aggregation, the default ray count, bad input."""

import math

import numpy as np
import pytest
from oracle import union_of_rays

import logsph_trace as lt
from logsph_trace.cone import cone_directions, default_ray_count, trace_cone, trace_cones

GRID = lt.Grid(0.3, 10.0, 24, 72, 36)
ORIGIN = np.array([0.4, 1.5, 1.2])
GAZE = np.array([-0.1, -0.4, 1.0])


def _union_of_rays(cone):
    """Reference aggregation (tests/oracle.py) of the cone's rays, traced again one by one."""
    return union_of_rays([(one.cells, one.t_enter) for one in cone.traces], cone.ray_weights)


def test_zero_half_angle_is_the_single_ray():
    cone = trace_cone(GRID, ORIGIN, GAZE, 0.0)
    ray = lt.trace(GRID, ORIGIN, GAZE)
    assert cone.directions.shape == (1, 3)
    np.testing.assert_array_equal(cone.cells, ray.unique())
    assert cone.weights.sum() == pytest.approx(1.0)


@pytest.mark.parametrize("pattern", ["fibonacci", "rings"])
@pytest.mark.parametrize("weighting", ["gaussian", "uniform"])
def test_weights_sum_to_one_and_every_crossed_cell_is_reported(pattern, weighting):
    cone = trace_cone(GRID, ORIGIN, GAZE, np.radians(8), n_rays=200, pattern=pattern,
                      weighting=weighting)
    assert cone.ray_weights.sum() == pytest.approx(1.0)
    assert cone.weights.sum() == pytest.approx(1.0)
    weights, first = _union_of_rays(cone)
    total = sum(weights.values())
    got = {tuple(c): (w, t) for c, w, t in zip(cone.cells.tolist(), cone.weights, cone.t_first)}
    assert set(got) == set(weights)
    for cell, (w, t) in got.items():
        assert w == pytest.approx(weights[cell] / total)
        assert t == first[cell]
    assert np.all(np.diff(cone.t_first) >= 0)  # ordered by first reach


def test_sampled_directions_lie_in_the_cone():
    for pattern in ("fibonacci", "rings"):
        directions, angles = cone_directions(GAZE, 0.3, 100, pattern)
        axis = GAZE / np.linalg.norm(GAZE)
        np.testing.assert_allclose(np.linalg.norm(directions, axis=1), 1.0)
        np.testing.assert_allclose(np.arccos(np.clip(directions @ axis, -1, 1)), angles, atol=1e-7)
        assert angles.max() <= 0.3 + 1e-12
    assert cone_directions(GAZE, 0.3, 100, "fibonacci")[0].shape == (100, 3)
    assert cone_directions(GAZE, 0.3, 100, "rings")[0].shape == (1 + 3 * 6 * 7, 3)  # 6 rings


def _numpy_cone(axis, half_angle, n_rays, pattern, sigma):
    """The cone's rays written out plainly in numpy: the construction
    ``cone_directions`` documents, to compare the sampling kernel with.

    Sines and cosines come from Python's ``math`` (the C library): some
    numpy versions' vectorised ones are off by 1e-14 at the thousands of
    radians the spiral turns through.
    """
    cos, sin, acos = (np.vectorize(f, otypes=[float]) for f in (math.cos, math.sin, math.acos))
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    if pattern == "fibonacci":
        index = np.arange(n_rays)
        angles = acos(1.0 - (1.0 - math.cos(half_angle)) * (index + 0.5) / n_rays)
        around = index * (math.pi * (3.0 - math.sqrt(5.0)))  # golden angles
    else:
        rings = int(np.ceil((-3.0 + np.sqrt(9.0 + 12.0 * (n_rays - 1))) / 6.0))
        angles, around = [0.0], [0.0]
        for ring in range(1, rings + 1):
            angles += [half_angle * ring / rings] * (6 * ring)
            around += list(2 * np.pi * (np.arange(6 * ring) + 0.5 * (ring % 2)) / (6 * ring))
        angles, around = np.array(angles), np.array(around)
    helper = np.array([1.0, 0, 0]) if abs(axis[0]) < 0.9 else np.array([0, 1.0, 0])
    first = np.cross(axis, helper)
    first /= np.linalg.norm(first)
    second = np.cross(axis, first)
    sideways = cos(around)[:, None] * first + sin(around)[:, None] * second
    directions = cos(angles)[:, None] * axis + sin(angles)[:, None] * sideways
    weights = np.exp(-0.5 * (angles / sigma) ** 2) if sigma else np.ones(len(angles))
    return directions, angles, weights / weights.sum()


@pytest.mark.parametrize("pattern, n_rays", [("fibonacci", 1000), ("fibonacci", 17),
                                             ("rings", 2), ("rings", 1000), ("rings", 4000)])
def test_sampled_rays_follow_the_documented_construction(pattern, n_rays):
    # Random axes, some within 1e-13 of the x axis where the frame's helper
    # changes, and of the z axis; the angles of the rings exactly r h / R.
    rng = np.random.default_rng(11)
    axes = [rng.normal(size=3), [1.0, 1e-13, -2e-13], [0.9 * (1 + 1e-15), 0.4, 0.1],
            [-1e-14, 3e-14, 1.0]]
    for axis in axes:
        half_angle = rng.uniform(0.001, 0.5)  # under 30 degrees: no unit warning
        sigma = rng.uniform(0.01, 1.0)
        cone = trace_cone(GRID, ORIGIN, axis, half_angle, n_rays=n_rays, pattern=pattern,
                          sigma=sigma)
        directions, angles = cone_directions(axis, half_angle, n_rays, pattern)
        want, want_angles, want_weights = _numpy_cone(axis, half_angle, n_rays, pattern, sigma)
        np.testing.assert_array_equal(cone.directions, directions)
        np.testing.assert_allclose(directions, want, rtol=0, atol=4e-16)
        np.testing.assert_allclose(angles, want_angles, rtol=1e-15, atol=1e-15)
        # In the tails exp() turns an ulp of the angle into many: compare exponents.
        np.testing.assert_allclose(np.log(cone.ray_weights), np.log(want_weights), rtol=1e-14,
                                   atol=1e-14)
        assert abs(math.fsum(cone.ray_weights) - 1.0) < 3e-16  # a compensated sum
        if pattern == "rings":
            rings = round(np.sqrt(n_rays / 3))  # 1 + 3 R (R + 1) rays: R(R + 1) ~ n / 3
            rings = next(r for r in range(rings - 2, rings + 3) if 1 + 3 * r * (r + 1) >= n_rays)
            ring_of = np.repeat(np.arange(rings + 1), [1] + [6 * r for r in range(1, rings + 1)])
            np.testing.assert_array_equal(angles, half_angle * ring_of / rings)


def test_chunks_of_many_cones_are_each_cones_own():
    from logsph_trace.cone import CONE_CHUNK_RAYS, CONE_CHUNKS, chunk_bounds, chunk_starts

    counts = [1, 31, 32, 33, 64, 65, 225, 511, 512, 513, 1000, 99_999, 7]
    bounds, cone_bounds = chunk_bounds(counts)
    start = 0
    for cone, count in enumerate(counts):
        own = bounds[cone_bounds[cone]:cone_bounds[cone + 1]] - start
        np.testing.assert_array_equal(own, chunk_starts(count))
        assert own[0] == 0 and own[-1] == count and np.all(np.diff(own) > 0)
        assert len(own) - 1 == max(1, min(CONE_CHUNKS, count // CONE_CHUNK_RAYS))
        assert np.ptp(np.diff(own)) <= 1  # as even as integers allow
        start += count


def test_first_reach_order_is_numpys_stable_argsort():
    # The radix sort that orders a cone's cells: ties in the order given,
    # -0.0 equal to 0.0, infinities and subnormals in place, keys that share
    # whole digits (skipped passes) and keys that differ only in their last bit.
    from logsph_trace.kernels.cone import first_reach_order

    rng = np.random.default_rng(5)
    tiny = np.finfo(float).smallest_subnormal
    cases = [np.empty(0), np.array([2.5]), np.array([0.0, -0.0, 0.0, -0.0]),
             np.array([3.0, 1.0, 3.0, -2.0, -0.0, np.inf, -np.inf, 0.0, tiny, -tiny, 1.0]),
             rng.uniform(0, 20, 2000), np.round(rng.uniform(0, 5, 3000), 1),
             rng.normal(size=5000) * 1e300, np.full(100, 7.5),
             np.nextafter(1.0, 2.0, out=np.ones(500), where=rng.random(500) < 0.5),
             np.concatenate([rng.uniform(0, 1, 100), -rng.uniform(0, 1, 100)])]
    for t_first in cases:
        np.testing.assert_array_equal(first_reach_order(t_first),
                                      np.argsort(t_first, kind="stable"))


def test_gaussian_weighting_favours_the_axis():
    cone = trace_cone(GRID, ORIGIN, GAZE, np.radians(10), n_rays=300)
    _, angles = cone_directions(GAZE, np.radians(10), 300)
    assert cone.ray_weights[np.argmin(angles)] > 5 * cone.ray_weights[np.argmax(angles)]


@pytest.mark.parametrize(
    "grid, origin, gaze, degrees",
    [
        (GRID, ORIGIN, GAZE, 6),
        (GRID, [1.0, 1.6, 0.0], [0.2, -0.3, 1.0], 3),
        (lt.Grid(0.3, 10.0, 64, 360, 180), ORIGIN, GAZE, 15),
        (lt.Grid(0.3, 5.0, 16, 36, 18), [2.0, 0.5, -1.0], [-1.0, 0.0, 1.0], 1),
    ],
)
def test_default_ray_count_covers_a_ten_times_denser_cone(grid, origin, gaze, degrees):
    # Stated tolerance (default_ray_count): the cells a 10x denser cone adds
    # carry under 3% of its weight -- slivers grazed by few of its rays.
    half_angle = np.radians(degrees)
    n_rays = default_ray_count(grid, origin, half_angle)
    default = trace_cone(grid, origin, gaze, half_angle)
    dense = trace_cone(grid, origin, gaze, half_angle, n_rays=10 * n_rays)
    assert default.directions.shape[0] == n_rays >= 16
    have = set(map(tuple, default.cells.tolist()))
    missing = [w for c, w in zip(dense.cells.tolist(), dense.weights) if tuple(c) not in have]
    assert sum(missing) < 0.03


def test_a_cone_across_the_theta_seam():
    # Looking along -z: theta = +-pi, the seam of the full circle.
    cone = trace_cone(GRID, [0.2, 0.3, 1.0], [0.0, 0.0, -1.0], np.radians(10), n_rays=300)
    weights, _ = _union_of_rays(cone)
    assert set(map(tuple, cone.cells.tolist())) == set(weights)
    j = cone.cells[:, 1]
    assert np.any(j == 0) and np.any(j == GRID.n_theta - 1)


def test_many_cones_equal_one_at_a_time():
    # One parallel call aggregates every cone of a batch, each in the chunks
    # trace_cone cuts it into: the same cells, weights and first reaches, bit
    # for bit. Cones of 1 to 700 rays (1 to 16 chunks), one across the theta
    # seam, one that misses the grid, a single ray.
    origins = np.array([ORIGIN, [1.0, 0.2, -2.0], [0.0, 1.0, 0.5], [0.5, 0.2, -1.0],
                        [30.0, 0.0, 0.0], ORIGIN])
    gazes = np.array([GAZE, [0.3, 0.1, 1.0], [0.0, -1.0, 0.2], [-1.0, 0.1, -0.01],
                      [1.0, 0.0, 0.0], [0.2, 0.3, -1.0]])
    half_angles = [0.05, 0.1, 0.0, 0.2, 0.1, 0.02]
    for n_rays in (64, 700, None):
        batch = trace_cones(GRID, origins, gazes, half_angles, n_rays=n_rays)
        for result, origin, gaze, angle in zip(batch, origins, gazes, half_angles):
            _same_cone(result, trace_cone(GRID, origin, gaze, angle, n_rays=n_rays))
            assert result.weights.sum() == pytest.approx(1.0) or len(result) == 0
    assert len(batch[4]) == 0  # outside the grid, looking away
    for kwargs in (dict(pattern="rings", n_rays=200), dict(weighting="uniform", n_rays=90),
                   dict(sigma=0.01)):
        batch = trace_cones(GRID, origins, gazes, half_angles, **kwargs)
        for result, origin, gaze, angle in zip(batch, origins, gazes, half_angles):
            _same_cone(result, trace_cone(GRID, origin, gaze, angle, **kwargs))


def _same_cone(one, other):
    np.testing.assert_array_equal(one.directions, other.directions)
    np.testing.assert_array_equal(one.ray_weights, other.ray_weights)
    np.testing.assert_array_equal(one.cells, other.cells)
    np.testing.assert_array_equal(one.weights, other.weights)
    np.testing.assert_array_equal(one.t_first, other.t_first)


def test_a_cone_is_the_same_on_every_path():
    # trace_cone aggregates straight from per-thread regions in reused scratch;
    # one thread, a second call and trace_cones must agree bit for bit.
    import numba

    args = (GRID, ORIGIN, GAZE, np.radians(8))
    regions = trace_cone(*args, n_rays=700)
    before = numba.get_num_threads()
    try:
        numba.set_num_threads(1)
        _same_cone(trace_cone(*args, n_rays=700), regions)
    finally:
        numba.set_num_threads(before)
    _same_cone(trace_cones(GRID, [ORIGIN], [GAZE], np.radians(8), n_rays=700)[0], regions)
    assert regions._traces is None
    _same_cone(regions, trace_cone(*args, n_rays=700))  # through the kept scratch


def test_reused_scratch_does_not_change_earlier_results():
    small = trace_cone(GRID, ORIGIN, GAZE, np.radians(3), n_rays=200)
    kept = (small.cells.copy(), small.weights.copy(), small.t_first.copy())
    trace_cone(GRID, [1.0, 0.2, -2.0], [0.3, 0.1, 1.0], np.radians(20), n_rays=3000)
    np.testing.assert_array_equal(small.cells, kept[0])
    np.testing.assert_array_equal(small.weights, kept[1])
    np.testing.assert_array_equal(small.t_first, kept[2])
    weights, first = _union_of_rays(small)  # its traces, traced again on access
    assert set(map(tuple, small.cells.tolist())) == set(weights)


def test_a_cones_boxes_in_reused_scratch_equal_fresh_ones(monkeypatch):
    # The chunks' copies of the boxes come from this thread's kept scratch
    # once it is large enough: from none, from too little, from enough, and
    # with keeping off, the cones and their fixation are the same bit for bit.
    from logsph_trace import _batching

    occupancy = lt.OccupancyGrid(GRID)
    occupancy.integrate(ORIGIN + np.array([[0.5, -1.6, 6.0], [-0.4, -1.2, 5.0]]), ORIGIN)
    calls = [lambda angle: trace_cone(GRID, ORIGIN, GAZE, angle, n_rays=700),
             lambda angle: lt.fixation_probability(occupancy, ORIGIN, GAZE, half_angle=angle,
                                                   n_rays=700)]

    def results():
        return [(c.cells, c.weights, c.t_first) if hasattr(c, "weights") else
                (c.cells, c.values, c.t_enter) for c in (call(angle) for call in calls
                                                         for angle in (0.02, 0.3, 0.02))]

    monkeypatch.setattr(_batching, "_scratch", type(_batching._scratch)())
    kept = results()  # from none, then too little for the wide cone, then enough
    pool = _batching.box_pools()[1]
    assert pool.size > 0
    results()
    assert _batching.box_pools()[1] is pool  # enough: not made again
    monkeypatch.setattr(_batching, "KEEP_BOXES", 0)
    monkeypatch.setattr(_batching, "_scratch", type(_batching._scratch)())
    fresh = results()
    assert _batching.box_pools()[1].size == 0
    for one, other in zip(kept, fresh):
        for a, b in zip(one, other):
            np.testing.assert_array_equal(a, b)


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(half_angle=-0.1), r"half_angle must be in \[0, pi/2\)"),
        (dict(half_angle=np.pi / 2), r"half_angle must be in \[0, pi/2\)"),
        (dict(half_angle=np.nan), r"half_angle must be in \[0, pi/2\)"),
        (dict(half_angle="wide"), "half_angle must be a number"),
        (dict(origin=[np.nan, 0, 0]), "origin must be finite"),
        (dict(origin=[0, 0]), r"origin must have shape \(m, 3\) or \(3,\)"),
        (dict(direction=[0, 0, 0]), "direction must be non-zero"),
        (dict(n_rays=0), "n_rays must be a positive integer"),
        (dict(pattern="spiral"), "pattern must be one of"),
        (dict(weighting="cosine"), "weighting must be one of"),
        (dict(sigma=-1.0), "sigma must be a positive number"),
        (dict(grid="not a grid"), "grid must be a logsph_trace.Grid"),
    ],
)
def test_bad_cone_input(kwargs, match):
    args = dict(grid=GRID, origin=ORIGIN, direction=GAZE, half_angle=0.1, n_rays=10)
    args.update(kwargs)
    with pytest.raises(ValueError, match=match):
        trace_cone(**args)


@pytest.mark.parametrize("seed", range(4))
def test_cones_summed_without_boxes_equal_the_boxes_bit_for_bit(monkeypatch, seed):
    # Eyes facing the robot are summed without boxes (sparse_cone); any cone
    # may be, and must give the boxes' cells, order, sums and first reaches.
    from logsph_trace import cone as cone_module
    from logsph_trace.scene import table_scene

    rng = np.random.default_rng(seed)
    grid = lt.Grid(0.3, 6.0, 24, 72, 36)
    scene, _, _ = table_scene()
    bvm = lt.OccupancyGrid(grid).integrate(scene.depth_points(width=160, height=120)[0],
                                           (0.0, 0.0, 0.0))
    for _ in range(6):
        origin = rng.normal(size=3) * rng.choice([0.2, 1.5, 3.0])
        axis = rng.normal(size=3)
        half_angle = np.radians(rng.uniform(1.0, 20.0))
        n_rays = int(rng.choice([40, 300, 1200]))
        results = []
        for sparse in (False, True):
            monkeypatch.setattr(cone_module, "_towards_the_centre", lambda o, a, s=sparse: s)
            cone = lt.trace_cone(grid, origin, axis, half_angle, n_rays=n_rays)
            fixation = lt.fixation_probability(bvm, origin, axis, half_angle=half_angle,
                                               n_rays=n_rays, min_distance=0.2)
            results.append((cone.cells, cone.weights, cone.t_first, fixation.cells,
                            fixation.values, fixation.t_enter))
        for boxed, sparse in zip(*results):
            np.testing.assert_array_equal(boxed, sparse)


def test_a_gaze_towards_the_robot_takes_the_sparse_sum():
    from logsph_trace import cone as cone_module

    assert cone_module._towards_the_centre((-0.2, 0.75, 3.0), (0.05, -0.79, -0.61))
    assert not cone_module._towards_the_centre((0.4, 1.5, 1.2), (-0.1, -0.4, 1.0))
