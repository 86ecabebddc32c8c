"""Depth cameras: pixels to points in the map's frame.

The frame change is drawn and explained once, in ``docs/how-to/frames.md``. In
short: pixels and camera coordinates follow OpenCV (x right, y down, z
forward along the optical axis; pixel ``(u, v)`` is column ``u``, row
``v``). A ``pose`` takes camera coordinates to the map's frame,
``p_map = R @ p_camera + t``. Without one, the camera sits at the map's
origin looking along +z with image-up along +y, so OpenCV's ``(x, y, z)``
becomes the map's ``(-x, -y, z)``: ``R = diag(-1, -1, 1)``, ``t = 0``.

A depth pixel holds Z, the distance along the optical axis (not along the
pixel's ray), in units of ``depth_scale`` (0.001 for millimetre images).
Pixels holding 0, NaN, infinity or a negative value have no depth: they are
skipped and counted, not errors.
"""

import math
from dataclasses import dataclass

import numpy as np

from . import _validate as validate
from .kernels import sensor as _kernels

# pose=None: OpenCV's (x right, y down, z forward) in the map's frame.
DEFAULT_ROTATION = np.diag([-1.0, -1.0, 1.0])
# An integer depth image with depth_scale=1 and a value this large is more
# likely millimetres than metres (a depth camera sees 0.2 to 10 m).
MILLIMETRES_LIKELY = 100


@dataclass(frozen=True)
class DepthPoints:
    """A depth image's valid pixels as points in the map's frame.

    Attributes
    ----------
    points : numpy.ndarray, float64, shape (n, 3)
        One point per valid pixel, in row-major pixel order.
    pixels : numpy.ndarray, int64, shape (n, 2)
        Each point's pixel as (row, column).
    origin : numpy.ndarray, float64, shape (3,)
        The camera's centre in the map's frame (the rays' origin).
    invalid : int
        Pixels skipped: 0, NaN, infinite or negative depth.
    """

    points: np.ndarray
    pixels: np.ndarray
    origin: np.ndarray
    invalid: int

    def __len__(self):
        return self.points.shape[0]


def intrinsics_of(intrinsics):
    """Check a camera's intrinsics: return (fx, fy, cx, cy, skew) as floats.

    Parameters
    ----------
    intrinsics : array_like
        A 3 x 3 camera matrix ``K = [[fx, s, cx], [0, fy, cy], [0, 0, 1]]``
        (OpenCV's), or ``(fx, fy, cx, cy)`` in pixels.
    """
    array = validate.real_array("intrinsics", intrinsics,
                                "a 3x3 matrix or (fx, fy, cx, cy)")
    if array.shape == (4,):
        fx, fy, cx, cy = array
        skew = 0.0
    elif array.shape == (3, 3):
        if not np.array_equal(array[2], [0.0, 0.0, 1.0]) or array[1, 0] != 0.0:
            raise ValueError(f"intrinsics must be a camera matrix [[fx, s, cx], [0, fy, cy], "
                             f"[0, 0, 1]], got {array.tolist()}")
        fx, skew, cx, fy, cy = array[0, 0], array[0, 1], array[0, 2], array[1, 1], array[1, 2]
    else:
        raise ValueError(f"intrinsics must be a 3x3 matrix or (fx, fy, cx, cy), "
                         f"got shape {array.shape}")
    if not np.all(np.isfinite(array)):
        raise ValueError(f"intrinsics must be finite, got {array.tolist()}")
    if not (fx > 0.0 and fy > 0.0):
        raise ValueError(f"focal lengths fx and fy must be positive, got {fx!r} and {fy!r}")
    return float(fx), float(fy), float(cx), float(cy), float(skew)


def pose_of(pose, name="pose"):
    """Check a camera pose: return (R (3, 3), t (3,)), camera to map.

    Parameters
    ----------
    pose : None, array_like (4, 4), or (R, t)
        ``None``: the camera at the map's origin looking along +z, image-up
        along +y (``R = diag(-1, -1, 1)``, ``t = 0``). A 4 x 4 rigid
        transform with last row ``(0, 0, 0, 1)``, or a rotation matrix and a
        translation. ``R`` must be a rotation (orthonormal within 1e-6,
        determinant +1).
    name : str
        What the messages call it.
    """
    if pose is None:
        return DEFAULT_ROTATION.copy(), np.zeros(3)
    if isinstance(pose, (tuple, list)) and len(pose) == 2:
        rotation, translation = pose
        rotation = _finite_array(f"{name} rotation", rotation, (3, 3))
        translation = _finite_array(f"{name} translation", translation, (3,))
    else:
        matrix = _finite_array(name, pose, (4, 4))
        if not np.array_equal(matrix[3], [0.0, 0.0, 0.0, 1.0]):
            raise ValueError(f"{name}'s last row must be (0, 0, 0, 1), got {matrix[3].tolist()}")
        rotation, translation = matrix[:3, :3].copy(), matrix[:3, 3].copy()
    if (np.max(np.abs(rotation.T @ rotation - np.eye(3))) > 1e-6
            or np.linalg.det(rotation) <= 0.0):
        raise ValueError(f"{name}'s rotation must be orthonormal with determinant +1, "
                         f"got {rotation.tolist()}")
    return rotation, translation


