"""logsph_trace: exact, fast ray traversal of bounded log-spherical grids.

Which voxels of a bounded log-spherical grid does a ray cross, in what order,
and for how long? See ``Grid``, ``trace`` and ``trace_many``.
"""

from .grid import Grid, cartesian_to_spherical, from_ros, spherical_to_cartesian
from .api import METHODS, Trace, Traces, trace, trace_many
from .cone import ConeTrace, trace_cone, trace_cones
from .occupancy import GazeTargets, OccupancyGrid, fixation_probability, gaze_targets

__all__ = [
    "ConeTrace",
    "GazeTargets",
    "Grid",
    "METHODS",
    "OccupancyGrid",
    "Trace",
    "Traces",
    "cartesian_to_spherical",
    "fixation_probability",
    "from_ros",
    "gaze_targets",
    "spherical_to_cartesian",
    "trace",
    "trace_cone",
    "trace_cones",
    "trace_many",
]
__version__ = "0.1.0"
