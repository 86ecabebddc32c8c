"""Synthetic scenes of boxes and a simulated depth sensor (the paper's Fig. 5 set-up).

Everything is in the grid's frame (y up, z forward from the robot), in metres.
"""

from dataclasses import dataclass

import numpy as np

from . import _validate as validate


@dataclass(frozen=True)
class Box:
    """An axis-aligned box named ``name`` from ``low`` to ``high`` (each (3,))."""

    name: str
    low: tuple
    high: tuple


class Scene:
    """Axis-aligned boxes that rays can be cast against.

    Parameters
    ----------
    boxes : sequence of Box
    """

    def __init__(self, boxes):
        self.boxes = tuple(boxes)
        if not self.boxes:
            raise ValueError("a scene needs at least one box")
        self.low = np.array([box.low for box in self.boxes], dtype=np.float64)
        self.high = np.array([box.high for box in self.boxes], dtype=np.float64)
        if np.any(self.low >= self.high):
            raise ValueError("every box needs low < high on each axis")
        self.names = [box.name for box in self.boxes]

    def index(self, name):
        """Position of the box called ``name``."""
        try:
            return self.names.index(name)
        except ValueError:
            raise ValueError(f"no box named {name!r}; boxes: {self.names}") from None

    def cast(self, origin, directions):
        """Nearest hit of each ray: (distances (n,), box index (n,)); inf and -1 for a miss.

        The slab test per box, vectorised over rays; ``directions`` need not be unit
        length (distances are in units of the direction's length).
        """
        origin = validate.vector("origin", origin)
        directions = validate.vectors("directions", directions)
        with np.errstate(divide="ignore", invalid="ignore"):
            t_low = (self.low[None, :, :] - origin) / directions[:, None, :]
            t_high = (self.high[None, :, :] - origin) / directions[:, None, :]
        near = np.nanmax(np.minimum(t_low, t_high), axis=2)
        far = np.nanmin(np.maximum(t_low, t_high), axis=2)
        hit = (far >= np.maximum(near, 0.0)) & np.isfinite(far)
        entry = np.where(near > 0.0, near, far)  # inside a box: its far side
        entry = np.where(hit, entry, np.inf)
        which = np.argmin(entry, axis=1)
        distance = entry[np.arange(entry.shape[0]), which]
        which[~np.isfinite(distance)] = -1
        return distance, which

    def depth_points(self, sensor=(0.0, 0.0, 0.0), width=640, height=480,
                     field_of_view=(60.0, 45.0), forward=(0.0, 0.0, 1.0), up=(0.0, 1.0, 0.0),
                     max_range=10.0):
        """Render a depth camera at ``sensor``: its point cloud and the box of each point.

        Parameters
        ----------
        sensor : array_like, shape (3,)
        width, height : int
            Pixels.
        field_of_view : (float, float)
            Horizontal and vertical, in degrees.
        forward, up : array_like, shape (3,)
            The optical axis and the image's up direction.
        max_range : float
            Returns farther than this are dropped (a real sensor's limit).

        Returns
        -------
        points : numpy.ndarray, shape (M, 3)
        labels : numpy.ndarray, int, shape (M,)
            Index of the box each point lies on.
        depth : numpy.ndarray, shape (height, width)
            Distance per pixel along its ray (inf where nothing is hit).
        """
        sensor = validate.vector("sensor", sensor)
        forward = validate.vector("forward", forward)
        forward = forward / np.linalg.norm(forward)
        up = validate.vector("up", up)
        right = np.cross(up, forward)
        right /= np.linalg.norm(right)
        up = np.cross(forward, right)
        half_w, half_h = np.tan(np.radians(np.asarray(field_of_view, dtype=np.float64)) / 2)
        u, v = np.meshgrid(np.linspace(half_w, -half_w, width),
                           np.linspace(half_h, -half_h, height))
        rays = forward + u.reshape(-1, 1) * right + v.reshape(-1, 1) * up
        rays /= np.linalg.norm(rays, axis=1)[:, None]
        distance, label = self.cast(sensor, rays)
        keep = distance <= max_range
        points = sensor + distance[keep, None] * rays[keep]
        depth = np.where(keep, distance, np.inf).reshape(height, width)
        return points, label[keep], depth