def _finite_array(name, value, shape):
    array = validate.real_array(name, value, f"numeric with shape {shape}")
    if array.shape != shape:
        raise ValueError(f"{name} must have shape {shape}, got {array.shape}")
    if not np.all(np.isfinite(array)):
        raise ValueError(f"{name} must be finite, got {array.tolist()}")
    return array


def _depth_image(depth, depth_scale):
    """Check a depth image (2-D, numeric) and its scale; return both."""
    validate.host_only("cpu", depth=depth)
    array = np.asarray(depth)
    if array.ndim != 2:
        raise ValueError(f"depth must be a 2-D image (rows, columns), got shape {array.shape}")
    if array.dtype.kind not in "fiu":
        raise ValueError(f"depth must hold numbers, got dtype {array.dtype}")
    if not array.dtype.isnative:  # raw 16-bit PGM files are big-endian
        array = array.astype(array.dtype.newbyteorder("="))
    if array.dtype == np.float16:  # no float16 arithmetic in the kernels
        array = array.astype(np.float32)
    scale = validate.finite("depth_scale", depth_scale)
    if not scale > 0.0:
        raise ValueError(f"depth_scale must be positive, got {depth_scale!r}")
    if array.dtype.kind in "iu" and scale == 1.0 and array.size:
        largest = int(array.max())
        if largest >= MILLIMETRES_LIKELY:
            validate.warn(
                f"depth is {array.dtype} with depth_scale=1 and values up to {largest:,}: "
                f"read as metres, that is {largest / 1000:g} km away. A 16-bit depth camera "
                f"writes millimetres: pass depth_scale=0.001",
                validate.DepthUnitWarning)
    return np.ascontiguousarray(array), scale


def depth_to_points(depth, intrinsics, pose=None, depth_scale=1.0):
    """Back-project a depth image to points in the map's frame.

    Parameters
    ----------
    depth : array_like, shape (rows, columns)
        Z along the optical axis per pixel, any numeric dtype (e.g. uint16
        millimetres or float32 metres). 0, NaN, infinite and negative values
        mark pixels without depth.
    intrinsics : array_like
        A 3 x 3 camera matrix or ``(fx, fy, cx, cy)`` (see :func:`intrinsics_of`).
    pose : None, array_like (4, 4), or (R, t)
        Camera to map (see :func:`pose_of`); ``None``: the camera at the
        map's origin, looking along +z with image-up along +y.
    depth_scale : float
        Metres (or the map's unit) per depth unit.

    Returns
    -------
    DepthPoints
        The valid pixels' points, their pixels, the camera's centre and the
        number of pixels skipped.

    Raises
    ------
    ValueError
        A depth that is not a 2-D numeric image, bad intrinsics, pose or
        ``depth_scale``.
    MemoryError
        The points would not fit in the memory available.
    """
    depth, scale = _depth_image(depth, depth_scale)
    fx, fy, cx, cy, skew = intrinsics_of(intrinsics)
    rotation, translation = pose_of(pose)
    # Per pixel: the mask (1 byte); per valid pixel: its index, point and
    # pixel (8 + 24 + 16 bytes). Counted as if every pixel were valid.
    validate.fits("depth", depth.size * 49, f"back-projecting {depth.size:,} pixels")
    if depth.dtype.kind == "f":
        valid = np.isfinite(depth) & (depth > 0)
    else:
        valid = depth > 0
    flat = np.flatnonzero(valid)
    points = np.empty((flat.shape[0], 3))
    pixels = np.empty((flat.shape[0], 2), dtype=np.int64)
    _kernels.back_project(depth.reshape(-1), flat, depth.shape[1], scale, fx, fy, cx, cy, skew,
                          rotation, translation, points, pixels)
    return DepthPoints(points, pixels, translation, int(depth.size - flat.shape[0]))


