"""The main job: a depth image and a gaze in, the named object out; frames and units."""

import contextlib
import warnings

import numpy as np
import pytest

import logsph_trace as lt
from logsph_trace import demo
from logsph_trace.images import read_image
from logsph_trace.scene import table_scene, yaw_pose

GRID = lt.Grid(0.3, 8.0, 64, 360, 180)


@pytest.fixture(scope="module")
def frame():
    pytest.importorskip("skimage")
    from logsph_trace import datasets

    return datasets.motorcycle()


@pytest.fixture(scope="module")
def bvm(frame):
    return lt.OccupancyGrid(GRID).integrate_depth(frame.depth, frame.intrinsics,
                                                  labels=frame.labels)


def test_the_frame_carries_its_objects(frame):
    assert frame.names == {1: "motorcycle", 2: "bench", 3: "shelves"}
    assert frame.labels.shape == frame.depth.shape and frame.labels.dtype == np.int32
    bike = frame.labels == 1
    assert 90_000 < bike.sum() < 110_000
    depth = frame.depth[bike]
    assert depth.min() > 2.0 and depth.max() < 2.9  # the bike, not the wall behind it
    assert not np.any(frame.labels[~frame.valid])  # no object where there is no depth


def test_a_point_on_the_image_right_lands_at_negative_map_x(frame):
    # pose=None: the map's x is the camera's left. The front wheel is on the
    # image's right (columns 470-640), the rear wheel on its left.
    scan = lt.depth_to_points(frame.depth, frame.intrinsics)
    columns = scan.pixels[:, 1]
    right = scan.points[(columns > 600) & (frame.labels[tuple(scan.pixels.T)] == 1)]
    left = scan.points[(columns < 150) & (frame.labels[tuple(scan.pixels.T)] == 1)]
    assert np.all(right[:, 0] < 0) and np.all(left[:, 0] > 0)
    rows = scan.pixels[:, 0]
    assert np.all(scan.points[rows < 100][:, 1] > scan.points[rows > 400][:, 1].max())  # up
    assert np.all(scan.points[:, 2] > 0)  # forward


@pytest.mark.parametrize("what, pitch, yaw", demo.GAZES)
def test_each_demo_gaze_lands_where_it_says(bvm, frame, what, pitch, yaw):
    gaze = lt.gaze_from_pitch_yaw(np.radians(pitch), np.radians(yaw), demo.EYES)
    objects = lt.gaze_objects(bvm, gaze, names=frame.names)
    named = what.split()[-1]
    if named == "floor":
        assert len(objects) == 0 and objects.top is None and objects.unlabelled > 0.5
        return
    top = objects.top
    assert top.name == named and top.probability > 0.99
    assert top.id == {name: label for label, name in frame.names.items()}[named]
    assert bvm.labels[top.cell] == top.id
    assert 0.2 < top.distance < 1.5
    assert np.allclose(top.point, gaze.origin + top.distance * gaze.direction)
    assert top.n_cells == np.count_nonzero(bvm.labels == top.id)


def test_a_gaze_is_given_whole_or_as_origin_and_direction(bvm, frame):
    gaze = lt.gaze_from_pitch_yaw(np.radians(-52.0), np.radians(5.0), demo.EYES)
    whole = lt.gaze_objects(bvm, gaze)
    parts = lt.gaze_objects(bvm, gaze.origin, gaze.direction)
    assert whole.ids.tolist() == parts.ids.tolist()
    np.testing.assert_array_equal(whole.probabilities, parts.probabilities)
    assert whole.top.name is None  # no names given
    cells = lt.fixation_probability(bvm, gaze, half_angle=np.radians(5))
    np.testing.assert_array_equal(
        cells.values, lt.fixation_probability(bvm, *gaze, half_angle=np.radians(5)).values)
    first = lt.gaze_targets(bvm, gaze)
    assert bvm.labels[tuple(first.cells[0])] == 1
    with pytest.raises(TypeError, match="not both"):
        lt.gaze_objects(bvm, gaze, gaze.direction)
    with pytest.raises(TypeError, match="direction is missing"):
        lt.fixation_probability(bvm, gaze.origin)
    with pytest.raises(TypeError, match="names must be a mapping"):
        lt.gaze_objects(bvm, gaze, names=["motorcycle"])


def test_label_objects_keeps_a_detector_s_labels():
    scene, eyes, target = table_scene()
    points, labels, _ = scene.depth_points()
    grid = lt.Grid(0.3, 10.0, 64, 360, 180)
    occupancy = lt.OccupancyGrid(grid)
    detected = np.where(labels == scene.index("object"), 7, 0)  # only the object was detected
    occupancy.integrate(points, (0.0, 0.0, 0.0), labels=detected)
    before = occupancy.labels.copy()
    found = lt.label_objects(occupancy)
    assert found > 0
    kept = before > 0
    np.testing.assert_array_equal(occupancy.labels[kept], before[kept])
    new = (occupancy.labels > 0) & ~kept
    assert new.any() and occupancy.labels[new].min() == 8  # numbered after the largest
    assert occupancy.labels.max() == 7 + found
    assert lt.gaze_objects(occupancy, eyes, target - eyes).top.id == 7
    after = occupancy.labels.copy()
    assert lt.label_objects(occupancy) == 0  # nothing left unlabelled: nothing changes
    np.testing.assert_array_equal(occupancy.labels, after)
    count = lt.label_objects(occupancy, replace=True)
    assert set(np.unique(occupancy.labels).tolist()) == set(range(count + 1))  # from 1 again
    assert count < found + 1  # the object joined the table it stands on


