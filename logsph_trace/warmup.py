"""Compile every kernel once, ahead of the first real call: ``logsph-trace warmup``.

Numba compiles a kernel the first time it runs and caches the machine code
beside the package. A robot, or a container image built once and started
many times, can pay that cost at install time instead of on its first gaze:
run :func:`warmup` (or ``logsph-trace warmup``) where the package is
installed, as the user who will run it, on the same kind of CPU. The paths
a call takes depend on the machine's thread count (one thread compiles no
parallel kernel), so run it on the machine itself.
"""

import time

import numpy as np


def warmup():
    """Run every public computation once on small inputs, so that its kernels compile and cache.

    Covers each ``trace`` method, ``trace_many`` on one thread and on all
    (a batch large enough to take the parallel path), cones one at a time
    (small ones, traced on one thread, and large ones) and in batches, the
    occupancy map from the centre, off it and from the gap with labels (a
    scan large enough for the coherent scan), depth images, fixation, objects,
    point look-ups and a map that moves. The CPU only: the GPU's kernels compile on their first
    ``device="cuda"`` call.

    Returns
    -------
    float
        The seconds it took (about a second when everything was cached).
    """
    from . import (
        METHODS,
        Grid,
        OccupancyGrid,
        depth_to_points,
        fixation_probability,
        gaze_from_pitch_yaw,
        gaze_objects,
        gaze_targets,
        label_objects,
        trace,
        trace_cone,
        trace_cones,
        trace_many,
    )
    from ._batching import CONE_PARALLEL_MIN_RAYS, PARALLEL_MIN_RAYS
    from ._validate import PARALLEL_CHECK_ROWS
    from .occupancy import COHERENT_MIN_RAYS
    from .scene import yaw_pose
    from .sensor import DEFAULT_ROTATION

    start = time.perf_counter()
    rng = np.random.default_rng(0)
    grid = Grid(0.3, 8.0, 16, 36, 18)
    for method in METHODS:
        trace(grid, (0.4, 1.0, 1.5), (-0.2, -0.5, -1.0), method=method)
    rays = rng.normal(size=(PARALLEL_MIN_RAYS, 6))
    for parallel in (False, True):
        trace_many(grid, rays, parallel=parallel)
    # Towards the map's centre (summed cell by cell) and away (in boxes).
    eyes = (0.4, 1.0, 1.5)
    looks = ((-0.2, -0.5, -1.0), (0.2, -0.5, 1.0))
    for look in looks:
        for n_rays in (None, CONE_PARALLEL_MIN_RAYS):
            trace_cone(grid, eyes, look, np.radians(5), n_rays=n_rays)
    trace_cones(grid, [(0.4, 1.0, 1.5), (0.0, 0.0, 0.0)], [(-0.2, -0.5, -1.0), (0, 0, 1)],
                np.radians(5))
    grid.cell_of(rng.normal(size=(64, 3)))
    grid.count_points(rng.normal(size=(64, 3)))
    # A depth image large enough for the coherent scan and the parallel input
    # check (256 x 160 pixels).
    rows = 160
    columns = max(256, -(-max(COHERENT_MIN_RAYS, PARALLEL_CHECK_ROWS) // rows))
    depth = 2.0 + 0.5 * rng.random((rows, columns))
    labels = (np.arange(rows * columns).reshape(rows, columns) // 4000 + 1).astype(np.int32)
    intrinsics = (200.0, 200.0, columns / 2, rows / 2)
    for sensor in ((0.0, 0.0, 0.0), (0.05, 0.02, 0.0), (0.0, 1.0, 0.0)):
        pose = (DEFAULT_ROTATION, np.asarray(sensor))
        bvm = OccupancyGrid(grid).integrate_depth(depth, intrinsics, pose=pose, labels=labels)
        points = depth_to_points(depth, intrinsics, pose=pose).points
        bvm.integrate(points[:64], sensor)
    gaze = gaze_from_pitch_yaw(-0.3, 3.0, (0.2, -0.3, 1.0))
    gaze_targets(bvm, gaze)
    fixation_probability(bvm, gaze)
    for look in looks:
        for n_rays in (None, CONE_PARALLEL_MIN_RAYS):
            fixation_probability(bvm, eyes, look, half_angle=np.radians(5), n_rays=n_rays)
    label_objects(bvm, replace=True)
    gaze_objects(bvm, gaze)
    # A robot that moves: a turn by whole cells, a turn, a step (read back).
    for motion in (yaw_pose(2 * np.pi / 36, (0.0, 0.0, 0.0)), yaw_pose(0.3, (0.0, 0.0, 0.0)),
                   yaw_pose(0.3, (0.05, 0.0, 0.0))):
        bvm.move(motion)
        bvm.log_odds  # noqa: B018 -- reading it resamples
    return time.perf_counter() - start