# ---- gaze from estimators -------------------------------------------------------------------
#
# Appearance-based gaze estimators report a gaze in the camera that saw the
# face. Their mean angular error is the natural cone half-angle: L2CS-Net
# reports 3.92 degrees on MPIIGaze and 10.41 on Gaze360 (Abdelrahman et al.,
# 2022), so 4-11 degrees covers a frontal face to a face seen in the wild.


@dataclass(frozen=True)
class Gaze:
    """A gaze in the map's frame: where the eyes are and where they look.

    :func:`~logsph_trace.gaze_objects`, :func:`~logsph_trace.fixation_probability`
    and :func:`~logsph_trace.gaze_targets` take it as it is; it also
    unpacks as ``origin, direction`` (``lt.trace_cone(grid, *gaze, half_angle)``).

    Attributes
    ----------
    origin : numpy.ndarray, float64, shape (3,)
        The eyes' position in the map's frame.
    direction : numpy.ndarray, float64, shape (3,)
        The gaze's unit direction in the map's frame.
    """

    origin: np.ndarray
    direction: np.ndarray

    def __iter__(self):
        return iter((self.origin, self.direction))


def gaze_pair(gaze, direction):
    """Return ``(origin, direction)`` from a :class:`Gaze`, or from a position and a direction."""
    if isinstance(gaze, Gaze):
        if direction is not None:
            raise TypeError("give a Gaze, or the eyes' position and a direction, not both")
        return gaze.origin, gaze.direction
    if direction is None:
        raise TypeError("direction is missing: give a Gaze (gaze_from_pitch_yaw, "
                        "gaze_from_vector), or the eyes' position and a direction")
    return gaze, direction


def gaze_from_vector(vector, eyes, pose=None):
    """Build a gaze from a gaze vector in the camera's frame (OpenFace's ``gaze_0``, ``gaze_1``).

    Parameters
    ----------
    vector : array_like, shape (3,)
        The gaze direction in the camera's OpenCV frame (x right, y down, z
        forward), any non-zero length; OpenFace writes it so.
    eyes : array_like, shape (3,)
        The eyes' position in the camera's frame, e.g. the face's 3-D
        landmarks, or a detected face's pixel back-projected at its depth.
    pose : None, array_like (4, 4), or (R, t)
        The camera's pose in the map (see :func:`pose_of`).

    Returns
    -------
    Gaze
    """
    rotation, translation = pose_of(pose)
    direction = validate.unit("vector", vector)
    eyes = validate.point("eyes", eyes)
    return Gaze(rotation @ eyes + translation, rotation @ direction)


def gaze_from_pitch_yaw(pitch, yaw, eyes, pose=None):
    """Build a gaze from pitch and yaw in the camera's frame (L2CS-Net, Gaze360, ETH-XGaze).

    Zero pitch and yaw look straight into the camera. The direction in the
    camera's OpenCV frame is ``(-cos(pitch) sin(yaw), -sin(pitch),
    -cos(pitch) cos(yaw))``, as L2CS-Net's ``gazeto3d`` builds it: positive
    pitch looks up, positive yaw towards the image's left.

    The estimator reports the gaze in the frame of the camera that saw the
    face, so ``eyes`` and ``pose`` are that camera's too. When the robot's
    depth camera sees the face, the map built with ``pose=None`` and a gaze
    built with ``pose=None`` share one frame.

    Parameters
    ----------
    pitch, yaw : float
        Radians. A pitch beyond pi/2 or either beyond 2 pi in magnitude
        warns (:class:`~logsph_trace.AngleUnitWarning`): likely degrees.
    eyes : array_like, shape (3,)
        The eyes' position in the camera's frame (OpenCV's: x right, y
        down, z forward), in metres: from the estimator's face detection,
        the face's pixel back-projected at its depth, or a face landmark
        model.
    pose : None, array_like (4, 4), or (R, t)
        The camera's pose in the map (see :func:`pose_of`).

    Returns
    -------
    Gaze
    """
    pitch = validate.finite("pitch", pitch)
    yaw = validate.finite("yaw", yaw)
    if abs(pitch) > math.pi / 2 or abs(yaw) > 2 * math.pi:
        validate.warn(
            f"pitch={pitch:g}, yaw={yaw:g} rad: beyond what a gaze can be in radians (pitch "
            f"within pi/2, yaw within 2 pi); if they are degrees, pass np.radians(...)",
            validate.AngleUnitWarning)
    vector = (-np.cos(pitch) * np.sin(yaw), -np.sin(pitch), -np.cos(pitch) * np.cos(yaw))
    return gaze_from_vector(vector, eyes, pose)
