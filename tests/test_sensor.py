"""Depth images into the map: back-projection, poses, invalid pixels, real data."""

import numpy as np
import pytest

import logsph_trace as lt
from logsph_trace.sensor import DEFAULT_ROTATION

GRID = lt.Grid(0.3, 8.0, 16, 48, 24)
K = np.array([[61.37, 0.0, 15.61], [0.0, 59.83, 11.27], [0.0, 0.0, 1.0]])


def _rotation(rng):
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q *= np.sign(np.diag(r))
    return q if np.linalg.det(q) > 0 else -q


def _reference(depth, intrinsics, rotation, translation, scale=1.0):
    """R K^-1 (u, v, 1) Z + t per valid pixel, row-major: the textbook formula."""
    rows, columns = np.nonzero(np.isfinite(depth) & (depth > 0))
    z = depth[rows, columns].astype(np.float64) * scale
    rays = np.linalg.solve(intrinsics, np.stack([columns, rows, np.ones_like(rows)]).astype(float))
    return (rotation @ (rays * z)).T + translation


def test_a_plane_in_front_of_the_default_camera():
    # A wall 2.5 m ahead: every point at z = 2.5; image-up is +y, image-right is -x.
    depth = np.full((24, 32), 2.5)
    scan = lt.depth_to_points(depth, K)
    assert len(scan) == depth.size and scan.invalid == 0
    assert np.allclose(scan.points[:, 2], 2.5, rtol=0, atol=1e-15)
    top_left = scan.points[0]
    assert top_left[0] > 0 and top_left[1] > 0  # left of and above the optical axis
    assert np.array_equal(scan.origin, [0.0, 0.0, 0.0])
    assert np.array_equal(scan.pixels[1], [0, 1])


def test_points_match_the_textbook_formula_for_random_cameras():
    rng = np.random.default_rng(4)
    for _ in range(20):
        depth = rng.uniform(0.31, 7.9, (13, 17))
        intrinsics = np.array([[rng.uniform(20, 90), rng.uniform(-0.3, 0.3), rng.uniform(5, 12)],
                               [0.0, rng.uniform(20, 90), rng.uniform(4, 9)], [0.0, 0.0, 1.0]])
        rotation, translation = _rotation(rng), rng.normal(scale=0.3, size=3)
        scan = lt.depth_to_points(depth, intrinsics, (rotation, translation))
        want = _reference(depth, intrinsics, rotation, translation)
        assert np.allclose(scan.points, want, rtol=1e-13, atol=1e-13)
        assert np.array_equal(scan.origin, translation)


def test_pose_forms_agree_and_none_is_the_documented_camera():
    rng = np.random.default_rng(5)
    depth = rng.uniform(0.5, 5.0, (6, 9))
    rotation, translation = _rotation(rng), np.array([0.061, -0.083, 0.017])
    matrix = np.eye(4)
    matrix[:3, :3], matrix[:3, 3] = rotation, translation
    as_pair = lt.depth_to_points(depth, K, (rotation, translation)).points
    assert np.array_equal(lt.depth_to_points(depth, K, matrix).points, as_pair)
    default = lt.depth_to_points(depth, K).points
    explicit = lt.depth_to_points(depth, K, (DEFAULT_ROTATION, np.zeros(3))).points
    assert np.array_equal(default, explicit)
    # OpenCV's (x, y, z) is the map's (-x, -y, z)
    camera = lt.depth_to_points(depth, K, (np.eye(3), np.zeros(3))).points
    assert np.array_equal(default, camera * [-1.0, -1.0, 1.0])
    four = (K[0, 0], K[1, 1], K[0, 2], K[1, 2])
    assert np.array_equal(lt.depth_to_points(depth, four).points, default)


def test_pixels_without_depth_are_skipped_and_counted():
    depth = np.full((5, 6), 1.7)
    bad = [(0, 0), (1, 2), (2, 3), (3, 4), (4, 5)]
    depth[tuple(np.array(bad).T)] = [0.0, np.nan, np.inf, -1.0, -np.inf]
    scan = lt.depth_to_points(depth, K)
    assert scan.invalid == 5 and len(scan) == 25
    assert not any(tuple(p) in bad for p in scan.pixels.tolist())
    occupancy = lt.OccupancyGrid(GRID).integrate_depth(depth, K)
    assert occupancy.last_scan == lt.ScanStats(rays=25, invalid=5)


def test_millimetre_images_with_a_depth_scale():
    rng = np.random.default_rng(6)
    millimetres = rng.integers(0, 6000, (9, 11)).astype(np.uint16)  # 0: no depth
    metres = millimetres.astype(np.float64) * 0.001
    got = lt.depth_to_points(millimetres, K, depth_scale=0.001)
    want = lt.depth_to_points(metres, K)
    assert got.invalid == want.invalid == int(np.count_nonzero(millimetres == 0))
    assert np.array_equal(got.points, want.points)