def table_scene():
    """Build the Fig. 5 set-up: a table with an object on it, a wall behind, a person.

    The robot's depth sensor is at the origin looking along +z. Returns
    ``(scene, eyes, target)``: the scene, the person's eye position (about
    1.5 m from the robot) and the point on the object the person looks at.
    """
    scene = Scene([
        Box("table", (-0.7, -0.60, 1.2), (0.7, -0.55, 2.2)),
        Box("object", (-0.10, -0.55, 1.55), (0.10, -0.30, 1.75)),
        Box("wall", (-3.0, -1.5, 3.5), (3.0, 1.5, 3.6)),
    ])
    eyes = np.array([1.0, 0.15, 1.1])
    target = np.array([0.0, -0.42, 1.65])
    return scene, eyes, target


def room_scene():
    """Build the Fig. 5 set-up with a side wall and a shelf on the robot's right (+x).

    A robot that turns towards +x keeps seeing something: the table and its
    object drift out of view and behind the camera, the shelf comes in.
    Returns the scene; its box ``b`` is object ``b + 1`` in a labelled map.
    """
    scene, _, _ = table_scene()
    return Scene(scene.boxes + (
        Box("side wall", (2.6, -1.5, -1.0), (2.7, 1.5, 3.5)),
        Box("shelf", (1.9, -0.9, 0.6), (2.3, 0.4, 1.3)),
    ))


@dataclass(frozen=True)
class Step:
    """One step of a simulated robot (see :func:`robot_walk`), in metres.

    Attributes
    ----------
    motion : numpy.ndarray, shape (4, 4)
        The robot's pose after the step in its frame before it (odometry's
        ``T_old_new``; the identity for the first step).
    pose : numpy.ndarray, shape (4, 4)
        The robot's pose in the world (the frame of the scene).
    points : numpy.ndarray, shape (M, 3)
        The depth sensor's points in the robot's frame (the sensor at its
        origin, looking along +z, image-up +y).
    labels : numpy.ndarray, int64, shape (M,)
        The box each point lies on, plus one (0 is none).
    """

    motion: np.ndarray
    pose: np.ndarray
    points: np.ndarray
    labels: np.ndarray


def yaw_pose(yaw, position):
    """Return a 4 x 4 pose: a turn by ``yaw`` radians about +y (+z to +x), then ``position``."""
    cos, sin = np.cos(yaw), np.sin(yaw)
    pose = np.eye(4)
    pose[:3, :3] = [[cos, 0.0, sin], [0.0, 1.0, 0.0], [-sin, 0.0, cos]]
    pose[:3, 3] = position
    return pose


def robot_walk(scene, steps=40, turn=np.radians(80.0), walk=(0.4, 0.0, 0.0), width=640,
               height=480):
    """Yield the :class:`Step` s of a robot that turns and walks while its depth sensor looks on.

    The robot starts at the scene's origin looking along +z, and in
    ``steps`` equal steps turns by ``turn`` radians about +y (towards +x)
    and walks by ``walk`` (world frame, metres). Each step, the first
    included (no motion), renders a ``width`` x ``height`` scan from the
    robot's new pose.
    """
    walk = validate.vector("walk", walk)
    before = None
    for step in range(steps + 1):
        pose = yaw_pose(turn * step / steps, walk * step / steps)
        rotation, position = pose[:3, :3], pose[:3, 3]
        points, boxes, _ = scene.depth_points(position, width, height,
                                              forward=rotation[:, 2], up=rotation[:, 1])
        motion = np.eye(4) if before is None else np.linalg.inv(before) @ pose
        yield Step(motion, pose, (points - position) @ rotation, boxes + 1)
        before = pose
