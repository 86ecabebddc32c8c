"""Synthetic ROS 2 recordings of the room scene, written by rosbags' own writer.

For trying :class:`~logsph_trace.ros.BagReplay` and ``logsph-trace replay``
without a robot, and for testing and timing them (``pip install
"logsph_trace[ros]"``). :func:`walking_robot` records a robot that turns and
walks past :func:`~logsph_trace.scene.room_scene` while two people look at
its boxes; :meth:`Recording.write` writes a rosbag2 folder (MCAP or sqlite3).
Frames follow ROS: ``odom`` is the world (x forward at the start, z up), the
robot's ``base_link`` moves in it, the depth camera's optical frame
``camera`` (x right, y down, z forward) is mounted on the base by a static
transform, and each person's gaze is a frame ``gaze_<name>`` whose z axis is
the gaze.
"""

from dataclasses import dataclass, field

import numpy as np
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.typesys import Stores, get_typestore

from .grid import ROS_TO_GRID
from .scene import room_scene

TYPES = get_typestore(Stores.ROS2_HUMBLE)
MSG = TYPES.types
# A scene point p (the library's frame: y up, z forward at the start) is
# SCENE_FROM_ODOM @ p_odom.
SCENE_FROM_ODOM = ROS_TO_GRID
# The optical frame in the base frame: its x right, y down, z forward.
BASE_FROM_OPTICAL = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
MOUNT = np.array([0.08, 0.0, 0.0])  # the camera 8 cm ahead of the base's origin
STORAGES = {"mcap": StoragePlugin.MCAP, "sqlite3": StoragePlugin.SQLITE3}


def _time(seconds):
    sec = int(np.floor(seconds))
    return MSG["builtin_interfaces/msg/Time"](sec=sec, nanosec=int(round((seconds - sec) * 1e9)))


def _header(seconds, frame):
    return MSG["std_msgs/msg/Header"](stamp=_time(seconds), frame_id=frame)


def quaternion(rotation):
    """(x, y, z, w) of a rotation matrix."""
    from scipy.spatial.transform import Rotation

    return Rotation.from_matrix(rotation).as_quat()


def transform(seconds, parent, child, matrix):
    """Return a ``geometry_msgs/TransformStamped`` of a 4 x 4 ``matrix`` (child to parent)."""
    x, y, z, w = quaternion(matrix[:3, :3])
    t = matrix[:3, 3]
    return MSG["geometry_msgs/msg/TransformStamped"](
        header=_header(seconds, parent), child_frame_id=child,
        transform=MSG["geometry_msgs/msg/Transform"](
            translation=MSG["geometry_msgs/msg/Vector3"](x=t[0], y=t[1], z=t[2]),
            rotation=MSG["geometry_msgs/msg/Quaternion"](x=x, y=y, z=z, w=w)))


def image(seconds, frame, pixels, encoding):
    """Return a ``sensor_msgs/Image`` of ``pixels`` (rows, columns) in ``encoding``."""
    data = np.ascontiguousarray(pixels)
    return MSG["sensor_msgs/msg/Image"](
        header=_header(seconds, frame), height=data.shape[0], width=data.shape[1],
        encoding=encoding, is_bigendian=0, step=data.shape[1] * data.itemsize,
        data=data.view(np.uint8).reshape(-1))


def camera_info(seconds, frame, shape, intrinsics):
    """Return a ``sensor_msgs/CameraInfo`` with camera matrix ``intrinsics`` (3 x 3)."""
    k = np.asarray(intrinsics, dtype=np.float64)
    p = np.zeros((3, 4))
    p[:, :3] = k
    return MSG["sensor_msgs/msg/CameraInfo"](
        header=_header(seconds, frame), height=shape[0], width=shape[1],
        distortion_model="plumb_bob", d=np.zeros(5), k=k.reshape(-1), r=np.eye(3).reshape(-1),
        p=p.reshape(-1), binning_x=0, binning_y=0,
        roi=MSG["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0,
                                                    do_rectify=False))


