"""Replay a robot's recording: ROS 2 bags in, attention events out.

``pip install "logsph_trace[ros]"`` (``rosbags`` reads the bags without ROS,
MCAP and sqlite3 alike; ``scipy`` interpolates rotations). :class:`BagReplay`
runs the egocentric map in the robot's base frame: each depth image is
integrated from the camera's pose in that frame (from ``/tf`` and
``/tf_static``), the map is moved by the odometry between stamps
(:meth:`OccupancyGrid.move`), and at each gaze -- a TF frame per person
whose z axis is the gaze, as ROS4HRI publishes them (``gaze_<id>``) -- the
objects are ranked (:func:`~logsph_trace.gaze_objects`).
``logsph-trace replay`` writes the events as JSON Lines.
"""

import fnmatch
import heapq
import math
import sys
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from . import _validate as validate
from . import gaze as _gaze
from .grid import ROS_TO_GRID, Grid
from .objects import label_objects
from .occupancy import OccupancyGrid

GAZE_FRAMES = "gaze_*"
# A transform interpolated between two samples farther apart than this
# (seconds) is stale: skipped, not guessed.
MAX_GAP = 0.5
# Images held back to put stamps that arrive out of order back in order.
REORDER = 16
DEFAULT_GRID = (0.3, 10.0, 64, 360, 180)
# Depth encodings: the dtype and the metres per unit.
DEPTH_ENCODINGS = {"16UC1": np.uint16, "mono16": np.uint16, "32FC1": np.float32}
DEPTH_SCALES = {"16UC1": 0.001, "mono16": 0.001, "32FC1": 1.0}
LABEL_ENCODINGS = {"8UC1": np.uint8, "mono8": np.uint8, "16UC1": np.uint16, "mono16": np.uint16,
                   "32SC1": np.int32}
TF_TOPICS = ("/tf", "/tf_static")
# The map's frame in ROS's base frame (x forward, y left, z up): forward is the
# map's +z and up its +y (``from_ros``), so the map's azimuth turns about the
# robot's vertical axis.
MAP_FROM_BASE = np.eye(4)
MAP_FROM_BASE[:3, :3] = ROS_TO_GRID


@dataclass(frozen=True)
class AttentionEvent:
    """An object a person's gaze may land on, at one gaze stamp.

    Attributes
    ----------
    stamp : float
        The gaze's stamp, seconds.
    person : str
        The face id taken from the gaze frame's name (``gaze_<id>``).
    frame_id : str
        The frame of ``point``: the robot's base frame at ``stamp``.
    object : int
        The object's label; 0 when the gaze reaches no object.
    probability : float
        The probability that the gaze stops at the object first (0 for none).
    point : tuple of float or None
        Where the gaze first reaches the object, metres in ``frame_id``.
    distance : float or None
        How far from the eyes that is, metres.
    """

    stamp: float
    person: str
    frame_id: str
    object: int
    probability: float
    point: tuple = None
    distance: float = None

    def as_dict(self):
        """Return the event as a JSON-ready dict."""
        return {"stamp": self.stamp, "person": self.person, "frame_id": self.frame_id,
                "object": self.object, "probability": self.probability,
                "point": None if self.point is None else list(self.point),
                "distance": self.distance}


@dataclass
class ReplaySummary:
    """What a replay did: counts, and what it skipped and why.

    Attributes
    ----------
    frames, gazes, events : int
        Depth frames integrated, gazes ranked, events produced.
    invalid_pixels : int
        Depth pixels without a depth (0, NaN, infinite), skipped.
    skipped : collections.Counter
        Messages left out, by reason.
    truncated : str or None
        Why the bag ended early (it could not be read to its end), or None.
    """

    frames: int = 0
    gazes: int = 0
    events: int = 0
    invalid_pixels: int = 0
    skipped: Counter = field(default_factory=Counter)
    truncated: str = None

    def line(self):
        """One line: frames, gazes, events, then each reason for skipping."""
        text = (f"{self.frames} frames, {self.gazes} gazes, {self.events} events; "
                f"{self.invalid_pixels:,} depth pixels without depth")
        if self.skipped:
            text += "; skipped: " + ", ".join(f"{count} {reason}"
                                              for reason, count in sorted(self.skipped.items()))
        if self.truncated:
            text += f"; the bag ends early ({self.truncated})"
        return text


