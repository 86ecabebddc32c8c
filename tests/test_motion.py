"""A map that follows the robot: ``OccupancyGrid.move`` and its resampling."""

import pickle

import numpy as np
import pytest

import logsph_trace as lt
from bench.egomotion import f_score, gaze_agreement, random_gazes, walk_maps
from logsph_trace import motion
from logsph_trace.scene import robot_walk, room_scene, table_scene, yaw_pose


def _random_rotation(rng, angle):
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    cross = np.array([[0.0, -axis[2], axis[1]], [axis[2], 0.0, -axis[0]],
                      [-axis[1], axis[0], 0.0]])
    return np.eye(3) + np.sin(angle) * cross + (1.0 - np.cos(angle)) * cross @ cross


def _sparse_map(rng, grid, known=0.05):
    """Random log-odds on a random ``known`` share of the cells, labels on some of those."""
    log_odds = np.zeros(grid.shape, dtype=np.float32)
    where = rng.random(grid.shape) < known
    log_odds[where] = rng.uniform(-2.0, 3.5, np.count_nonzero(where)).astype(np.float32)
    labels = np.where(where & (log_odds > 0), rng.integers(1, 5, grid.shape), 0)
    return log_odds, labels.astype(np.int32)


def _reference(grid, log_odds, labels, rotation, translation):
    """``motion.resample`` one column and shell at a time, with ``lt.trace``."""
    out_log_odds = np.zeros(grid.shape, dtype=np.float32)
    out_labels = np.zeros(grid.shape, dtype=np.int32)
    directions = motion.column_directions(grid) @ rotation.T
    for column, direction in enumerate(directions):
        j, k = divmod(column, grid.n_phi)
        ray = lt.trace(grid, translation, direction)
        for i in range(grid.n_rho):
            low, high = grid.rho_edges[i], grid.rho_edges[i + 1]
            overlap = np.minimum(ray.t_exit, high) - np.maximum(ray.t_enter, low)
            if ray.cells.shape[0] and overlap.max() > 0.0:
                cell = tuple(ray.cells[int(np.argmax(overlap))])
                out_log_odds[i, j, k] = log_odds[cell]
                out_labels[i, j, k] = labels[cell]
    return out_log_odds, out_labels


@pytest.mark.parametrize("distance", [0.0, 1e-9, 0.37, 0.93, 1.6])  # of rho_min
def test_resampling_equals_a_cell_by_cell_reference(grid, distance, monkeypatch):
    monkeypatch.setattr(motion, "COLUMNS_PER_CHUNK", 37)  # chunks end mid-batch
    rng = np.random.default_rng(int(distance * 1000) + grid.n_rho)
    log_odds, labels = _sparse_map(rng, grid)
    rotation = _random_rotation(rng, rng.uniform(0.05, 3.0))
    translation = rng.normal(size=3)
    translation *= distance * max(grid.rho_min, 0.1) / np.linalg.norm(translation)
    got = motion.resample(grid, log_odds, labels, rotation, translation)
    want = _reference(grid, log_odds, labels, rotation, translation)
    np.testing.assert_array_equal(got[0], want[0])
    np.testing.assert_array_equal(got[1], want[1])


@pytest.mark.parametrize("theta_min", [-np.pi, 1.0 / 3.0])
@pytest.mark.parametrize("cells", [1, -2, 7, 181, 359])
def test_a_turn_by_whole_azimuth_cells_is_an_index_roll(theta_min, cells):
    grid = lt.Grid(0.3, 10.0, 6, 360, 20, theta_range=(theta_min, theta_min + 2 * np.pi))
    rng = np.random.default_rng(abs(cells))
    log_odds, labels = _sparse_map(rng, grid, known=0.3)
    occupancy = lt.OccupancyGrid(grid, log_odds=log_odds)
    occupancy.labels = labels
    occupancy.move(yaw_pose(cells * 2 * np.pi / 360, (0.0, 0.0, 0.0)))
    np.testing.assert_array_equal(occupancy.log_odds, np.roll(log_odds, -cells, axis=1))
    np.testing.assert_array_equal(occupancy.labels, np.roll(labels, -cells, axis=1))


