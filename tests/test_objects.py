"""Objects in the map: voted labels, connected components, the object a gaze names."""

from collections import deque

import numpy as np
import pytest

import logsph_trace as lt
from logsph_trace.scene import Box, Scene, table_scene

GRID = lt.Grid(0.3, 10.0, 64, 360, 180)


def _table_map(sensor=(0.0, 0.0, 0.0)):
    scene, eyes, target = table_scene()
    points, labels, _ = scene.depth_points(sensor=sensor)
    occupancy = lt.OccupancyGrid(GRID).integrate(points, sensor, labels=labels + 1)
    return scene, eyes, target, occupancy


@pytest.mark.parametrize("sensor", [(0.0, 0.0, 0.0), (0.06, 0.08, 0.0)])
def test_every_hit_cell_takes_the_label_of_its_points(sensor):
    scene, _, _, occupancy = _table_map(sensor)
    points, labels, _ = scene.depth_points(sensor=sensor)
    cells = GRID.cell_of(points)
    got = occupancy.labels[tuple(cells.T)]
    # A cell holding points of two boxes takes the majority; elsewhere the box's own.
    keys = np.ravel_multi_index(tuple(cells.T), GRID.shape)
    mixed = np.array([len(set(labels[keys == key])) > 1 for key in np.unique(keys)])
    assert np.mean(got == labels + 1) > 0.99
    assert mixed.mean() < 0.05
    occupied = occupancy.occupied(0.6)
    assert np.all(occupancy.labels[tuple(occupied.T)] > 0)


def test_votes_take_the_majority_and_ties_the_smaller_label():
    grid = lt.Grid(0.3, 10.0, 8, 12, 6)
    centre = grid.cell_centers([[5, 3, 2]])[0]
    other = grid.cell_centers([[6, 7, 4]])[0]
    points = np.array([centre, centre * 1.001, centre * 0.999, other, other * 1.001])
    occupancy = lt.OccupancyGrid(grid).integrate(points, (0, 0, 0), labels=[7, 5, 7, 9, 4])
    assert occupancy.labels[5, 3, 2] == 7 and occupancy.labels[6, 7, 4] == 4
    occupancy.integrate(points[:1], (0, 0, 0), labels=[3])  # a later scan re-votes its cells
    assert occupancy.labels[5, 3, 2] == 3 and occupancy.labels[6, 7, 4] == 4


def _majority(grid, cells, labels):
    """Each hit cell's most frequent label, ties to the smaller (a dict per cell)."""
    votes = {}
    for cell, label in zip(map(tuple, cells.tolist()), labels.tolist()):
        if cell[0] >= 0:
            votes.setdefault(cell, {}).setdefault(label, 0)
            votes[cell][label] += 1
    expected = np.zeros(grid.shape, dtype=np.int64)
    for cell, counts in votes.items():
        expected[cell] = min(counts, key=lambda label: (-counts[label], label))
    return expected