class MissingTransform(LookupError):
    """No transform between two frames at a stamp, or only a stale one."""


def _matrix(translation, quaternion):
    from scipy.spatial.transform import Rotation

    matrix = np.eye(4)
    matrix[:3, :3] = Rotation.from_quat(quaternion).as_matrix()
    matrix[:3, 3] = translation
    return matrix


# How many of the latest lookups a TransformTree keeps.
ROOTS_KEPT = 64


class TransformTree:
    """The TF tree of a recording: static and dynamic transforms, looked up at a stamp.

    A dynamic transform between two samples is interpolated (translation
    linearly, rotation by slerp); a stamp outside its samples, or between two
    more than ``max_gap`` seconds apart, raises :class:`MissingTransform`.
    """

    def __init__(self, max_gap=MAX_GAP):
        self.max_gap = max_gap
        self._parent = {}
        self._static = {}
        self._samples = {}  # child: [(stamp, translation, quaternion)]
        self._arrays = {}
        # (frame, stamp): _to_root's answer. A replay asks for the base at each
        # stamp three or four times (the frame, the move, each gaze), and each
        # asking would slerp anew (python -m bench.replay A/Bs the memo).
        self._roots = {}

    def add(self, transform, static):
        """Add a ``geometry_msgs/TransformStamped``."""
        child = transform.child_frame_id.lstrip("/")
        parent = transform.header.frame_id.lstrip("/")
        t, q = transform.transform.translation, transform.transform.rotation
        translation = (t.x, t.y, t.z)
        quaternion = (q.x, q.y, q.z, q.w)
        if not all(math.isfinite(v) for v in translation + quaternion) or not any(quaternion):
            return False
        self._parent[child] = parent
        self._roots.clear()
        if static:
            self._static[child] = _matrix(translation, quaternion)
        else:
            self._samples.setdefault(child, []).append(
                (_seconds(transform.header.stamp), translation, quaternion))
            self._arrays.pop(child, None)
        return True

    def frames_matching(self, pattern):
        """Return the dynamic child frames whose names match ``pattern`` (fnmatch), sorted."""
        return sorted(name for name in self._samples if fnmatch.fnmatchcase(name, pattern))

    def stamps(self, child):
        """Return the stamps of ``child``'s dynamic samples, sorted."""
        return self._sorted(child)[0]

    def root(self, frame):
        """Return the top of ``frame``'s chain of parents."""
        seen = {frame}
        while frame in self._parent:
            frame = self._parent[frame]
            if frame in seen:
                raise MissingTransform(f"the TF tree has a loop at {frame!r}")
            seen.add(frame)
        return frame

    def lookup(self, target, source, stamp):
        """Return the 4 x 4 transform from ``source`` to ``target`` at ``stamp``."""
        from_root = self._to_root(source, stamp)
        to_root = self._to_root(target, stamp)
        if from_root[1] != to_root[1]:
            raise MissingTransform(f"no transform {target} <- {source}")
        return np.linalg.inv(to_root[0]) @ from_root[0]

    def _to_root(self, frame, stamp):
        """Return (the transform from ``frame`` to its root at ``stamp``, the root's name)."""
        known = self._roots.get((frame, stamp))
        if known is None:
            if len(self._roots) >= ROOTS_KEPT:
                self._roots.clear()
            known = self._roots[frame, stamp] = self._walk_to_root(frame, stamp)
        return known

    def _walk_to_root(self, frame, stamp):
        matrix = np.eye(4)
        seen = set()
        while frame in self._parent:
            if frame in seen:
                raise MissingTransform(f"the TF tree has a loop at {frame!r}")
            seen.add(frame)
            step = self._static.get(frame)
            if step is None:
                step = self._interpolated(frame, stamp)
            matrix = step @ matrix
            frame = self._parent[frame]
        return matrix, frame

    def _sorted(self, child):
        arrays = self._arrays.get(child)
        if arrays is None:
            samples = sorted(self._samples[child], key=lambda sample: sample[0])
            arrays = (np.array([s[0] for s in samples]), np.array([s[1] for s in samples]),
                      np.array([s[2] for s in samples]))
            self._arrays[child] = arrays
        return arrays

    def _interpolated(self, child, stamp):
        from scipy.spatial.transform import Rotation, Slerp

        stamps, translations, quaternions = self._sorted(child)
        after = int(np.searchsorted(stamps, stamp, side="left"))
        if after < stamps.shape[0] and stamps[after] == stamp:
            return _matrix(translations[after], quaternions[after])
        if after == 0 or after == stamps.shape[0]:
            raise MissingTransform(f"no transform {self._parent[child]} <- {child} at "
                                   f"{stamp:.3f} s (samples {stamps[0]:.3f} to "
                                   f"{stamps[-1]:.3f} s)")
        before = after - 1
        gap = stamps[after] - stamps[before]
        if gap > self.max_gap:
            raise MissingTransform(f"a stale transform {self._parent[child]} <- {child} at "
                                   f"{stamp:.3f} s (samples {gap:.2f} s apart)")
        weight = (stamp - stamps[before]) / gap
        rotation = Slerp([0.0, 1.0], Rotation.from_quat(quaternions[[before, after]]))([weight])
        matrix = np.eye(4)
        matrix[:3, :3] = rotation.as_matrix()[0]
        matrix[:3, 3] = (1.0 - weight) * translations[before] + weight * translations[after]
        return matrix


