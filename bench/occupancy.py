"""Occupancy integration timing (issue 4): a 640 x 480 depth image into a 64 x 360 x 180 map.

    python -m bench.occupancy

The point cloud of ``logsph_trace.scene.table_scene`` seen by a 640 x 480
depth sensor. Timed with the sensor at the map's centre (the egocentric case,
radial rays) and 10 cm off it (the column walk), all threads, best and
median of 10 scans, each against trace_many of the same rays timed in the
same run. Writes bench/results/occupancy.json and occupancy.md.
"""

import time

import numba
import numpy as np

import logsph_trace as lt
from bench.workload import write_results
from logsph_trace.scene import table_scene


def main(argv=None):
    grid = lt.Grid(0.3, 10.0, 64, 360, 180)
    scene, _, _ = table_scene()
    rows = []
    for label, sensor in (("at the map's centre", (0.0, 0.0, 0.0)),
                          ("10 cm off the centre", (0.06, 0.08, 0.0))):
        points, _, _ = scene.depth_points(sensor=sensor)
        offsets = points - np.asarray(sensor)
        distances = np.linalg.norm(offsets, axis=1)
        origins = np.broadcast_to(np.asarray(sensor, dtype=np.float64), points.shape)
        occupancy = lt.OccupancyGrid(grid)
        occupancy.integrate(points, sensor)
        segments = lt.trace_many(grid, origins, offsets, t_max=distances).cells.shape[0]
        times, trace_times = [], []
        for _ in range(10):  # interleaved with the baseline: the exact trace of the same rays
            start = time.perf_counter()
            occupancy.integrate(points, sensor)
            times.append(time.perf_counter() - start)
            start = time.perf_counter()
            lt.trace_many(grid, origins, offsets, t_max=distances)
            trace_times.append(time.perf_counter() - start)
        rows.append({"sensor": label, "points": int(points.shape[0]), "segments": int(segments),
                     "best_ms": min(times) * 1e3, "median_ms": float(np.median(times)) * 1e3,
                     "trace_best_ms": min(trace_times) * 1e3,
                     "speedup": min(trace_times) / min(times)})
    lines = [f"{grid}; 640 x 480 depth image of the table scene; "
             f"{numba.get_num_threads()} threads; "
             "10 scans, interleaved with the baseline: trace_many of the same rays up to their "
             "end points (the exact traversal, segments kept)", "",
             "| sensor | points | cells crossed | best (ms) | median (ms) | trace_many best (ms) "
             "| speed-up |", "|---|---:|---:|---:|---:|---:|---:|"]
    for r in rows:
        lines.append(f"| {r['sensor']} | {r['points']:,} | {r['segments']:,} | {r['best_ms']:.1f} "
                     f"| {r['median_ms']:.1f} | {r['trace_best_ms']:.1f} | {r['speedup']:.1f}x |")
    write_results("occupancy", argv, "\n".join(lines),
                  {"threads": numba.get_num_threads(), "rows": rows})


if __name__ == "__main__":
    main()