def test_integrate_depth_is_integrate_of_its_points_frame_after_frame():
    # Two cameras, two frames each, one cut at max_range: the same map as
    # integrating the helper's points from the helper's origin.
    rng = np.random.default_rng(7)
    by_depth, by_points = lt.OccupancyGrid(GRID), lt.OccupancyGrid(GRID)
    for frame in range(4):
        depth = rng.uniform(0.2, 9.0, (12, 16))
        depth[rng.random(depth.shape) < 0.1] = np.nan
        pose = (_rotation(rng), rng.normal(scale=0.2, size=3)) if frame % 2 else None
        max_range = 6.0 if frame == 1 else None
        by_depth.integrate_depth(depth, K, pose, max_range=max_range)
        scan = lt.depth_to_points(depth, K, pose)
        by_points.integrate(scan.points, scan.origin, max_range=max_range)
        assert np.array_equal(by_depth.log_odds, by_points.log_odds)
        assert by_depth.last_scan.invalid == scan.invalid


def test_max_range_clears_without_marking_a_hit():
    depth = np.full((8, 10), 6.0)
    occupancy = lt.OccupancyGrid(GRID).integrate_depth(depth, K, max_range=3.0)
    assert len(occupancy.occupied(0.5)) == 0
    free = np.argwhere(occupancy.log_odds < 0)
    assert free.size and GRID.rho_edges[free[:, 0].max()] < 3.0
    near = lt.OccupancyGrid(GRID).integrate_depth(depth, K, max_range=7.0)
    assert len(near.occupied(0.5)) > 0


def test_nan_points_raise_by_default_and_are_skipped_when_asked():
    rng = np.random.default_rng(8)
    points = rng.uniform(-6, 6, (200, 3))
    points[[3, 50, 51]] = [np.nan, 0.0, 1.0]
    points[120, 2] = np.inf
    with pytest.raises(ValueError, match="points must be finite; row 3"):
        lt.OccupancyGrid(GRID).integrate(points, (0.1, 0.0, 0.0))
    skipped = lt.OccupancyGrid(GRID).integrate(points, (0.1, 0.0, 0.0), invalid="skip")
    assert skipped.last_scan == lt.ScanStats(rays=196, invalid=4)
    finite = lt.OccupancyGrid(GRID).integrate(points[np.isfinite(points).all(axis=1)],
                                              (0.1, 0.0, 0.0))
    assert np.array_equal(skipped.log_odds, finite.log_odds)
    with pytest.raises(ValueError, match="invalid must be one of"):
        lt.OccupancyGrid(GRID).integrate(points, (0.1, 0.0, 0.0), invalid="drop")


@pytest.mark.parametrize("kwargs, match", [
    (dict(intrinsics=np.eye(2)), "3x3 matrix or"),
    (dict(intrinsics=(0.0, 50.0, 1.0, 1.0)), "must be positive"),
    (dict(intrinsics=(50.0, np.nan, 1.0, 1.0)), "must be finite"),
    (dict(intrinsics=[[50, 0, 1], [0, 50, 1], [0, 1, 1]]), "camera matrix"),
    (dict(pose=np.eye(3)), r"pose must have shape \(4, 4\)"),
    (dict(pose=np.diag([1.0, 1.0, 1.0, 2.0])), "last row"),
    (dict(pose=(np.diag([1.0, 1.0, -1.0]), np.zeros(3))), "determinant"),
    (dict(pose=(np.eye(3) * 1.01, np.zeros(3))), "orthonormal"),
    (dict(pose=(np.eye(3), [0.0, np.inf, 0.0])), "pose translation must be finite"),
    (dict(depth=np.ones((2, 3, 4))), "2-D image"),
    (dict(depth=np.array([["a"]])), "must hold numbers"),
    (dict(depth_scale=0.0), "depth_scale must be positive"),
    (dict(depth_scale=np.nan), "depth_scale must be a finite number"),
])
def test_bad_camera_input_is_a_clear_value_error(kwargs, match):
    arguments = dict(depth=np.ones((4, 5)), intrinsics=K, pose=None, depth_scale=1.0)
    arguments.update(kwargs)
    with pytest.raises(ValueError, match=match):
        lt.depth_to_points(**arguments)
    with pytest.raises(ValueError, match=match):
        lt.OccupancyGrid(GRID).integrate_depth(**arguments)


def test_the_real_motorcycle_frame():
    # Middlebury 2014 Motorcycle (scikit-image): every point in an occupied
    # cell, the space in front of the points free, the pixels without
    # ground truth counted; from the centre and 10 cm off it.
    pytest.importorskip("skimage")
    from logsph_trace import datasets

    frame = datasets.motorcycle()
    grid = lt.Grid(0.3, 8.0, 64, 360, 180)
    assert int(frame.valid.sum()) == 343_274
    for sensor in ((0.0, 0.0, 0.0), (0.06, 0.08, 0.0)):
        occupancy = lt.OccupancyGrid(grid).integrate_depth(
            frame.depth, frame.intrinsics, (DEFAULT_ROTATION, np.array(sensor)))
        assert occupancy.last_scan == lt.ScanStats(rays=343_274, invalid=frame.depth.size - 343_274)
        points = lt.depth_to_points(frame.depth, frame.intrinsics,
                                    (DEFAULT_ROTATION, np.array(sensor))).points
        at_points = occupancy.log_odds[tuple(grid.cell_of(points).T)]
        assert np.mean(at_points > 0) >= 0.999
        before = np.array(sensor) + 0.8 * (points - np.array(sensor))
        assert np.mean(occupancy.log_odds[tuple(grid.cell_of(before).T)] < 0) >= 0.95