class McapScan:
    """The messages of an MCAP file read record by record, without its index.

    For a file cut short, which rosbags' reader refuses: the ``mcap``
    library's stream reader gives its schemas, channels and messages (in
    chunks or not, compressed or not) in the order written, and an
    ``EOFError`` is raised where the file ends inside a record. It offers
    what :class:`BagReplay` uses of rosbags' ``AnyReader``.
    """

    def __init__(self, path):
        from mcap.records import Channel, Message, Schema
        from rosbags.typesys import Stores, get_typestore

        self.path = Path(path)
        self.typestore = get_typestore(Stores.LATEST)
        schemas, channels, counts = {}, {}, Counter()
        try:
            for record in self._records():
                if isinstance(record, Schema):
                    schemas[record.id] = record.name
                elif isinstance(record, Channel):
                    channels[record.id] = (record.topic, schemas.get(record.schema_id, ""))
                elif isinstance(record, Message):
                    counts[record.channel_id] += 1
        except EOFError:
            pass  # counted up to the cut; messages() says where it is
        self.connections = [_ScannedChannel(channel, topic, msgtype, counts[channel])
                            for channel, (topic, msgtype) in channels.items()]

    def _records(self):
        from mcap.exceptions import McapError
        from mcap.stream_reader import StreamReader

        with self.path.open("rb") as stream:
            try:
                yield from StreamReader(stream).records
            except McapError as error:
                raise EOFError(f"the file ends inside a record ({error})") from None

    def messages(self, connections=()):
        """Yield (connection, log time, raw message) of ``connections``, in file order."""
        from mcap.records import Message

        wanted = {connection.id: connection for connection in connections}
        for record in self._records():
            if isinstance(record, Message) and record.channel_id in wanted:
                yield wanted[record.channel_id], record.log_time, record.data

    def deserialize(self, raw, msgtype):
        """Decode a CDR message of type ``msgtype``."""
        return self.typestore.deserialize_cdr(raw, msgtype)

    def close(self):
        """Nothing to close: each pass opens the file anew."""


@dataclass(frozen=True)
class _ScannedChannel:
    id: int
    topic: str
    msgtype: str
    msgcount: int


def _seconds(stamp):
    return stamp.sec + 1e-9 * stamp.nanosec