def depth_pixels(depth, encoding):
    """Depth in metres (inf or NaN: none) as ``16UC1`` millimetres (0: none) or ``32FC1``."""
    valid = np.isfinite(depth) & (depth > 0)
    if encoding == "16UC1":
        return np.where(valid, np.round(depth * 1000.0), 0).astype(np.uint16)
    return np.where(valid, depth, np.nan).astype(np.float32)


@dataclass
class Recording:
    """Messages to write: (seconds, topic, message) in the order written."""

    messages: list = field(default_factory=list)

    def add(self, seconds, topic, message):
        """Record ``message`` on ``topic`` at ``seconds`` (its log time)."""
        self.messages.append((seconds, topic, message))

    def write(self, path, storage="mcap"):
        """Write a rosbag2 folder at ``path``; return it."""
        connections = {}
        with Writer(path, version=9, storage_plugin=STORAGES[storage]) as writer:
            for seconds, topic, message in self.messages:
                if topic not in connections:
                    connections[topic] = writer.add_connection(topic, message.__msgtype__,
                                                               typestore=TYPES)
                writer.write(connections[topic], int(round(seconds * 1e9)),
                             TYPES.serialize_cdr(message, message.__msgtype__))
        return path


def base_pose(step, steps, turn=np.radians(60.0), walk=(0.0, 0.3, 0.0)):
    """Return the robot's pose in ``odom`` at ``step``: turned by ``turn`` about z, walked."""
    angle = turn * step / steps
    pose = np.eye(4)
    pose[:3, :3] = [[np.cos(angle), -np.sin(angle), 0.0], [np.sin(angle), np.cos(angle), 0.0],
                    [0.0, 0.0, 1.0]]
    pose[:3, 3] = np.asarray(walk) * step / steps
    return pose


def camera_pose():
    """Return the optical frame's pose in the base frame (static)."""
    pose = np.eye(4)
    pose[:3, :3] = BASE_FROM_OPTICAL
    pose[:3, 3] = MOUNT
    return pose


def render(scene, odom_from_optical, shape, intrinsics):
    """Depth (Z, metres; inf: no hit) and labels (box + 1; 0: none) of a pinhole camera."""
    rows, columns = shape
    fx, fy, cx, cy = intrinsics[0, 0], intrinsics[1, 1], intrinsics[0, 2], intrinsics[1, 2]
    v, u = np.mgrid[0:rows, 0:columns]
    rays = np.stack([(u - cx) / fx, (v - cy) / fy, np.ones_like(u, dtype=float)], axis=-1)
    rays = rays.reshape(-1, 3) @ (SCENE_FROM_ODOM @ odom_from_optical[:3, :3]).T
    origin = SCENE_FROM_ODOM @ odom_from_optical[:3, 3]
    distance, box = scene.cast(origin, rays)  # in units of the ray, whose Z is 1: depth
    return distance.reshape(shape), (box + 1).reshape(shape).astype(np.uint16)


def look_at(eyes, target):
    """Return a 4 x 4 gaze frame at ``eyes`` whose z axis points at ``target`` (odom)."""
    z = (target - eyes) / np.linalg.norm(target - eyes)
    x = np.cross([0.0, 0.0, 1.0], z)
    x /= np.linalg.norm(x)
    pose = np.eye(4)
    pose[:3, :3] = np.stack([x, np.cross(z, x), z], axis=1)
    pose[:3, 3] = eyes
    return pose


# People in odom, and the scene box each looks at.
PEOPLE = {"alice": (np.array([1.1, -1.0, 0.15]), "object"),
          "bob": (np.array([0.6, 0.8, 0.3]), "shelf")}


def box_centre(scene, name):
    """Return the centre of box ``name`` in odom."""
    index = scene.index(name)
    return SCENE_FROM_ODOM.T @ (0.5 * (scene.low[index] + scene.high[index]))


