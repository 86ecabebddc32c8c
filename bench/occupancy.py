"""Occupancy integration timing: depth scans into a 64 x 360 x 180 map.

    python -m bench.occupancy [--threads 1,2,4,...] [--repeats 10]

Two scans: the point cloud of ``logsph_trace.scene.table_scene`` seen by a
640 x 480 depth sensor, and the real Middlebury 2014 Motorcycle frame that
scikit-image ships (343,274 valid pixels; skipped with a note when
scikit-image is missing). Each is timed with the sensor at the map's centre
(the egocentric case, radial rays) and 10 cm off it (the coherent scan:
sampled rays, then the others walked from near their ends), per thread
count, best and median of ``--repeats`` scans with the phases of the best
(prepare: input checks and scratch in Python; mark: each ray's set-up and
walk, in parallel; apply: the parallel map update). Same-run baselines:
the same scan with every ray walked whole (the coherent scan switched off,
as before it existed), and ``trace_many`` of the same rays up to their end
points, on all threads. Before each scan is timed, twice the size of that
baseline's output is written once (``bench.workload.prime_memory``: a fresh
virtual machine's first touch of memory would slow the baseline). Writes
bench/results/occupancy.json and occupancy.md.
"""

import numba
import numpy as np

import logsph_trace as lt
from bench.workload import (
    motorcycle_points,
    prime_memory,
    prime_note,
    thread_arguments,
    timed,
    write_results,
)
from logsph_trace import occupancy as occupancy_module
from logsph_trace._batching import SEGMENT_BYTES
from logsph_trace.scene import table_scene

SENSORS = (("at the centre", (0.0, 0.0, 0.0)), ("10 cm off", (0.06, 0.08, 0.0)))
PHASES = ("prepare", "mark", "apply")


def scans():
    """(scene name, sensor label, sensor, points) for every scan that can be made here."""
    scene, _, _ = table_scene()
    for label, sensor in SENSORS:
        yield "table scene, 640 x 480", label, sensor, scene.depth_points(sensor=sensor)[0]
    try:
        for label, sensor in SENSORS:
            yield "Motorcycle (real)", label, sensor, motorcycle_points(sensor)
    except ImportError:
        print("scikit-image is not installed: the Motorcycle frame is skipped "
              "(pip install scikit-image)")


def _walk_every_ray(occupancy, points, sensor):
    """Integrate with every ray walked whole: the coherent scan switched off."""
    saved = occupancy_module.COHERENT_MIN_RAYS
    occupancy_module.COHERENT_MIN_RAYS = np.iinfo(np.int64).max
    try:
        occupancy.integrate(points, sensor)
    finally:
        occupancy_module.COHERENT_MIN_RAYS = saved


def main(argv=None):
    args, counts = thread_arguments(__doc__.splitlines()[0], 10, argv)
    most = numba.get_num_threads()
    grid = lt.Grid(0.3, 10.0, 64, 360, 180)
    rows, primed = [], None
    for scene, label, sensor, points in scans():
        offsets = points - np.asarray(sensor)
        distances = np.linalg.norm(offsets, axis=1)
        origins = np.broadcast_to(np.asarray(sensor, dtype=np.float64), points.shape)
        occupancy = lt.OccupancyGrid(grid)
        occupancy.integrate(points, sensor)  # compiles or loads the kernels
        segments = lt.trace_many(grid, origins, offsets, t_max=distances).cells.shape[0]
        # The trace_many baseline writes fresh output: twice its size, written once
        # first, keeps a fresh virtual machine's first touch out of it (prime_memory).
        scan_primed = prime_memory(2 * segments * SEGMENT_BYTES / 2**20)
        if primed is None or scan_primed[0] > primed[0]:
            primed = scan_primed
        best, times, baseline, walked = {}, {t: [] for t in counts}, None, {}
        for _ in range(args.repeats):  # alternated, so that all see the same machine
            for threads in counts:
                numba.set_num_threads(threads)
                run = timed(lambda: occupancy.integrate(points, sensor))
                times[threads].append(run["seconds"])
                if threads not in best or run["seconds"] < best[threads]["seconds"]:
                    best[threads] = run
                walked[threads] = timed(lambda: _walk_every_ray(occupancy, points, sensor),
                                        walked.get(threads))
            numba.set_num_threads(most)
            baseline = timed(lambda: lt.trace_many(grid, origins, offsets, t_max=distances),
                             baseline)
        for threads in counts:
            run = best[threads]
            rows.append({
                "scene": scene, "sensor": label, "points": int(points.shape[0]),
                "segments": int(segments), "threads": threads,
                "best_ms": run["seconds"] * 1e3,
                "median_ms": float(np.median(times[threads])) * 1e3,
                "speedup_over_one_thread": best[1]["seconds"] / run["seconds"],
                "phases_ms": {p: run["phases"].get(p, 0.0) * 1e3 for p in PHASES},
                "every_ray_walked_best_ms": walked[threads]["seconds"] * 1e3,
                "trace_many_all_threads_best_ms": baseline["seconds"] * 1e3,
            })
    lines = [f"{grid}; best of {args.repeats} scans per thread count, alternated; "
             f"baseline: trace_many of the same rays up to their end points on all {most} "
             "threads (the exact traversal, segments kept); before each scan's timing, "
             f"{prime_note(primed)} (the largest scan's)", "",
             "| scan | sensor | points | cells crossed | threads | best (ms) | median (ms) "
             "| speed-up | "
             + " | ".join(f"{p} (ms)" for p in PHASES)
             + " | every ray walked (ms) | trace_many (ms) |",
             "|---|---|---:|---:|---:|---:|---:|---:|" + "---:|" * len(PHASES) + "---:|---:|"]
    for r in rows:
        phases = " | ".join(f"{r['phases_ms'][p]:.1f}" for p in PHASES)
        lines.append(f"| {r['scene']} | {r['sensor']} | {r['points']:,} | {r['segments']:,} "
                     f"| {r['threads']} | {r['best_ms']:.1f} | {r['median_ms']:.1f} "
                     f"| {r['speedup_over_one_thread']:.2f}x | {phases} "
                     f"| {r['every_ray_walked_best_ms']:.1f} "
                     f"| {r['trace_many_all_threads_best_ms']:.1f} |")
    lines += ["", "speed-up: over the same scan on 1 thread; prepare (input checks and "
              "scratch) runs on one thread but for the finite check of the points, mark "
              "and apply on all; every ray walked: the same call with the coherent scan "
              "switched off, same threads"]
    write_results("occupancy", argv, "\n".join(lines),
                  {"threads": counts, "primed_mb_s": primed, "rows": rows})


if __name__ == "__main__":
    main()
