"""Depth-image integration: the real Motorcycle frame into a 64 x 360 x 180 map.

    python -m bench.depth [--threads 1,2,...] [--repeats 20]

Times ``OccupancyGrid.integrate_depth`` with the camera at the map's centre
and 10 cm off it, next to its two parts in the same rounds:
``depth_to_points`` (back-projection, invalid pixels skipped and counted)
and ``integrate`` of the same points. Needs scikit-image (the ``data``
extra). Writes bench/results/depth.json and depth.md.
"""

import time

import numba
import numpy as np

import logsph_trace as lt
from bench.workload import thread_arguments, write_results
from logsph_trace import datasets
from logsph_trace.sensor import DEFAULT_ROTATION

SENSORS = (("at the centre", (0.0, 0.0, 0.0)), ("10 cm off", (0.06, 0.08, 0.0)))


def main(argv=None):
    args, counts = thread_arguments(__doc__.splitlines()[0], 20, argv)
    most = numba.get_num_threads()
    frame = datasets.motorcycle()
    grid = lt.Grid(0.3, 8.0, 64, 360, 180)
    rows = []
    for label, sensor in SENSORS:
        pose = (DEFAULT_ROTATION, np.array(sensor))
        points = lt.depth_to_points(frame.depth, frame.intrinsics, pose).points
        occupancy = lt.OccupancyGrid(grid).integrate_depth(frame.depth, frame.intrinsics, pose)
        stats = occupancy.last_scan
        calls = {
            "integrate_depth": lambda: occupancy.integrate_depth(frame.depth, frame.intrinsics,
                                                                 pose),
            "depth_to_points": lambda: lt.depth_to_points(frame.depth, frame.intrinsics, pose),
            "integrate(points)": lambda: occupancy.integrate(points, sensor),
        }
        best = {}
        for _ in range(args.repeats):  # alternated, so that all see the same machine
            for threads in counts:
                numba.set_num_threads(threads)
                for name, call in calls.items():
                    start = time.perf_counter()
                    call()
                    seconds = time.perf_counter() - start
                    best[name, threads] = min(best.get((name, threads), np.inf), seconds)
        numba.set_num_threads(most)
        for threads in counts:
            rows.append({"sensor": label, "threads": threads,
                         **{f"{name}_ms": 1e3 * best[name, threads] for name in calls}})
    lines = [
        f"{frame.name}: {stats.rays:,} pixels with depth, {stats.invalid:,} without; "
        f"{grid}; best of {args.repeats} calls, alternated",
        "",
        "| camera | threads | integrate_depth (ms) | depth_to_points (ms) | integrate of the "
        "points (ms) |",
        "|---|---:|---:|---:|---:|",
        *[f"| {r['sensor']} | {r['threads']} | {r['integrate_depth_ms']:.1f} | "
          f"{r['depth_to_points_ms']:.1f} | {r['integrate(points)_ms']:.1f} |" for r in rows],
    ]
    write_results("depth", argv, "\n".join(lines), {"grid": str(grid), "rows": rows})


if __name__ == "__main__":
    main()