def _table_map(grid):
    scene, _, _ = table_scene()
    occupancy = lt.OccupancyGrid(grid)
    for sensor in ((0.0, 0.0, 0.0), (0.03, 0.02, -0.04)):
        points, boxes, _ = scene.depth_points(sensor, 320, 240)
        occupancy.integrate(points, sensor, labels=boxes + 1)
    return occupancy


@pytest.mark.parametrize("seed", range(4))
def test_a_move_and_its_inverse_keep_the_map(seed):
    grid = lt.Grid(0.3, 10.0, 48, 240, 120)
    rng = np.random.default_rng(seed)
    occupancy = _table_map(grid)
    before = occupancy.log_odds.copy()
    step = np.eye(4)
    step[:3, :3] = _random_rotation(rng, np.radians(rng.uniform(0.5, 5.0)))
    step[:3, 3] = rng.normal(size=3) * rng.uniform(0.005, 0.05) / np.sqrt(3.0)
    occupancy.move(step).recentre().move(np.linalg.inv(step))
    f, _, _ = f_score(occupancy.log_odds > 0, before > 0)
    assert f >= 0.95


def test_a_walking_turning_robot_keeps_what_it_saw():
    """The robot turns 80 degrees and walks 0.4 m in 40 steps, a scan after each."""
    grid = lt.Grid(0.3, 10.0, 48, 240, 120)
    scene = room_scene()
    steps = list(robot_walk(scene, 40, np.radians(80.0), (0.4, 0.0, 0.0), 320, 240))
    moving, scratch, _ = walk_maps(grid, steps)
    f, _, _ = f_score(moving.log_odds > 0, scratch.log_odds > 0)
    assert f >= 0.9
    eyes, directions, boxes = random_gazes(scene, steps[-1].pose, 200)
    ahead = np.einsum("ij,ij->i", eyes + directions, np.array([0.0, 0.0, 1.0])[None]) > 0
    assert 0 < np.count_nonzero(~ahead)  # some targets are now behind the camera
    assert gaze_agreement(moving, scratch, eyes, directions) >= 0.95


def test_scans_and_gazes_after_a_move_are_in_the_new_frame():
    grid = lt.Grid(0.3, 10.0, 32, 180, 90)
    scene, eyes, target = table_scene()
    points, boxes, _ = scene.depth_points(width=320, height=240)
    turned = yaw_pose(np.radians(-30.0), (0.05, 0.0, 0.02))  # left by 30 degrees, a step
    rotation, position = turned[:3, :3], turned[:3, 3]

    def now(world):  # the robot's frame after the move
        return (np.asarray(world) - position) @ rotation

    robot = lt.OccupancyGrid(grid).move(turned)
    robot.integrate(now(points), now((0.0, 0.0, 0.0)), labels=boxes + 1)
    hit = lt.gaze_objects(robot, now(eyes), now(target) - now(eyes)).top
    assert hit is not None and hit.id == scene.index("object") + 1
    axis = (now(target) - now(eyes)) / np.linalg.norm(now(target) - now(eyes))
    np.testing.assert_allclose(hit.point, now(eyes) + hit.distance * axis)
    # The arrays read now are in the robot's frame too: the cell the answer
    # names carries its label, and the scan's points lie in occupied cells.
    assert robot.labels[hit.cell] == hit.id
    assert robot.probability[tuple(grid.cell_of(now(points[::97])).T)].mean() > 0.5


def test_depth_images_after_a_move_use_the_robot_frame():
    grid = lt.Grid(0.3, 10.0, 24, 120, 60)
    depth = np.full((48, 64), 2.0)
    intrinsics = (50.0, 50.0, 31.5, 23.5)
    moved = lt.OccupancyGrid(grid).move(yaw_pose(0.4, (0.04, 0.0, 0.03)))
    moved.integrate_depth(depth, intrinsics)
    still = lt.OccupancyGrid(grid).integrate_depth(depth, intrinsics)
    f, _, _ = f_score(moved.log_odds > 0, still.log_odds > 0)
    assert f >= 0.95
    assert moved.last_scan == still.last_scan


