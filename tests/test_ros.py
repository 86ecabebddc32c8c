"""Replaying ROS 2 bags (``logsph_trace.ros``, ``logsph-trace replay``) on bags rosbags writes."""

import json

import numpy as np
import pytest

pytest.importorskip("rosbags")
pytest.importorskip("scipy")

import logsph_trace as lt  # noqa: E402
from logsph_trace import cli  # noqa: E402
from logsph_trace.ros import BagReplay, TransformTree  # noqa: E402
from logsph_trace.ros_scene import (  # noqa: E402 -- after the skips
    MSG,
    PEOPLE,
    SCENE_FROM_ODOM,
    Recording,
    as_recorded,
    base_pose,
    camera_info,
    camera_pose,
    depth_pixels,
    image,
    look_at,
    transform,
    walking_robot,
)

GRID = lt.Grid(0.3, 8.0, 32, 180, 90)
# Where a gaze first reaches an object's cells lies within about a cell of the
# object: this grid's cells are 17 cm deep 1.7 m from the robot.
NEAR = 0.25
TOPICS = {"depth": "/camera/depth", "camera_info": "/camera/camera_info",
          "base_frame": "base_link"}


def _replay(path, **options):
    replay = BagReplay(path, **{**TOPICS, "grid": GRID, **options})
    return list(replay), replay.summary


def _top_events(events):
    """{(stamp, person): the first (most probable) event}."""
    top = {}
    for event in events:
        top.setdefault((event.stamp, event.person), event)
    return top


def _distance_to_box(scene, name, point_odom):
    index = scene.index(name)
    point = SCENE_FROM_ODOM @ point_odom
    nearest = np.clip(point, scene.low[index], scene.high[index])
    return float(np.linalg.norm(point - nearest))


@pytest.mark.parametrize("storage", ["mcap", "sqlite3"])
@pytest.mark.parametrize("encoding", ["16UC1", "32FC1"])
def test_each_gaze_names_the_object_it_is_aimed_at(tmp_path, storage, encoding):
    recording, scene = walking_robot(encoding=encoding)
    bag = recording.write(tmp_path / "walk", storage)
    events, summary = _replay(bag, labels="/camera/labels")
    assert summary.frames == 9 and summary.gazes == 18 and not summary.skipped
    assert summary.truncated is None
    top = _top_events(events)
    for (stamp, person), event in top.items():
        target = scene.index(PEOPLE[person][1]) + 1
        assert event.frame_id == "base_link"
        # Bob looks at the shelf, which the robot sees only once it has turned.
        assert event.object in (target, 0), event
        assert event.object == target or (person == "bob" and stamp < 1.5), event
        if event.object:  # the point is at the box, in the base frame at the gaze's stamp
            assert _distance_to_box(scene, PEOPLE[person][1], _in_odom(stamp, event)) < NEAR


def _in_odom(stamp, event):
    """The event's point in odom: the base frame at its stamp (walking_robot's pose)."""
    pose = base_pose(min((stamp - 1.0) * 10.0, 8.0), 8)
    return pose[:3, :3] @ np.asarray(event.point) + pose[:3, 3]


@pytest.mark.parametrize("storage", ["mcap", "sqlite3"])
def test_without_a_label_topic_the_map_finds_the_objects(tmp_path, storage):
    recording, scene = walking_robot(labels=False)
    events, summary = _replay(recording.write(tmp_path / "walk", storage))
    assert summary.gazes == 18
    top = _top_events(events)
    for (stamp, person), event in top.items():
        if person == "bob" and stamp < 1.5:
            continue  # the shelf is not in view yet
        assert event.object > 0
        assert _distance_to_box(scene, PEOPLE[person][1], _in_odom(stamp, event)) < NEAR
    # each person's object keeps its id from gaze to gaze
    for person in PEOPLE:
        ids = {event.object for (stamp, who), event in top.items()
               if who == person and event.object}
        assert len(ids) == 1, (person, ids)


