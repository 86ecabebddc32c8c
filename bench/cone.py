"""Gaze-cone timing: a 1,000-ray cone on a 64 x 360 x 180 grid, rho 0.3-10 m.

    python -m bench.cone [--threads 1,2,4,...] [--repeats 50]

A person 1.5 m from the robot looks down at a table; the cone is traced and
aggregated into weighted cells, per thread count, with the phases of the
best call (bound: the rays' segment bounds and the scratch; trace; aggregate).
In the same rounds: ``fixation_probability`` on the same gaze over the table
scene's map (its cost over the cone's alone is the figure to watch), and
the packed-trace baseline. Writes bench/results/cone.json and cone.md.
"""

import numba
import numpy as np

import logsph_trace as lt
from bench.workload import thread_arguments, timed, write_results
from logsph_trace.scene import table_scene

ORIGIN = (0.4, 1.5, 1.2)
GAZE = (-0.1, -0.4, 1.0)


def _packed(grid, origin, gaze, half_angle, n_rays):
    """The plain cone, this benchmark's in-run baseline: trace into fresh
    packed arrays, then aggregate."""
    from logsph_trace.cone import aggregate_cells, sample_rays, trace_given_rays

    origin = np.asarray(origin, dtype=np.float64)
    directions, ray_weights = sample_rays(grid, origin, gaze, half_angle, n_rays, "fibonacci",
                                      "gaussian", None)
    traces = trace_given_rays(grid, origin, directions)
    return aggregate_cells(grid, traces.offsets, traces.cells, traces.t_enter, origin,
                           directions[0], ray_weights)


def fixation_map(grid):
    """The table scene integrated from the map's centre: what the gaze looks at."""
    scene, _, _ = table_scene()
    points = scene.depth_points(sensor=(0.0, 0.0, 0.0))[0]
    return lt.OccupancyGrid(grid).integrate(points, (0.0, 0.0, 0.0))


PHASES = ("bound", "trace", "aggregate")


def main(argv=None):
    args, counts = thread_arguments(__doc__.splitlines()[0], 50, argv)
    most = numba.get_num_threads()
    grid = lt.Grid(0.3, 10.0, 64, 360, 180)
    occupancy = fixation_map(grid)
    rows = []
    for half_angle_deg, n_rays in ((5.0, 1000), (5.0, None)):
        half_angle = np.radians(half_angle_deg)
        calls = {
            "trace_cone": lambda: lt.trace_cone(grid, ORIGIN, GAZE, half_angle, n_rays=n_rays),
            "fixation_probability": lambda: lt.fixation_probability(
                occupancy, ORIGIN, GAZE, half_angle=half_angle, n_rays=n_rays),
            "packed baseline": lambda: _packed(grid, ORIGIN, GAZE, half_angle, n_rays),
        }
        cone = calls["trace_cone"]()
        assert np.array_equal(calls["packed baseline"]()[0], cone.cells)
        runs = {}
        for _ in range(args.repeats):  # alternated, so that all see the same machine
            for threads in counts:
                numba.set_num_threads(threads)
                for name, call in calls.items():
                    run = timed(call)
                    runs.setdefault((name, threads), []).append(run)
        numba.set_num_threads(most)
        for threads in counts:
            best = {name: min(runs[name, threads], key=lambda run: run["seconds"])
                    for name in calls}
            one = min(run["seconds"] for run in runs["trace_cone", 1])
            rows.append({
                "half_angle_deg": half_angle_deg,
                "n_rays": int(cone.directions.shape[0]),
                "n_rays_rule": "given" if n_rays else "default_ray_count",
                "cells": len(cone),
                "segments": int(cone.traces.cells.shape[0]),
                "threads": threads,
                "best_ms": best["trace_cone"]["seconds"] * 1e3,
                "median_ms": float(np.median([run["seconds"] for run in
                                              runs["trace_cone", threads]])) * 1e3,
                "speedup_over_one_thread": one / best["trace_cone"]["seconds"],
                "phases_ms": {p: best["trace_cone"]["phases"].get(p, 0.0) * 1e3 for p in PHASES},
                "fixation_best_ms": best["fixation_probability"]["seconds"] * 1e3,
                "fixation_over_cone": (best["fixation_probability"]["seconds"]
                                       / best["trace_cone"]["seconds"]),
                "packed_best_ms": best["packed baseline"]["seconds"] * 1e3,
                "speedup": best["packed baseline"]["seconds"] / best["trace_cone"]["seconds"],
            })
    lines = [f"{grid}; gaze from {ORIGIN} towards {GAZE}; {args.repeats} calls each per "
             "thread count, alternated with fixation_probability on the table scene's map "
             "and the baseline (trace into fresh packed arrays, then aggregate)", "",
             "| half-angle | rays | cells | segments | threads | best (ms) | median (ms) "
             "| speed-up | " + " | ".join(f"{p} (ms)" for p in PHASES)
             + " | fixation_probability (ms) | fixation / cone | baseline (ms) "
             "| over baseline |",
             "|---:|---:|---:|---:|---:|---:|---:|---:|" + "---:|" * len(PHASES)
             + "---:|---:|---:|---:|"]
    for r in rows:
        phases = " | ".join(f"{r['phases_ms'][p]:.2f}" for p in PHASES)
        lines.append(f"| {r['half_angle_deg']:g} deg | {r['n_rays']} ({r['n_rays_rule']}) "
                     f"| {r['cells']} | {r['segments']} | {r['threads']} | {r['best_ms']:.2f} "
                     f"| {r['median_ms']:.2f} | {r['speedup_over_one_thread']:.2f}x | {phases} "
                     f"| {r['fixation_best_ms']:.2f} | {r['fixation_over_cone']:.2f}x "
                     f"| {r['packed_best_ms']:.2f} | {r['speedup']:.2f}x |")
    lines += ["", "speed-up: trace_cone over itself on 1 thread; fixation / cone: best "
              "fixation_probability over best trace_cone on the same gaze and thread count; "
              "over baseline: the packed baseline's best over trace_cone's"]
    write_results("cone", argv, "\n".join(lines), {"threads": counts, "rows": rows})


if __name__ == "__main__":
    main()