def image_array(message, encodings, topic):
    """Return an image message's pixels as an array (rows, columns), in its own dtype.

    ``encodings``: {encoding: dtype} accepted; another is a ValueError naming it.
    """
    dtype = encodings.get(message.encoding)
    if dtype is None:
        raise ValueError(f"{topic}: unknown image encoding {message.encoding!r}; expected one of "
                         f"{sorted(encodings)}")
    dtype = np.dtype(dtype).newbyteorder(">" if message.is_bigendian else "<")
    rows, columns, step = int(message.height), int(message.width), int(message.step)
    data = np.asarray(message.data, dtype=np.uint8)
    if step < columns * dtype.itemsize or data.size < rows * step:
        raise ValueError(f"{topic}: an image of {rows} x {columns} {message.encoding} pixels with "
                         f"step {step} needs {rows * step} bytes, got {data.size}")
    pixels = data[:rows * step].reshape(rows, step)[:, :columns * dtype.itemsize]
    return np.ascontiguousarray(pixels).view(dtype).astype(dtype.newbyteorder("="))


def _person(frame, pattern):
    """Return the face id in a gaze frame's name: what the pattern's wildcards matched."""
    cut = [i for i, c in enumerate(pattern) if c in "*?["]
    if not cut:
        return frame
    prefix = pattern[:cut[0]]
    suffix = pattern[pattern.rfind("*") + 1:] if "*" in pattern else ""
    return frame[len(prefix):len(frame) - len(suffix)] if suffix else frame[len(prefix):]