def walking_robot(steps=8, shape=(120, 160), encoding="16UC1", labels=True, rate=10.0,
                  gazes_per_frame=1):
    """Record a robot that turns and walks past the room scene; return (Recording, scene).

    ``steps`` + 1 depth frames of ``shape`` pixels at ``rate`` Hz (``16UC1``
    millimetres or ``32FC1`` metres), their camera info, an instance-label
    image per frame when ``labels``, the odometry on ``/tf``, the camera's
    mounting on ``/tf_static``, and ``gazes_per_frame`` samples per frame of
    each person in :data:`PEOPLE` (``gaze_alice`` looks at the object on
    the table, ``gaze_bob`` at the shelf). The robot turns 60 degrees left
    and walks 0.3 m to its left (:func:`base_pose`).
    """
    scene = room_scene()
    intrinsics = np.array([[140.0, 0.0, shape[1] / 2 - 0.5], [0.0, 140.0, shape[0] / 2 - 0.5],
                           [0.0, 0.0, 1.0]])
    recording = Recording()
    recording.add(0.0, "/tf_static", MSG["tf2_msgs/msg/TFMessage"](
        transforms=[transform(0.0, "base_link", "camera", camera_pose())]))
    for step in range(steps + 1):
        seconds = 1.0 + step / rate
        odom_from_base = base_pose(step, steps)
        recording.add(seconds, "/tf", MSG["tf2_msgs/msg/TFMessage"](
            transforms=[transform(seconds, "odom", "base_link", odom_from_base)]))
        depth, boxes = render(scene, odom_from_base @ camera_pose(), shape, intrinsics)
        recording.add(seconds, "/camera/camera_info",
                      camera_info(seconds, "camera", shape, intrinsics))
        recording.add(seconds, "/camera/depth",
                      image(seconds, "camera", depth_pixels(depth, encoding), encoding))
        if labels:
            recording.add(seconds, "/camera/labels", image(seconds, "camera", boxes, "16UC1"))
        for k in range(gazes_per_frame):
            at = seconds + (k + 0.5) / (gazes_per_frame * rate)
            for name, (eyes, box) in PEOPLE.items():
                recording.add(at, "/tf", MSG["tf2_msgs/msg/TFMessage"](transforms=[
                    transform(at, "odom", f"gaze_{name}", look_at(eyes, box_centre(scene, box)))]))
    end = 1.0 + (steps + 1) / rate  # the odometry outlasts the last frame's gazes
    recording.add(end, "/tf", MSG["tf2_msgs/msg/TFMessage"](
        transforms=[transform(end, "odom", "base_link", base_pose(steps, steps))]))
    return recording, scene


def as_recorded(bag):
    """Rewrite a bag's MCAP file as the ROS 2 recorder lays one out, and return its path.

    rosbags' writer puts the schemas and channels after the messages, in the
    summary; the recorder writes them before the first message that needs
    them, so a file cut short still says what its messages are. Here (with
    the ``mcap`` library): the header, the schemas, the channels, then every
    message as a record of its own, unchunked, then the summary.
    """
    from mcap.reader import make_reader
    from mcap.writer import Writer

    path = next(bag.glob("*.mcap"))
    with path.open("rb") as stream:
        reader = make_reader(stream)
        summary = reader.get_summary()
        messages = [message for _, _, message in reader.iter_messages(log_time_order=False)]
    with path.open("wb") as out:
        writer = Writer(out, use_chunking=False)
        writer.start(profile="ros2", library="logsph_trace.ros_scene")
        schema_ids = {schema.id: writer.register_schema(schema.name, schema.encoding, schema.data)
                      for schema in summary.schemas.values()}
        channel_ids = {channel.id: writer.register_channel(
            channel.topic, channel.message_encoding, schema_ids[channel.schema_id],
            channel.metadata) for channel in summary.channels.values()}
        for message in messages:
            writer.add_message(channel_ids[message.channel_id], message.log_time, message.data,
                               message.publish_time, message.sequence)
        writer.finish()
    return path
