"""logsph_trace: exact, fast ray traversal of bounded log-spherical grids.

Which voxels of a bounded log-spherical grid does a ray cross, in what order,
and for how long? See ``Grid``, ``trace`` and ``trace_many``; for what a
person looks at, ``OccupancyGrid``, ``gaze_from_pitch_yaw`` and
``gaze_objects``.
"""

from importlib import metadata as _metadata

from ._validate import AngleUnitWarning, DepthUnitWarning, UnitWarning
from .cone import ConeTrace, default_ray_count, trace_cone, trace_cones
from .gaze import (
    GazeAccumulator,
    GazeObjects,
    GazeTargets,
    ObjectHit,
    fixation_probability,
    gaze_objects,
    gaze_targets,
)
from .grid import Grid, cartesian_to_spherical, from_ros, spherical_to_cartesian
from .objects import Plane, fit_plane, label_objects
from .occupancy import OccupancyGrid, ScanStats
from .sensor import DepthPoints, Gaze, depth_to_points, gaze_from_pitch_yaw, gaze_from_vector
from .trace import METHODS, trace, trace_many
from .traces import Trace, TraceBuffers, Traces
from .warmup import warmup

__all__ = [
    "AngleUnitWarning",
    "ConeTrace",
    "DepthUnitWarning",
    "Gaze",
    "GazeAccumulator",
    "GazeObjects",
    "DepthPoints",
    "GazeTargets",
    "Grid",
    "METHODS",
    "ObjectHit",
    "OccupancyGrid",
    "Plane",
    "ScanStats",
    "Trace",
    "TraceBuffers",
    "Traces",
    "UnitWarning",
    "cartesian_to_spherical",
    "default_ray_count",
    "depth_to_points",
    "fit_plane",
    "fixation_probability",
    "from_ros",
    "gaze_from_pitch_yaw",
    "gaze_from_vector",
    "gaze_objects",
    "gaze_targets",
    "label_objects",
    "spherical_to_cartesian",
    "trace",
    "trace_cone",
    "trace_cones",
    "trace_many",
    "warmup",
]
try:  # one version, written once: pyproject.toml's
    __version__ = _metadata.version("logsph_trace")
except _metadata.PackageNotFoundError:  # a source tree that was never installed
    __version__ = "0+unknown"