def test_a_millimetre_depth_image_warns_and_the_right_scale_does_not(frame):
    millimetres = np.where(frame.valid, frame.depth * 1000, 0).astype(np.uint16)
    occupancy = lt.OccupancyGrid(GRID)
    with pytest.warns(lt.DepthUnitWarning, match="depth_scale=0.001") as record:
        occupancy.integrate_depth(millimetres, frame.intrinsics)
    assert record[0].filename == __file__  # the user's line, not the library's
    assert len(occupancy.occupied()) == 0  # what the warning is about
    assert any("none of the scan's" in str(w.message) for w in record)  # and the map says so
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        occupancy.integrate_depth(millimetres, frame.intrinsics, depth_scale=0.001)
        lt.depth_to_points(np.full((4, 4), 2.5, dtype=np.float32), frame.intrinsics)
        lt.depth_to_points(np.full((4, 4), 5, dtype=np.uint8), frame.intrinsics)  # metres
    assert len(occupancy.occupied()) > 3_000


def test_a_scan_that_lands_outside_the_map_warns():
    occupancy = lt.OccupancyGrid(lt.Grid(0.3, 8.0, 16, 36, 18))
    far = np.random.default_rng(3).normal(size=(50, 3)) * 100 + [0, 0, 500]
    with pytest.warns(lt.DepthUnitWarning, match="none of the scan's 50 points lies in the map"):
        occupancy.integrate(far, (0.0, 0.0, 0.0))
    with pytest.warns(lt.UnitWarning, match="reaches from 0.3 to 8"):
        occupancy.integrate([[0.0, 0.0, 0.1], [0.05, 0.0, 0.1]], (0.0, 0.0, 0.0))  # in the gap
    wedge = lt.OccupancyGrid(lt.Grid(0.3, 8.0, 16, 36, 18, theta_range=(0.0, 1.0)))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        occupancy.integrate(np.vstack([far, [[0.0, 0.0, 5.0]]]), (0.0, 0.0, 0.0))  # one lands
        occupancy.integrate([[0.0, 0.0, 5.0]], (0.1, 0.0, 0.0), max_range=1.0)  # beyond range
        wedge.integrate([[-2.0, 0.0, 2.0]], (0.0, 0.0, 0.0))  # outside the wedge's angles


@pytest.mark.parametrize("pitch, yaw", [(30.0, 200.0), (-52.0, 5.0), (0.0, 7.0), (2.0, 0.0)])
def test_pitch_and_yaw_in_degrees_warn(pitch, yaw):
    with pytest.warns(lt.AngleUnitWarning, match="np.radians") as record:
        lt.gaze_from_pitch_yaw(pitch, yaw, (0.0, 0.0, 1.0))
    assert record[0].filename == __file__


@pytest.mark.parametrize("pitch, yaw", [(0.0, 0.0), (-0.9, 2.5), (1.5, -3.1), (-0.2, 6.2)])
def test_pitch_and_yaw_in_radians_do_not_warn(pitch, yaw):
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        lt.gaze_from_pitch_yaw(pitch, yaw, (0.0, 0.0, 1.0))


def test_pitch_and_yaw_follow_l2cs_net():
    eyes = (0.3, -0.2, 2.0)
    into_camera = lt.gaze_from_pitch_yaw(0.0, 0.0, eyes)
    np.testing.assert_allclose(into_camera.direction, [0.0, 0.0, -1.0], atol=1e-15)
    up = lt.gaze_from_pitch_yaw(0.3, 0.0, eyes).direction
    assert up[1] > 0  # up in the camera is up in the map
    image_left = lt.gaze_from_pitch_yaw(0.0, 0.3, eyes).direction
    assert image_left[0] > 0  # the image's left is the map's +x
    np.testing.assert_allclose(into_camera.origin, [-0.3, 0.2, 2.0])


