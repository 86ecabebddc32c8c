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
