"""Occupancy integration timing (issue 4): a 640 x 480 depth image into a 64 x 360 x 180 map.

    python -m bench.occupancy

The point cloud of ``logsph_trace.scene.table_scene`` seen by a 640 x 480
depth sensor. Timed with the sensor at the map's centre (the egocentric case,
radial rays) and 10 cm off it (general traversal), all threads, best and
median of 10 scans. Writes bench/results/occupancy.json and occupancy.md.
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
        occupancy = lt.OccupancyGrid(grid)
        occupancy.integrate(points, sensor)
        times = []
        for _ in range(10):
            start = time.perf_counter()
            occupancy.integrate(points, sensor)
            times.append(time.perf_counter() - start)
        rows.append({"sensor": label, "points": int(points.shape[0]),
                     "best_ms": min(times) * 1e3, "median_ms": float(np.median(times)) * 1e3})
    lines = [f"{grid}; 640 x 480 depth image of the table scene; {numba.get_num_threads()} threads; "
             "10 scans", "", "| sensor | points | best (ms) | median (ms) |", "|---|---:|---:|---:|"]
    for r in rows:
        lines.append(f"| {r['sensor']} | {r['points']:,} | {r['best_ms']:.1f} | {r['median_ms']:.1f} |")
    write_results("occupancy", argv, "\n".join(lines),
                  {"threads": numba.get_num_threads(), "rows": rows})


if __name__ == "__main__":
    main()