def test_images_read_npy_png_and_pfm(tmp_path):
    rng = np.random.default_rng(0)
    depth = rng.integers(0, 65535, size=(7, 5)).astype(np.uint16)
    np.save(tmp_path / "d.npy", depth)
    np.testing.assert_array_equal(read_image(tmp_path / "d.npy"), depth)
    pil = pytest.importorskip("PIL.Image")
    pil.fromarray(depth).save(tmp_path / "d.png")
    png = read_image(tmp_path / "d.png")
    assert png.dtype == np.uint16
    np.testing.assert_array_equal(png, depth)
    values = rng.random((7, 5)).astype(np.float32)
    for scale, order in ((-1.0, "<f4"), (1.0, ">f4")):
        with open(tmp_path / "d.pfm", "wb") as stream:
            stream.write(f"Pf\n5 7\n{scale}\n".encode())
            stream.write(values[::-1].astype(order).tobytes())  # bottom row first
        np.testing.assert_array_equal(read_image(tmp_path / "d.pfm"), values)
    with open(tmp_path / "short.pfm", "wb") as stream:
        stream.write(b"Pf\n5 7\n-1.0\n" + values.tobytes()[:40])
    with pytest.raises(ValueError, match="truncated"):
        read_image(tmp_path / "short.pfm")
    with open(tmp_path / "colour.pfm", "wb") as stream:
        stream.write(b"PF\n5 7\n-1.0\n")
    with pytest.raises(ValueError, match="colour PFM"):
        read_image(tmp_path / "colour.pfm")
    with pytest.raises(ValueError, match=r"\.npy, \.png or \.pfm"):
        read_image(tmp_path / "d.jpg")
    with pytest.raises(FileNotFoundError, match="no such depth file"):
        read_image(tmp_path / "missing.npy", "depth")
    np.save(tmp_path / "cube.npy", np.zeros((2, 2, 2)))
    with pytest.raises(ValueError, match="2-D image of numbers"):
        read_image(tmp_path / "cube.npy")


def test_the_view_is_one_self_contained_file(bvm, frame, tmp_path):
    pytest.importorskip("plotly")
    from logsph_trace.view import write_view

    gaze = lt.gaze_from_pitch_yaw(np.radians(-52.0), np.radians(5.0), demo.EYES)
    objects = lt.gaze_objects(bvm, gaze, names=frame.names)
    path = write_view(tmp_path / "view.html", bvm, gaze, objects, np.radians(5),
                      names=frame.names, axis_titles=demo.MAP_AXES)
    html = path.read_text()
    assert 1_000_000 < len(html) < 20_000_000  # plotly.js inlined
    tags = [tag.split(">")[0] for tag in html.split("<script")[1:]]
    assert tags and not [tag for tag in tags if "src" in tag]  # nothing fetched from anywhere
    assert "<link" not in html
    for name in ("motorcycle", "bench", "shelves", "eyes", "gaze cone", "motorcycle: 1.00",
                 "to the camera's left"):
        assert name in html, name
    bare = write_view(tmp_path / "bare.html", bvm).read_text()
    assert "gaze" not in bare.split("Plotly.newPlot(")[1]
    with pytest.raises(TypeError, match="gaze must be a Gaze"):
        write_view(tmp_path / "x.html", bvm, gaze=(demo.EYES, (0, 0, 1)))
    assert not (tmp_path / "x.html").exists()


@contextlib.contextmanager
def _compiles():
    """Collect the Python functions Numba compiles inside the block."""
    from numba.core import event

    compiled = []

    class Listener(event.Listener):
        def on_start(self, ev):
            compiled.append(getattr(ev.data.get("dispatcher"), "py_func", None))

        def on_end(self, ev):
            pass

    listener = Listener()
    event.register("numba:compile", listener)
    try:
        yield compiled
    finally:
        event.unregister("numba:compile", listener)


def test_after_warmup_the_main_job_compiles_nothing(frame):
    lt.warmup()
    with _compiles() as compiled:
        bvm = lt.OccupancyGrid(GRID).integrate_depth(frame.depth, frame.intrinsics,
                                                     labels=frame.labels)
        gaze = lt.gaze_from_pitch_yaw(np.radians(-52), np.radians(5), demo.EYES)
        assert lt.gaze_objects(bvm, gaze, names=frame.names).top.name == "motorcycle"
    assert not compiled, [getattr(f, "__qualname__", f) for f in compiled]


def test_after_warmup_a_map_that_moves_compiles_nothing(frame):
    lt.warmup()
    bvm = lt.OccupancyGrid(GRID).integrate_depth(frame.depth, frame.intrinsics,
                                                 labels=frame.labels)
    with _compiles() as compiled:
        for motion in (yaw_pose(2 * np.pi / GRID.n_theta, (0.0, 0.0, 0.0)),
                       yaw_pose(0.2, (0.0, 0.0, 0.0)), yaw_pose(-0.1, (0.03, 0.0, 0.01)),
                       yaw_pose(0.0, (0.2, 0.0, 0.0))):
            bvm.move(motion)
            bvm.integrate_depth(frame.depth, frame.intrinsics, labels=frame.labels)
            gaze = lt.gaze_from_pitch_yaw(np.radians(-52), np.radians(5), demo.EYES)
            lt.gaze_objects(bvm, gaze)
            bvm.log_odds  # noqa: B018 -- reading it resamples
    assert not compiled, [getattr(f, "__qualname__", f) for f in compiled]