def test_the_gaze_memory_keeps_its_objects_across_moves():
    grid = lt.Grid(0.3, 10.0, 32, 180, 90)
    occupancy = _table_map(grid)
    scene, eyes, target = table_scene()
    memory = lt.GazeAccumulator(half_life=10.0)
    memory.add(lt.gaze_objects(occupancy, eyes, target - eyes), time=0.0)
    first = memory.top
    for step in range(1, 6):
        occupancy.move(yaw_pose(np.radians(7.0), (0.02, 0.0, 0.01)))
        pose = np.linalg.matrix_power(yaw_pose(np.radians(7.0), (0.02, 0.0, 0.01)), step)
        eyes_now, target_now = ((np.array([eyes, target]) - pose[:3, 3]) @ pose[:3, :3])
        memory.add(lt.gaze_objects(occupancy, eyes_now, target_now - eyes_now), time=step)
    assert first == scene.index("object") + 1
    assert memory.top == first


def test_objects_found_after_a_move_are_labelled_in_the_new_frame():
    grid = lt.Grid(0.3, 10.0, 32, 180, 90)
    occupancy = _table_map(grid)
    occupancy.labels = np.zeros(grid.shape, dtype=np.int32)
    occupancy.move(yaw_pose(0.3, (0.05, 0.0, 0.0)))
    found = lt.label_objects(occupancy)
    assert found > 0
    labelled = occupancy.labels > 0
    assert np.all(occupancy.log_odds[labelled] > 0)  # both resampled into one frame


@pytest.mark.parametrize("motion_value, match", [
    (np.diag([2.0, 2.0, 2.0, 1.0]), "orthonormal"),
    (np.diag([1.0, 1.0, -1.0, 1.0]), "determinant"),
    (np.full((4, 4), np.nan), "finite"),
    ((np.eye(3) + 2e-6, np.zeros(3)), "orthonormal"),
    (np.eye(3), r"shape \(4, 4\)"),
    ((np.eye(3), np.zeros(2)), r"shape \(3,\)"),
    (None, "None"),
    (np.array([[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 1, 1.0]]), "last row"),
])
def test_a_motion_that_is_not_rigid_is_refused_before_the_map_changes(motion_value, match):
    grid = lt.Grid(0.3, 10.0, 8, 36, 18)
    occupancy = lt.OccupancyGrid(grid).move(yaw_pose(0.1, (0.01, 0.0, 0.0)))
    held = occupancy._held()[0].copy(), occupancy._pose
    with pytest.raises(ValueError, match=match):
        occupancy.move(motion_value)
    assert occupancy._pose is held[1]
    np.testing.assert_array_equal(occupancy._held()[0], held[0])


def test_a_moved_map_saves_loads_and_pickles_its_pose(tmp_path):
    grid = lt.Grid(0.3, 10.0, 24, 120, 60)
    occupancy = _table_map(grid).move(yaw_pose(0.2, (0.03, 0.01, 0.0)))
    loaded = lt.OccupancyGrid.load(occupancy.save(tmp_path / "moved"))
    copied = pickle.loads(pickle.dumps(occupancy))
    for other in (loaded, copied):
        assert other._pose is not None
        other.move(yaw_pose(-0.2, (0.0, 0.0, 0.02)))
    occupancy.move(yaw_pose(-0.2, (0.0, 0.0, 0.02)))
    for other in (loaded, copied):
        np.testing.assert_array_equal(other.log_odds, occupancy.log_odds)
        np.testing.assert_array_equal(other.labels, occupancy.labels)


def test_many_small_moves_stay_a_rotation():
    rng = np.random.default_rng(3)
    pose = (np.eye(3), np.zeros(3))
    for _ in range(2000):
        pose = motion.compose(pose, (_random_rotation(rng, 0.01), rng.normal(size=3) * 1e-3))
    np.testing.assert_allclose(pose[0].T @ pose[0], np.eye(3), atol=1e-13)


def test_an_array_the_user_holds_is_never_reused():
    grid = lt.Grid(0.3, 10.0, 16, 72, 36)
    occupancy = _table_map(grid)
    held = occupancy.log_odds
    kept = held.copy()
    for _ in range(3):
        occupancy.move(yaw_pose(0.05, (0.01, 0.0, 0.0))).recentre()
    np.testing.assert_array_equal(held, kept)