def _motorcycle_bag(path, encoding):
    from logsph_trace import datasets

    frame = datasets.motorcycle()
    recording = Recording()
    recording.add(0.0, "/tf_static", MSG["tf2_msgs/msg/TFMessage"](
        transforms=[transform(0.0, "base_link", "camera", camera_pose())]))
    recording.add(1.0, "/camera/camera_info",
                  camera_info(1.0, "camera", frame.depth.shape, frame.intrinsics))
    recording.add(1.0, "/camera/depth",
                  image(1.0, "camera", depth_pixels(frame.depth, encoding), encoding))
    recording.add(1.0, "/camera/labels", image(1.0, "camera", frame.labels, "32SC1"))
    # The README's gaze, in the camera's optical frame, as a frame on /tf.
    gaze = lt.gaze_from_pitch_yaw(np.radians(-52), np.radians(5), eyes=[0.2, -0.75, 3.0])
    optical = np.diag([-1.0, -1.0, 1.0])  # the map's frame (pose=None) to OpenCV's
    eyes, aim = optical @ gaze.origin, optical @ gaze.direction
    base_from_gaze = camera_pose() @ look_at(eyes, eyes + aim)
    recording.add(1.05, "/tf", MSG["tf2_msgs/msg/TFMessage"](
        transforms=[transform(1.05, "base_link", "gaze_7", base_from_gaze)]))
    return recording.write(path, "mcap"), frame


@pytest.mark.parametrize("encoding", ["16UC1", "32FC1"])
def test_the_motorcycle_frame_from_a_bag(tmp_path, encoding):
    pytest.importorskip("skimage")
    bag, frame = _motorcycle_bag(tmp_path / "motorcycle", encoding)
    events, summary = _replay(bag, labels="/camera/labels", grid=lt.Grid(0.3, 8.0, 64, 360, 180))
    assert summary.frames == 1 and summary.gazes == 1 and not summary.skipped
    invalid = ~np.isfinite(frame.depth) | (frame.depth <= 0)
    assert summary.invalid_pixels == np.count_nonzero(invalid)
    assert events[0].person == "7"
    assert frame.names[events[0].object] == "motorcycle"
    assert events[0].probability > 0.9


def _write_without(recording, path, drop):
    kept = Recording([m for m in recording.messages if not drop(*m)])
    return kept.write(path)


def test_a_missing_topic_names_the_topics_present(tmp_path):
    recording, _ = walking_robot(steps=2)
    bag = recording.write(tmp_path / "walk")
    with pytest.raises(ValueError, match=r"no topic '/depth'.*its topics: .*/camera/depth "
                                         r"\(sensor_msgs/msg/Image\)"):
        list(BagReplay(bag, "/depth", "/camera/camera_info", "base_link"))


def test_missing_and_stale_transforms_are_skipped_and_counted(tmp_path):
    recording, _ = walking_robot(steps=8)

    def drop(seconds, topic, message):  # odometry stops between 1.25 s and 1.85 s
        return (topic == "/tf" and message.transforms[0].child_frame_id == "base_link"
                and 1.25 < seconds < 1.85)

    events, summary = _replay(_write_without(recording, tmp_path / "gap", drop),
                              labels="/camera/labels", max_gap=0.3)
    # frames at 1.3 .. 1.8 s and their gazes fall in a 0.6 s gap: stale, not guessed
    assert summary.skipped["depth frames without a transform"] == 6
    assert summary.skipped["gazes without a transform"] >= 10
    assert summary.frames == 3
    assert all(not (1.25 < event.stamp < 1.85) for event in events)


def test_depth_stamps_out_of_order_are_put_in_order(tmp_path):
    recording, _ = walking_robot(steps=6)
    ordered = _replay(recording.write(tmp_path / "ordered"), labels="/camera/labels")
    messages = recording.messages
    depth = [i for i, m in enumerate(messages) if m[1] == "/camera/depth"]
    for a, b in zip(depth[::2], depth[1::2]):  # swap neighbouring frames' places in the bag
        messages[a], messages[b] = messages[b], messages[a]
    shuffled = _replay(Recording(messages).write(tmp_path / "shuffled"),
                       labels="/camera/labels")
    assert shuffled[1].frames == ordered[1].frames == 7
    assert [e.as_dict() for e in shuffled[0]] == [e.as_dict() for e in ordered[0]]


def test_an_unknown_encoding_is_an_error_naming_it(tmp_path):
    recording, _ = walking_robot(steps=1)
    messages = [(s, t, image(s, "camera", np.zeros((4, 4, 3), np.uint8).reshape(4, 12), "rgb8")
                 if t == "/camera/depth" else m) for s, t, m in recording.messages]
    bag = Recording(messages).write(tmp_path / "rgb")
    with pytest.raises(ValueError, match="unknown image encoding 'rgb8'"):
        _replay(bag)


def _cut(bag, suffix, keep=2 / 3):
    storage = next(bag.glob(f"*.{suffix}"))
    data = storage.read_bytes()
    storage.write_bytes(data[:int(len(data) * keep)])


