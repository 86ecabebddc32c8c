"""Real sensor data to try the library on.

:func:`motorcycle` is the Middlebury 2014 "Motorcycle" stereo frame that
scikit-image ships (``pip install "logsph_trace[data]"``), as a depth
image with its camera and an instance image of its objects.
"""

from dataclasses import dataclass

import numpy as np

# Calibration of the frame as scikit-image ships it (skimage.data.stereo_motorcycle's
# docstring): focal length and principal point in pixels, the disparity offset
# between the two cameras' principal points, and the baseline in metres.
MOTORCYCLE_FOCAL = 994.978
MOTORCYCLE_CX = 311.193
MOTORCYCLE_CY = 254.877
MOTORCYCLE_DOFFS = 31.086
MOTORCYCLE_BASELINE = 0.193001


# Four parts of the motorcycle, boxed by hand on the 741 x 500 left image:
# label -> (name, (first column, end column), (first row, end row)).
MOTORCYCLE_PARTS = {
    1: ("front wheel", (470, 640), (270, 440)),
    2: ("rear wheel", (110, 250), (250, 410)),
    3: ("fuel tank", (290, 440), (150, 225)),
    4: ("engine", (300, 420), (240, 340)),
}


def box_labels(shape, boxes):
    """Paint 2-D boxes into an instance image of ``shape``, as a detector would give it.

    ``boxes``: ``{label: (name, (first column, end column), (first row, end
    row))}``, painted in order (a later box wins where two overlap); every
    other pixel is 0, no object.
    """
    labels = np.zeros(shape, dtype=np.int32)
    for label, (_, (c0, c1), (r0, r1)) in boxes.items():
        labels[r0:r1, c0:c1] = label
    return labels


# The frame's objects as a 2-D instance segmenter would give them:
# label -> (name, (first column, end column), (first row, end row), (nearest Z, farthest Z)).
# Each is a box drawn by hand on the left image, cut to the object's depth
# range (metres), with the floor left out.
MOTORCYCLE_OBJECTS = {
    1: ("motorcycle", (95, 660), (55, 460), (0.0, 2.9)),
    2: ("bench", (20, 210), (110, 300), (2.9, 4.2)),
    3: ("shelves", (290, 741), (0, 330), (3.3, np.inf)),
}
# Pixels whose point lies within this of the fitted floor are floor, not an object (metres).
_FLOOR_MARGIN = 0.04


@dataclass(frozen=True)
class DepthFrame:
    """A camera image with its depth, intrinsics and objects.

    Attributes
    ----------
    image : numpy.ndarray, uint8, shape (rows, columns, 3)
        The colour image.
    depth : numpy.ndarray, float64, shape (rows, columns)
        Z along the optical axis, metres; ``inf`` where there is no ground
        truth (what :meth:`~logsph_trace.OccupancyGrid.integrate_depth` skips).
    intrinsics : numpy.ndarray, float64, shape (3, 3)
        The camera matrix K (OpenCV's convention).
    name : str
    labels : numpy.ndarray, int32, shape (rows, columns)
        An instance image of the frame's objects, as a 2-D segmenter gives
        it: each pixel's object, 0 for none.
    names : dict of int to str
        Each object's name, by label.
    """

    image: np.ndarray
    depth: np.ndarray
    intrinsics: np.ndarray
    name: str
    labels: np.ndarray
    names: dict

    @property
    def valid(self):
        """Pixels with a depth."""
        return np.isfinite(self.depth)


def motorcycle():
    """Return the Middlebury 2014 Motorcycle frame (left camera) as a :class:`DepthFrame`.

    Depth comes from the ground-truth disparity ``d`` as
    ``Z = f B / (d + doffs)``; pixels without ground truth (``inf`` in the
    disparity, not NaN as scikit-image's docstring says) stay ``inf``. An
    indoor garage 2.1-5.3 m deep, 343,274 pixels with depth.

    Its objects (``labels`` and ``names``) are a motorcycle 2.1-2.7 m from
    the camera, a bench and shelves behind it: boxes drawn by hand, each cut
    to its object's depth range, with the floor (found by
    :func:`~logsph_trace.fit_plane`) left out.

    Raises
    ------
    ImportError
        scikit-image is not installed (``pip install "logsph_trace[data]"``).
    """
    try:
        from skimage.data import stereo_motorcycle
    except ImportError:
        raise ImportError("the Motorcycle frame needs scikit-image: "
                          "pip install 'logsph_trace[data]'") from None
    left, _, disparity = stereo_motorcycle()
    with np.errstate(invalid="ignore"):  # inf + doffs is inf; f B / inf is 0, masked below
        depth = MOTORCYCLE_FOCAL * MOTORCYCLE_BASELINE / (disparity.astype(np.float64)
                                                          + MOTORCYCLE_DOFFS)
    depth[~np.isfinite(disparity)] = np.inf
    intrinsics = np.array([[MOTORCYCLE_FOCAL, 0.0, MOTORCYCLE_CX],
                           [0.0, MOTORCYCLE_FOCAL, MOTORCYCLE_CY],
                           [0.0, 0.0, 1.0]])
    labels = _object_labels(depth, intrinsics)
    names = {label: name for label, (name, *_) in MOTORCYCLE_OBJECTS.items()}
    return DepthFrame(left, depth, intrinsics, "Middlebury 2014 Motorcycle (scikit-image)",
                      labels, names)


def _object_labels(depth, intrinsics):
    """Paint MOTORCYCLE_OBJECTS: each box's pixels in its depth range and off the floor."""
    from . import depth_to_points, fit_plane

    scan = depth_to_points(depth, intrinsics)
    above_floor = np.zeros(depth.shape, dtype=bool)
    floor = fit_plane(scan.points, tolerance=0.03)
    rows, columns = scan.pixels.T
    above_floor[rows, columns] = floor.distance(scan.points) > _FLOOR_MARGIN
    labels = np.zeros(depth.shape, dtype=np.int32)
    for label, (_, (c0, c1), (r0, r1), (near, far)) in MOTORCYCLE_OBJECTS.items():
        box = (slice(r0, r1), slice(c0, c1))
        inside = (depth[box] >= near) & (depth[box] < far) & above_floor[box]
        labels[box][inside] = label
    return labels
