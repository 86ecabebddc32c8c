"""Gaze-cone timing (issue 4): a 1,000-ray cone on a 64 x 360 x 180 grid, rho 0.3-10 m.

    python -m bench.cone

A person 1.5 m from the robot looks down at a table; the cone is traced with
all threads (parallel=True) and aggregated into weighted cells. Prints the
best and median of 50 calls and writes bench/results/cone.json and cone.md.
"""

import time

import numba
import numpy as np

import logsph_trace as lt
from bench.workload import write_results

ORIGIN = (0.4, 1.5, 1.2)
GAZE = (-0.1, -0.4, 1.0)


def main(argv=None):
    grid = lt.Grid(0.3, 10.0, 64, 360, 180)
    rows = []
    for half_angle_deg, n_rays in ((5.0, 1000), (5.0, None)):
        run = lambda: lt.trace_cone(grid, ORIGIN, GAZE, np.radians(half_angle_deg), n_rays=n_rays)  # noqa: E731
        cone = run()
        times = []
        for _ in range(50):
            start = time.perf_counter()
            run()
            times.append(time.perf_counter() - start)
        rows.append({
            "half_angle_deg": half_angle_deg,
            "n_rays": int(cone.directions.shape[0]),
            "n_rays_rule": "given" if n_rays else "default_ray_count",
            "cells": len(cone),
            "segments": int(cone.traces.cells.shape[0]),
            "best_ms": min(times) * 1e3,
            "median_ms": float(np.median(times)) * 1e3,
        })
    lines = [f"{grid}; gaze from {ORIGIN} towards {GAZE}; {numba.get_num_threads()} threads; "
             "50 calls", "",
             "| half-angle | rays | cells | segments | best (ms) | median (ms) |",
             "|---:|---:|---:|---:|---:|---:|"]
    for r in rows:
        lines.append(f"| {r['half_angle_deg']:g} deg | {r['n_rays']} ({r['n_rays_rule']}) "
                     f"| {r['cells']} | {r['segments']} | {r['best_ms']:.2f} | {r['median_ms']:.2f} |")
    write_results("cone", argv, "\n".join(lines),
                  {"threads": numba.get_num_threads(), "rows": rows})


if __name__ == "__main__":
    main()
