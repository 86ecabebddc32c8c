"""Gaze-cone timing (issue 4): a 1,000-ray cone on a 64 x 360 x 180 grid, rho 0.3-10 m.

    python -m bench.cone

A person 1.5 m from the robot looks down at a table; the cone is traced with
all threads and aggregated into weighted cells. Prints the best and median
of 50 calls, against the packed-trace baseline timed in the same run, and
writes bench/results/cone.json and cone.md.
"""

import time

import numba
import numpy as np

import logsph_trace as lt
from bench.workload import write_results

ORIGIN = (0.4, 1.5, 1.2)
GAZE = (-0.1, -0.4, 1.0)


def _packed(grid, origin, gaze, half_angle, n_rays):
    """The cone as issue 4 first built it, kept as this benchmark's in-run
    baseline: trace into fresh packed arrays, then aggregate."""
    from logsph_trace.cone import aggregate_cells, sample_rays, trace_given_rays

    origin = np.asarray(origin, dtype=np.float64)
    directions, ray_weights = sample_rays(grid, origin, gaze, half_angle, n_rays, "fibonacci",
                                      "gaussian", None)
    traces = trace_given_rays(grid, origin, directions)
    return aggregate_cells(grid, traces.offsets, traces.cells, traces.t_enter, directions[0],
                      ray_weights)


def main(argv=None):
    grid = lt.Grid(0.3, 10.0, 64, 360, 180)
    rows = []
    for half_angle_deg, n_rays in ((5.0, 1000), (5.0, None)):
        half_angle = np.radians(half_angle_deg)
        run = lambda: lt.trace_cone(grid, ORIGIN, GAZE, half_angle, n_rays=n_rays)  # noqa: E731
        baseline = lambda: _packed(grid, ORIGIN, GAZE, half_angle, n_rays)  # noqa: E731
        cone = run()
        assert np.array_equal(baseline()[0], cone.cells)
        times, base_times = [], []
        for _ in range(50):  # interleaved, so both see the same machine
            start = time.perf_counter()
            run()
            times.append(time.perf_counter() - start)
            start = time.perf_counter()
            baseline()
            base_times.append(time.perf_counter() - start)
        rows.append({
            "half_angle_deg": half_angle_deg,
            "n_rays": int(cone.directions.shape[0]),
            "n_rays_rule": "given" if n_rays else "default_ray_count",
            "cells": len(cone),
            "segments": int(cone.traces.cells.shape[0]),
            "best_ms": min(times) * 1e3,
            "median_ms": float(np.median(times)) * 1e3,
            "packed_best_ms": min(base_times) * 1e3,
            "speedup": min(base_times) / min(times),
        })
    lines = [f"{grid}; gaze from {ORIGIN} towards {GAZE}; {numba.get_num_threads()} threads; "
             "50 calls each, interleaved with the baseline (trace into fresh packed arrays, "
             "then aggregate)", "",
             "| half-angle | rays | cells | segments | best (ms) | median (ms) "
             "| baseline best (ms) | speed-up |",
             "|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for r in rows:
        lines.append(f"| {r['half_angle_deg']:g} deg | {r['n_rays']} ({r['n_rays_rule']}) "
                     f"| {r['cells']} | {r['segments']} | {r['best_ms']:.2f} "
                     f"| {r['median_ms']:.2f} "
                     f"| {r['packed_best_ms']:.2f} | {r['speedup']:.2f}x |")
    write_results("cone", argv, "\n".join(lines),
                  {"threads": numba.get_num_threads(), "rows": rows})


if __name__ == "__main__":
    main()