class BagReplay:
    """Replay a ROS 2 bag through the egocentric map; iterate to get :class:`AttentionEvent` s.

    Parameters
    ----------
    bag : str or Path
        A rosbag2 folder (MCAP or sqlite3 storage) or its single storage file.
    depth : str
        The depth image topic (``sensor_msgs/Image``, ``16UC1`` millimetres or
        ``32FC1`` metres).
    camera_info : str
        Its ``sensor_msgs/CameraInfo`` topic.
    base_frame : str
        The robot's base frame: the map's frame, and the frame of the events.
    labels : str, optional
        An instance-label image topic aligned with the depth (same stamps;
        0 is no object). Without it, objects are the map's connected groups
        of occupied cells (:func:`~logsph_trace.label_objects`).
    gaze_frames : str
        A pattern (fnmatch) for the gaze frames on ``/tf``; the part a
        wildcard matches names the person.
    half_angle : float
        The gaze cone's half-angle, radians.
    grid : Grid, optional
        The map's grid (default 0.3 to 10 m, 64 x 360 x 180).
    max_gap : float
        Seconds between two TF samples beyond which interpolating is stale.
    progress : bool
        Draw a progress bar over the images on stderr (tqdm).

    Attributes
    ----------
    summary : ReplaySummary
        Filled in while iterating.
    occupancy : OccupancyGrid
        The map, at the base frame's last stamp replayed: its x is the
        robot's left, y up and z forward (``MAP_FROM_BASE``), so that its
        azimuth turns about the robot's vertical axis.

    Raises
    ------
    ImportError
        Without ``rosbags`` (``pip install "logsph_trace[ros]"``).
    ValueError
        A topic is missing (the message names the topics present), or an
        image has an unknown encoding.
    """

    def __init__(self, bag, depth, camera_info, base_frame, labels=None,
                 gaze_frames=GAZE_FRAMES, half_angle=math.radians(5.0), grid=None,
                 max_gap=MAX_GAP, progress=False):
        try:
            import rosbags  # noqa: F401 -- checked here, used below
        except ImportError:
            raise ImportError('replaying a bag needs rosbags: pip install "logsph_trace[ros]"'
                              ) from None
        self.bag = Path(bag)
        if not self.bag.exists():
            raise FileNotFoundError(f"no such bag: '{self.bag}'")
        self.topics = {"depth": depth, "camera_info": camera_info, "labels": labels}
        self.base_frame = base_frame.lstrip("/")
        self.gaze_frames = gaze_frames
        self.half_angle = validate.finite("half_angle", half_angle)
        self.occupancy = OccupancyGrid(grid if grid is not None else Grid(*DEFAULT_GRID))
        self.summary = ReplaySummary()
        self.tree = TransformTree(max_gap)
        self.progress = progress
        self._stamp = None  # the base frame's stamp the map is in
        self._labelled = True  # the map's labels are up to date (label_objects)

    def __iter__(self):
        from rosbags.highlevel import AnyReader

        reader = AnyReader([self.bag])
        try:
            reader.open()
        except Exception as error:  # noqa: BLE001 -- rosbags' errors vary by storage
            cut = sorted(self.bag.glob("*.mcap")) if self.bag.is_dir() else []
            if "end magic" not in str(error) or len(cut) != 1:
                raise ValueError(f"{self.bag} cannot be read: {error}") from None
            # An MCAP file cut short (the recorder was killed) has no index or
            # footer: read its records in order, up to where it ends.
            reader = McapScan(cut[0])
        try:
            connections = self._connections(reader)
            infos = self._read_transforms(reader, connections)
            gazes = self._gaze_samples()
            frames = self._frames(reader, connections)
            for stamp, depth, labels in frames:
                while gazes and gazes[0][0] < stamp:
                    yield from self._gaze(*heapq.heappop(gazes))
                self._frame(stamp, depth, labels, infos)
            while gazes:
                yield from self._gaze(*heapq.heappop(gazes))
        finally:
            reader.close()

    # ---- reading ------------------------------------------------------------
    def _connections(self, reader):
        """{role: [connections]}; a missing topic is a ValueError naming those present."""
        by_topic = {}
        for connection in reader.connections:
            by_topic.setdefault(connection.topic, []).append(connection)
        present = ", ".join(f"{topic} ({conns[0].msgtype})"
                            for topic, conns in sorted(by_topic.items()))
        out = {}
        for role, topic in self.topics.items():
            if topic is None:
                continue
            if topic not in by_topic:
                raise ValueError(f"{self.bag}: no topic {topic!r} (--{role.replace('_', '-')}); "
                                 f"its topics: {present or 'none'}")
            out[role] = by_topic[topic]
        out["tf"] = [c for topic in TF_TOPICS for c in by_topic.get(topic, [])]
        if not out["tf"]:
            raise ValueError(f"{self.bag}: no /tf or /tf_static topic; its topics: "
                             f"{present or 'none'}")
        return out

    def _messages(self, reader, connections):
        """Yield (connection, message) in the bag's order.

        A bag that cannot be read to its end stops the iteration, noted in the
        summary.
        """
        try:
            for connection, _, raw in reader.messages(connections=connections):
                yield connection, reader.deserialize(raw, connection.msgtype)
        except Exception as error:  # noqa: BLE001 -- any reader error ends the bag
            self.summary.truncated = f"{type(error).__name__}: {error}"

    def _read_transforms(self, reader, connections):
        """Read TF and camera info; return the camera infos: (their stamps, [K]), sorted."""
        infos = []
        for connection, message in self._messages(
                reader, connections["tf"] + connections["camera_info"]):
            if connection.topic in TF_TOPICS:
                static = connection.topic == "/tf_static"
                for transform in message.transforms:
                    if not self.tree.add(transform, static):
                        self.summary.skipped["transforms not finite"] += 1
            else:
                infos.append((_seconds(message.header.stamp),
                              np.asarray(message.k, dtype=np.float64).reshape(3, 3)))
        if not infos:
            raise ValueError(f"{self.bag}: no messages on {self.topics['camera_info']!r}")
        infos.sort(key=lambda info: info[0])
        return np.array([info[0] for info in infos]), [info[1] for info in infos]

    def _gaze_samples(self):
        """Return a heap of (stamp, frame) for every sample of every gaze frame."""
        heap = [(float(stamp), frame) for frame in self.tree.frames_matching(self.gaze_frames)
                for stamp in self.tree.stamps(frame)]
        heapq.heapify(heap)
        return heap

    def _frames(self, reader, connections):
        """Depth frames as (stamp, (pixels, frame_id, scale), labels or None), in stamp order.

        Images are held back ``REORDER`` at a time so that stamps out of order
        come out in order; one older than a frame already given is skipped.
        """
        from tqdm import tqdm

        held, labels, last = [], {}, -math.inf
        wanted = connections["depth"] + connections.get("labels", [])
        bar = tqdm(self._messages(reader, wanted), total=sum(c.msgcount for c in wanted),
                   unit="image", disable=not self.progress, file=sys.stderr)
        for connection, message in bar:
            stamp = _seconds(message.header.stamp)
            if connection.topic == self.topics["labels"]:
                labels[stamp] = image_array(message, LABEL_ENCODINGS, connection.topic)
                continue
            pixels = image_array(message, DEPTH_ENCODINGS, connection.topic)
            heapq.heappush(held, (stamp, message.header.frame_id.lstrip("/"), pixels,
                                  DEPTH_SCALES[message.encoding]))
            while len(held) > REORDER:
                last = yield from self._release(held, labels, last)
        while held:
            last = yield from self._release(held, labels, last)

    def _release(self, held, labels, last):
        stamp, frame_id, pixels, scale = heapq.heappop(held)
        if stamp <= last:
            self.summary.skipped["depth frames out of order"] += 1
            return last
        label_image = labels.pop(stamp, None)
        if len(labels) > 4 * REORDER:  # label images no depth frame will come for
            for old in [key for key in labels if key < stamp]:
                del labels[old]
        if self.topics["labels"] is not None and label_image is None:
            self.summary.skipped["depth frames without a label image"] += 1
            return last
        yield stamp, (pixels, frame_id, scale), label_image
        return stamp

    # ---- replaying ----------------------------------------------------------
    def _move_to(self, stamp):
        """Move the map into the base frame at ``stamp`` (odometry from the last one)."""
        if self._stamp is not None and stamp != self._stamp:
            root = self.tree.root(self.base_frame)
            before = self.tree.lookup(root, self.base_frame, self._stamp)
            now = self.tree.lookup(root, self.base_frame, stamp)
            self.occupancy.move(MAP_FROM_BASE @ np.linalg.inv(before) @ now @ MAP_FROM_BASE.T)
        self._stamp = stamp

    def _arrive(self, stamp, frame, what):
        """Move the map to ``stamp``; return ``frame``'s pose in the map's frame then.

        Or, where a transform is missing or stale, count ``what`` as skipped
        and return None, the map left where it was.
        """
        try:
            pose = MAP_FROM_BASE @ self.tree.lookup(self.base_frame, frame, stamp)
            self._move_to(stamp)
        except MissingTransform:
            self.summary.skipped[f"{what} without a transform"] += 1
            return None
        return pose

    def _frame(self, stamp, depth, labels, infos):
        pixels, camera, scale = depth
        pose = self._arrive(stamp, camera, "depth frames")
        if pose is None:
            return
        stamps, matrices = infos
        at = max(int(np.searchsorted(stamps, stamp, side="right")) - 1, 0)
        self.occupancy.integrate_depth(pixels, matrices[at], pose=pose, depth_scale=scale,
                                       labels=labels)
        self.summary.invalid_pixels += self.occupancy.last_scan.invalid
        self._labelled = labels is not None
        self.summary.frames += 1

    def _gaze(self, stamp, frame):
        gaze = self._arrive(stamp, frame, "gazes")
        if gaze is None:
            return
        if not self._labelled:
            label_objects(self.occupancy, replace=True)
            self._labelled = True
        # gaze_objects without the objects' centroids, which events do not carry
        origin = validate.point("origin", gaze[:3, 3], validate.reach(self.occupancy.grid))
        objects = _gaze._ranked(self.occupancy, origin, gaze[:3, 2], self.half_angle, None, None,
                                {}, _gaze._fixation_options(), centroids=False)
        person = _person(frame, self.gaze_frames)
        self.summary.gazes += 1
        if not len(objects):
            self.summary.events += 1
            yield AttentionEvent(stamp, person, self.base_frame, 0, 0.0)
            return
        for hit in objects:
            self.summary.events += 1
            point = MAP_FROM_BASE[:3, :3].T @ hit.point  # back in the base frame
            yield AttentionEvent(stamp, person, self.base_frame, hit.id, hit.probability,
                                 tuple(point.tolist()), hit.distance)