@pytest.mark.parametrize("sensor", [(0.0, 0.0, 0.0), (0.0731, -0.0412, 0.0519)])
@pytest.mark.parametrize("one_key", [True, False])
def test_votes_match_a_per_cell_count(sensor, one_key, monkeypatch):
    # Runs of equal votes (as neighbouring pixels give), interleaved runs for one
    # cell, and labels up to the largest a map holds.
    if not one_key:
        monkeypatch.setattr(lt.occupancy, "SORT_KEY_MAX", 0)  # the two-key sort
    grid = lt.Grid(0.3, 10.0, 9, 16, 8)
    rng = np.random.default_rng(5)
    centres = grid.cell_centers(np.stack([rng.integers(0, n, 40) for n in grid.shape], axis=1))
    which = np.repeat(rng.integers(0, 40, 300), rng.integers(1, 6, 300))
    points = centres[which] * rng.uniform(0.999, 1.001, (which.size, 1))
    choices = np.array([1, 2, 3, 2**31 - 1])
    labels = choices[np.repeat(rng.integers(0, 4, which.size // 3 + 1), 3)[:which.size]]
    occupancy = lt.OccupancyGrid(grid).integrate(points, sensor, labels=labels)
    assert np.array_equal(occupancy.labels, _majority(grid, grid.cell_of(points), labels))


def test_depth_labels_are_the_points_labels_of_their_pixels():
    rng = np.random.default_rng(11)
    depth = rng.uniform(0.5, 8.0, (12, 16))
    depth[rng.random(depth.shape) < 0.2] = 0.0
    image = rng.integers(0, 4, depth.shape)
    intrinsics = (14.2, 13.9, 7.7, 5.6)
    pose = (np.diag([-1.0, -1.0, 1.0]), [0.05, -0.03, 0.02])
    by_depth = lt.OccupancyGrid(GRID).integrate_depth(depth, intrinsics, pose, labels=image)
    scan = lt.depth_to_points(depth, intrinsics, pose)
    by_points = lt.OccupancyGrid(GRID).integrate(
        scan.points, scan.origin, labels=image[scan.pixels[:, 0], scan.pixels[:, 1]])
    assert np.array_equal(by_depth.labels, by_points.labels) and by_depth.labels.any()


def test_labels_are_saved_loaded_and_checked(tmp_path):
    _, _, _, occupancy = _table_map()
    loaded = lt.OccupancyGrid.load(occupancy.save(tmp_path / "map"))
    assert np.array_equal(loaded.labels, occupancy.labels)
    with pytest.raises(ValueError, match="labels must have shape"):
        occupancy.labels = np.zeros((2, 2), dtype=int)
    with pytest.raises(ValueError, match=">= 0"):
        occupancy.integrate([[1.0, 0.0, 0.0]], (0, 0, 0), labels=[-1])
    with pytest.raises(ValueError, match="integers"):
        occupancy.integrate([[1.0, 0.0, 0.0]], (0, 0, 0), labels=[1.5])
    with pytest.raises(ValueError, match=r"labels must have shape \(2,\)"):
        occupancy.integrate([[1.0, 0.0, 0.0], [2.0, 0.0, 0.0]], (0, 0, 0), labels=[1])


def _components(occupied, wrap):
    """Breadth-first oracle: 26-neighbourhood, theta wrapping; numbered in C order."""
    labels = np.zeros(occupied.shape, dtype=int)
    count = 0
    n_theta = occupied.shape[1]
    for start in zip(*np.nonzero(occupied)):
        if labels[start]:
            continue
        count += 1
        labels[start] = count
        queue = deque([start])
        while queue:
            i, j, k = queue.popleft()
            for di in (-1, 0, 1):
                for dj in (-1, 0, 1):
                    for dk in (-1, 0, 1):
                        ni, nj, nk = i + di, j + dj, k + dk
                        if wrap:
                            nj %= n_theta
                        inside = (0 <= ni < occupied.shape[0] and 0 <= nj < n_theta
                                  and 0 <= nk < occupied.shape[2])
                        if inside and occupied[ni, nj, nk] and not labels[ni, nj, nk]:
                            labels[ni, nj, nk] = count
                            queue.append((ni, nj, nk))
    return labels, count


@pytest.mark.parametrize("full", [True, False])
def test_label_objects_matches_a_breadth_first_oracle(full):
    theta = (-np.pi, np.pi) if full else (-2.0, 2.5)
    grid = lt.Grid(0.3, 10.0, 7, 9, 6, theta_range=theta)
    rng = np.random.default_rng(12)
    for density in (0.05, 0.15, 0.3):
        occupied = rng.random(grid.shape) < density
        occupied[:, 0, 2] = occupied[:, -1, 3] = True  # a diagonal step across the seam
        occupancy = lt.OccupancyGrid(grid, log_odds=np.where(occupied, 2.0, -1.0))
        count = lt.label_objects(occupancy)
        want, want_count = _components(occupied, wrap=full)
        assert count == want_count and np.array_equal(occupancy.labels, want)


def test_an_object_across_the_seam_is_one_object():
    grid = lt.Grid(0.3, 10.0, 6, 12, 6)
    log_odds = np.full(grid.shape, -1.0, dtype=np.float32)
    log_odds[2, 0, 3] = log_odds[2, 11, 3] = log_odds[4, 5, 1] = 2.0
    occupancy = lt.OccupancyGrid(grid, log_odds=log_odds)
    assert lt.label_objects(occupancy) == 2
    assert occupancy.labels[2, 0, 3] == occupancy.labels[2, 11, 3] != occupancy.labels[4, 5, 1]


def test_the_gaze_names_the_object_on_the_table():
    _, eyes, target, occupancy = _table_map()
    objects = lt.gaze_objects(occupancy, eyes, target - eyes)
    top = objects.top
    assert top.id == 2 and top.name is None  # the object (box 1, label 2), not the table
    assert objects.probabilities[0] > objects.probabilities[1:].sum()
    assert np.all(np.diff(objects.probabilities) <= 0)
    assert occupancy.labels[top.cell] == 2
    assert 0.0 < top.distance < np.linalg.norm(target - eyes) + 0.2
    axis = (target - eyes) / np.linalg.norm(target - eyes)
    np.testing.assert_allclose(top.point, eyes + top.distance * axis, rtol=1e-12)
    cells = np.argwhere(occupancy.labels == 2)
    assert top.n_cells == len(cells)
    np.testing.assert_allclose(top.centroid, GRID.cell_centers(cells).mean(axis=0), rtol=1e-12,
                               atol=1e-12)  # metres: x is 0 up to rounding


def test_a_ranking_without_centroids_is_the_same_ranking():
    # What a replay asks for: the same hits, without the pass over every label.
    _, eyes, target, occupancy = _table_map()
    occupancy.move((np.eye(3), [0.021, -0.013, 0.008]))
    whole = lt.gaze_objects(occupancy, eyes, target - eyes)
    lean = lt.gaze._ranked(occupancy, eyes, target - eyes, lt.gaze.DEFAULT_HALF_ANGLE, None,
                           None, {}, lt.gaze._fixation_options(), centroids=False)
    assert len(whole) == len(lean) > 1
    for full, bare in zip(whole, lean):
        assert full._replace(centroid=None, n_cells=None, point=None) == bare._replace(point=None)
        assert np.array_equal(full.point, bare.point)


def test_an_occluded_object_ranks_below_its_occluder():
    # Two boxes in line with the gaze, both in the map (the back one was seen
    # before the front one arrived): the gaze stops at the front one.
    back = Box("back", (-0.6, -0.6, 3.0), (0.6, 0.6, 3.1))
    occupancy = lt.OccupancyGrid(GRID)
    for scene, offset in ((Scene([back]), 2), (Scene([Box("front", (-0.3, -0.3, 1.8),
                                                          (0.3, 0.3, 1.9)), back]), 1)):
        points, labels, _ = scene.depth_points(sensor=(0.0, 0.0, 0.0))
        for _ in range(3):
            occupancy.integrate(points, (0.0, 0.0, 0.0), labels=labels + offset)
    eyes = np.array([0.4, 0.1, 0.4])
    behind = np.array([0.0, 0.0, 3.0])
    objects = lt.gaze_objects(occupancy, eyes, behind - eyes, half_angle=np.radians(2))
    assert list(objects.ids[:2]) == [1, 2]
    assert objects.probabilities[0] > 2 * objects.probabilities[1]


def test_found_labels_are_an_ordinary_array(tmp_path):
    # label_objects' labels come from fresh pages of the system: the user
    # writes, copies, pickles and saves them as any array.
    import pickle

    points, _, _ = Scene([Box("a", (-0.8, -0.2, 2.0), (-0.4, 0.2, 2.1))]).depth_points()
    occupancy = lt.OccupancyGrid(GRID).integrate(points, (0.0, 0.0, 0.0))
    assert lt.label_objects(occupancy, replace=True) == 1
    labels = occupancy.labels
    assert labels.dtype == np.int32 and labels.shape == GRID.shape and labels.flags.writeable
    assert np.count_nonzero(labels) == len(occupancy.occupied(0.6)) > 0
    labels[0, 0, 0] = 7
    assert occupancy.labels[0, 0, 0] == 7
    np.testing.assert_array_equal(pickle.loads(pickle.dumps(occupancy)).labels, labels)
    loaded = lt.OccupancyGrid.load(occupancy.save(tmp_path / "map"))
    np.testing.assert_array_equal(loaded.labels, labels)
    del occupancy, labels  # the pages go back to the system with the last reference


def test_components_name_the_object_when_no_detector_did():
    scene = Scene([Box("a", (-0.8, -0.2, 2.0), (-0.4, 0.2, 2.1)),
                   Box("b", (0.4, -0.2, 2.0), (0.8, 0.2, 2.1)),
                   Box("wall", (-3.0, -1.5, 3.5), (3.0, 1.5, 3.6))])
    points, _, _ = scene.depth_points()
    occupancy = lt.OccupancyGrid(GRID).integrate(points, (0.0, 0.0, 0.0))
    assert lt.label_objects(occupancy) == 3
    eyes = np.array([0.0, 0.3, 0.5])
    for centre in ((-0.6, 0.0, 2.0), (0.6, 0.0, 2.0)):
        objects = lt.gaze_objects(occupancy, eyes, np.array(centre) - eyes)
        named = occupancy.labels[tuple(GRID.cell_of(np.array(centre) + [0, 0, 0.05]))]
        assert objects.top.id == named != 0


def test_a_held_look_beats_a_glance():
    def seen(label, probability):
        hit = lt.ObjectHit(label, None, probability, 1.0, np.zeros(3), (0, 0, 0), np.zeros(3), 1)
        return lt.GazeObjects((hit,), 0.0)

    glance, look = seen(1, 0.9), seen(2, 0.4)
    memory = lt.GazeAccumulator(half_life=0.5).add(glance, time=0.0)
    assert memory.top == 1
    for time in (0.1, 0.2, 0.3):
        memory.add(look, time=time)
    assert memory.top == 2
    labels, scores = memory.scores()
    assert list(labels) == [2, 1]
    assert scores[1] == pytest.approx(0.9 * 0.5 ** (0.3 / 0.5), rel=1e-12)
    stepped = lt.GazeAccumulator(half_life=2.0).add(glance).add(look)  # one unit a gaze
    assert dict(zip(*stepped.scores()))[1] == pytest.approx(0.9 / np.sqrt(2.0), rel=1e-12)
    with pytest.raises(ValueError, match="time must not go back"):
        memory.add(look, time=0.1)
    with pytest.raises(ValueError, match="half_life must be positive"):
        lt.GazeAccumulator(half_life=0.0)
    with pytest.raises(ValueError, match="objects must be GazeObjects"):
        memory.add([1, 2])


def test_gazes_from_estimators():
    # Zero pitch and yaw look into the camera; the vector form agrees with the
    # angle form for random angles; a pose moves both.
    straight = lt.gaze_from_pitch_yaw(0.0, 0.0, (0.1, -0.2, 1.5))
    assert np.allclose(straight.origin, [-0.1, 0.2, 1.5]) and np.allclose(
        straight.direction, [0.0, 0.0, -1.0])
    rng = np.random.default_rng(13)
    for _ in range(20):
        pitch, yaw = rng.uniform(-0.6, 0.6, 2)
        eyes = rng.normal(size=3)
        rotation = np.linalg.qr(rng.normal(size=(3, 3)))[0]
        rotation *= np.sign(np.linalg.det(rotation))
        pose = (rotation, rng.normal(size=3))
        gaze = lt.gaze_from_pitch_yaw(pitch, yaw, eyes, pose)
        vector = (-np.cos(pitch) * np.sin(yaw), -np.sin(pitch), -np.cos(pitch) * np.cos(yaw))
        same = lt.gaze_from_vector(np.array(vector) * 3.0, eyes, pose)
        assert np.allclose(gaze.direction, same.direction, atol=1e-15)
        assert np.allclose(gaze.origin, rotation @ eyes + pose[1])
        camera = rotation.T @ gaze.direction
        assert np.isclose(np.arcsin(-camera[1]), pitch) and np.isclose(
            np.arctan2(-camera[0], -camera[2]), yaw)
    origin, direction = lt.gaze_from_vector((0.0, -1.0, 0.0), (0.0, 0.0, 2.0))
    assert np.allclose(direction, [0.0, 1.0, 0.0])  # up in the image is up in the map
    with pytest.raises(ValueError, match="vector must be non-zero"):
        lt.gaze_from_vector((0.0, 0.0, 0.0), (0.0, 0.0, 1.0))


def _floor_scene():
    # A box standing on a floor: touching, they are one connected group.
    floor = Box("floor", (-4.0, -1.25, 0.5), (4.0, -1.2, 6.0))
    box = Box("box", (-0.4, -1.2, 2.2), (0.4, -0.4, 2.6))
    points, labels, _ = Scene([floor, box]).depth_points(forward=(0.0, -0.3, 1.0))
    return points, labels


def test_leaving_out_the_floor_separates_what_stands_on_it():
    points, labels = _floor_scene()
    occupancy = lt.OccupancyGrid(GRID).integrate(points, (0.0, 0.0, 0.0))
    assert lt.label_objects(occupancy) == 1
    floor = lt.fit_plane(points, tolerance=0.01)
    assert np.allclose(floor.normal, [0.0, 1.0, 0.0], atol=1e-4)  # up, to the sensor
    assert np.isclose(floor.offset, 1.2, atol=1e-4)
    assert floor.inliers[labels == 0].all() and not floor.inliers[points[:, 1] > -1.18].any()
    exclude = GRID.count_points(points[floor.inliers]) > 0
    assert lt.label_objects(occupancy, exclude=exclude, replace=True) == 1
    box = occupancy.labels[tuple(GRID.cell_of(points[labels == 1]).T)]
    on_floor = occupancy.labels[tuple(GRID.cell_of(points[labels == 0]).T)]
    assert np.mean(box == 1) > 0.9 and not np.any(on_floor)
    assert not np.any(occupancy.labels[exclude])
    eyes = np.array([1.0, 0.3, 0.5])
    assert lt.gaze_objects(occupancy, eyes, np.array([0.0, -0.8, 2.3]) - eyes).top.id == 1


def test_fit_plane_finds_a_noisy_plane_among_outliers():
    rng = np.random.default_rng(5)
    normal = rng.normal(size=3)
    normal /= np.linalg.norm(normal)
    basis = np.linalg.svd(normal[None, :])[2][1:]
    on = rng.uniform(-3, 3, (30_000, 2)) @ basis - 1.7 * normal  # offset 1.7: origin above
    on += rng.normal(scale=0.002, size=on.shape) * normal
    off = rng.uniform(-3, 3, (20_000, 3))
    points = np.concatenate([on, off])
    plane = lt.fit_plane(points, tolerance=0.01)
    assert abs(plane.normal @ normal) > 1 - 1e-6 and plane.normal @ normal > 0
    assert np.isclose(plane.offset, 1.7, atol=1e-3)
    assert plane.inliers[:30_000].mean() > 0.99
    far = np.abs(off @ plane.normal + plane.offset) > 0.011
    assert not plane.inliers[30_000:][far].any()
    assert np.allclose(plane.distance(points), points @ plane.normal + plane.offset)
    again = lt.fit_plane(points, tolerance=0.01)  # the same seed, the same plane
    assert np.array_equal(again.normal, plane.normal) and again.offset == plane.offset


def test_fit_plane_and_label_objects_reject_bad_input():
    with pytest.raises(ValueError, match="at least 3 points"):
        lt.fit_plane(np.zeros((2, 3)))
    with pytest.raises(ValueError, match="span no plane"):
        lt.fit_plane(np.outer(np.arange(10.0), [1.0, 2.0, 3.0]))
    with pytest.raises(ValueError, match="span no plane"):  # a line, up to rounding
        lt.fit_plane(np.outer(np.linspace(0.1, 7.3, 50), [0.3, np.pi, 1 / 3]) + [0.7, 0.1, 0.2])
    with pytest.raises(ValueError, match="tolerance must be a positive number"):
        lt.fit_plane(np.eye(3), tolerance=0.0)
    with pytest.raises(ValueError, match="iterations must be a positive integer"):
        lt.fit_plane(np.eye(3), iterations=0)
    with pytest.raises(ValueError, match="points must be finite"):
        lt.fit_plane([[0.0, 0.0, np.nan], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    occupancy = lt.OccupancyGrid(GRID)
    with pytest.raises(ValueError, match="exclude must be a boolean array of shape"):
        lt.label_objects(occupancy, exclude=np.zeros(GRID.shape, dtype=int))
    with pytest.raises(ValueError, match="exclude must be a boolean array of shape"):
        lt.label_objects(occupancy, exclude=np.zeros((2, 2), dtype=bool))
    with pytest.raises(ValueError, match="min_cells must be a positive integer"):
        lt.label_objects(occupancy, min_cells=0)


def test_small_components_are_dropped_and_the_rest_renumbered():
    grid = lt.Grid(0.3, 10.0, 7, 9, 6, theta_range=(-2.0, 2.5))
    rng = np.random.default_rng(13)
    occupied = rng.random(grid.shape) < 0.15
    occupancy = lt.OccupancyGrid(grid, log_odds=np.where(occupied, 2.0, -1.0))
    want, want_count = _components(occupied, wrap=False)
    sizes = np.bincount(want.ravel())[1:]
    assert sizes.min() < 3 <= sizes.max()
    count = lt.label_objects(occupancy, min_cells=3)
    assert count == np.count_nonzero(sizes >= 3)
    # The kept components keep their cells and order; the small ones are 0.
    kept = np.flatnonzero(sizes >= 3) + 1
    renumber = np.zeros(want_count + 1, dtype=int)
    renumber[kept] = np.arange(1, count + 1)
    assert np.array_equal(occupancy.labels, renumber[want])


def test_count_points_counts_each_cells_points():
    rng = np.random.default_rng(14)
    points = rng.uniform(-12, 12, (5_000, 3))
    counts = GRID.count_points(points)
    cells = GRID.cell_of(points)
    inside = cells[:, 0] >= 0
    assert counts.shape == GRID.shape and counts.sum() == inside.sum() < len(points)
    for cell in cells[inside][:50]:
        assert counts[tuple(cell)] == np.all(cells == cell, axis=1).sum()
    assert GRID.count_points(points[0]).sum() == inside[0]


def test_gaze_objects_checks_its_map():
    with pytest.raises(ValueError, match="occupancy must be an OccupancyGrid"):
        lt.gaze_objects(GRID, (0, 0, 0), (0, 0, 1))
    with pytest.raises(ValueError, match="occupancy must be an OccupancyGrid"):
        lt.label_objects(None)


def test_gazes_at_four_parts_of_the_real_motorcycle():
    # Middlebury 2014 Motorcycle, parts boxed by hand in the image as a 2-D
    # detector would box them; an eye 1.5 m to the camera's right looks at
    # the middle of each part through a 5-degree cone: the part comes first.
    pytest.importorskip("skimage")
    from logsph_trace import datasets

    frame = datasets.motorcycle()
    grid = lt.Grid(0.3, 8.0, 64, 360, 180)
    labels = datasets.box_labels(frame.depth.shape, datasets.MOTORCYCLE_PARTS)
    occupancy = lt.OccupancyGrid(grid).integrate_depth(frame.depth, frame.intrinsics,
                                                       labels=labels)
    scan = lt.depth_to_points(frame.depth, frame.intrinsics)
    of_points = labels[scan.pixels[:, 0], scan.pixels[:, 1]]
    eyes = np.array([-1.5, 0.3, 0.5])
    for label in datasets.MOTORCYCLE_PARTS:
        target = np.median(scan.points[of_points == label], axis=0)
        assert lt.gaze_objects(occupancy, eyes, target - eyes).top.id == label


def test_without_boxes_the_motorcycle_is_its_own_object():
    # No detector: the floor (fit_plane) and cells with fewer than 3 points
    # (pixels on silhouettes, between the bike and the shelves behind it)
    # are left out; the bike is then one object apart from the background,
    # and the gazes at its four parts all name it.
    pytest.importorskip("skimage")
    from logsph_trace import datasets

    frame = datasets.motorcycle()
    grid = lt.Grid(0.3, 8.0, 64, 360, 180)
    occupancy = lt.OccupancyGrid(grid).integrate_depth(frame.depth, frame.intrinsics)
    scan = lt.depth_to_points(frame.depth, frame.intrinsics)
    assert lt.label_objects(occupancy) < 20  # without: one group holds nearly everything
    everything = np.bincount(occupancy.labels[tuple(grid.cell_of(scan.points).T)])
    assert everything.max() > 0.99 * len(scan.points)
    floor = lt.fit_plane(scan.points, tolerance=0.03)
    assert floor.normal[1] > 0.95 and 1.0 < floor.offset < 1.2  # ~1.1 m below the camera
    exclude = grid.count_points(scan.points[floor.inliers]) > 0
    exclude |= grid.count_points(scan.points) < 3
    lt.label_objects(occupancy, exclude=exclude, replace=True)
    labels = occupancy.labels[tuple(grid.cell_of(scan.points).T)]
    parts = datasets.box_labels(frame.depth.shape, datasets.MOTORCYCLE_PARTS)
    of_points = parts[scan.pixels[:, 0], scan.pixels[:, 1]]
    distance = np.linalg.norm(scan.points, axis=1)
    on_bike = (of_points > 0) & (distance < 2.8)  # the boxes also hold the wall behind
    bike = np.bincount(labels[on_bike]).argmax()
    assert bike > 0 and np.mean(labels[on_bike] == bike) > 0.85
    assert np.mean(labels[distance > 3.3] == bike) < 1e-3  # shelves, bench and wall apart
    eyes = np.array([-1.5, 0.3, 0.5])
    for label in datasets.MOTORCYCLE_PARTS:
        target = np.median(scan.points[of_points == label], axis=0)
        assert lt.gaze_objects(occupancy, eyes, target - eyes).top.id == bike