def test_a_truncated_bag_gives_the_events_so_far_and_exit_code_1(tmp_path, capsys):
    recording, _ = walking_robot(steps=8, shape=(60, 80))
    bag = recording.write(tmp_path / "walk", "mcap")
    whole, _ = _replay(bag, labels="/camera/labels")
    as_recorded(bag)  # the recorder's layout: what a message is comes before it
    _cut(bag, "mcap")
    events, summary = _replay(bag, labels="/camera/labels")
    assert summary.truncated
    assert 0 < len(events) < len(whole)
    assert [e.as_dict() for e in events] == [e.as_dict() for e in whole[:len(events)]]
    out = tmp_path / "events.jsonl"
    code = cli.main(["replay", str(bag), "--depth", "/camera/depth", "--camera-info",
                     "/camera/camera_info", "--base-frame", "base_link", "--labels",
                     "/camera/labels", "--grid", "0.3,8,32,180,90", "--out", str(out)])
    assert code == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert "ends early" in err[-1] and "Traceback" not in "".join(err)
    assert len(out.read_text().splitlines()) == len(events)


def test_a_damaged_sqlite3_bag_is_one_clear_error(tmp_path):
    recording, _ = walking_robot(steps=2, shape=(60, 80))
    bag = recording.write(tmp_path / "walk", "sqlite3")
    _cut(bag, "db3")
    with pytest.raises(ValueError, match="cannot be read.*malformed"):
        _replay(bag)


def test_the_command_line_writes_json_lines(tmp_path, capsys):
    recording, _ = walking_robot(steps=4)
    bag = recording.write(tmp_path / "walk", "sqlite3")
    out = tmp_path / "events.jsonl"
    code = cli.main(["replay", str(bag), "--depth", "/camera/depth", "--camera-info",
                     "/camera/camera_info", "--base-frame", "base_link", "--labels",
                     "/camera/labels", "--gaze-frames", "gaze_*", "--half-angle", "4",
                     "--grid", "0.3,8,32,180,90", "--out", str(out)])
    assert code == 0
    rows = [json.loads(line) for line in out.read_text().splitlines()]
    assert {"stamp", "person", "frame_id", "object", "probability", "point",
            "distance"} <= set(rows[0])
    assert {row["person"] for row in rows} == set(PEOPLE)
    printed = capsys.readouterr().out
    assert "5 frames, 10 gazes" in printed


def test_the_tree_interpolates_and_refuses_to_extrapolate():
    tree = TransformTree(max_gap=1.0)
    for seconds, angle in ((1.0, 0.0), (2.0, np.pi / 2)):
        pose = base_pose(1, 1, turn=angle, walk=(2.0 * seconds, 0.0, 0.0))
        tree.add(transform(seconds, "odom", "base_link", pose), static=False)
    tree.add(transform(0.0, "base_link", "camera", camera_pose()), static=True)
    middle = tree.lookup("odom", "base_link", 1.5)
    np.testing.assert_allclose(middle[:3, 3], [3.0, 0.0, 0.0])
    np.testing.assert_allclose(middle[:3, :3], base_pose(1, 1, turn=np.pi / 4)[:3, :3],
                               atol=1e-12)
    np.testing.assert_allclose(tree.lookup("odom", "camera", 1.0), tree.lookup(
        "odom", "base_link", 1.0) @ camera_pose(), atol=1e-12)
    for stamp in (0.5, 2.5):
        with pytest.raises(LookupError, match="no transform"):
            tree.lookup("odom", "base_link", stamp)


def test_a_lookup_sees_transforms_added_after_it():
    # Lookups are remembered; a transform added later is not hidden by them.
    tree = TransformTree(max_gap=1.0)
    for seconds in (1.0, 2.0):
        pose = base_pose(1, 1, turn=0.3 * seconds, walk=(seconds, 0.0, 0.0))
        tree.add(transform(seconds, "odom", "base_link", pose), static=False)
    before = tree.lookup("odom", "base_link", 1.5)
    assert np.array_equal(tree.lookup("odom", "base_link", 1.5), before)
    tree.add(transform(1.5, "odom", "base_link", np.eye(4)), static=False)
    np.testing.assert_allclose(tree.lookup("odom", "base_link", 1.5), np.eye(4))
    tree.add(transform(0.0, "base_link", "camera", camera_pose()), static=True)
    np.testing.assert_allclose(tree.lookup("odom", "camera", 1.5), camera_pose(), atol=1e-15)
