"""Traversal benchmark: exact log-spherical kernel vs Amanatides-Woo, in one run.

    python -m bench.run                 # 128^3 cells, 100,000 rays
    python -m bench.run --rays 20000 --cells 64 --repeats 3
    python -m bench.run --threads 1,2,4,8,16

Prints a table and writes ``bench/results/traversal.json`` (and ``.md``).
Machines are noisy: the two kernels are timed in alternating rounds of the
same run and the figure that matters is their ratio. Each timing is the best
of ``--repeats`` rounds of ``trace_many`` (output arrays included). Both
kernels batch the same way: one appending pass on one thread, ordered
chunks on more; per thread count the
table gives the time in each phase. Four times the exact output's size of
memory is written once before timing (``--prime MB``; 0 skips it): on a fresh
virtual machine a process's first touch of memory costs the host a fault as well
(``bench.workload.prime_memory``).
"""

import argparse
from pathlib import Path

import numba

import logsph_trace as lt
from bench.workload import (
    add_prime_option,
    fresh_processes,
    make_box,
    make_grid,
    make_rays,
    prime_memory,
    prime_note,
    thread_counts,
    timed,
    write_results,
)
from logsph_trace import _batching

RESULTS = Path(__file__).resolve().parent / "results"

FIRST_CALL = """
import time
start = time.perf_counter()
import numpy as np
import logsph_trace as lt
grid = lt.Grid(0.1, 10.0, 64, 64, 64)
lt.trace(grid, [0.5, 1.5, 1.0], [-0.3, -0.2, 1.0])
first = time.perf_counter() - start
lt.trace_many(grid, np.zeros((4096, 3)) + 1.0, np.ones((4096, 3)), parallel=True)
print(first, time.perf_counter() - start)
"""


def first_call_times():
    """Import + first trace, in fresh processes: with an empty cache, then with the cache warm."""
    runs = fresh_processes(FIRST_CALL)
    (cold_trace, cold_parallel), (warm_trace, warm_parallel) = runs
    return {
        "cold_import_and_first_trace_s": cold_trace,
        "cold_import_first_trace_and_first_parallel_batch_s": cold_parallel,
        "warm_import_and_first_trace_s": warm_trace,
        "warm_import_first_trace_and_first_parallel_batch_s": warm_parallel,
    }


def measure(n_rays, cells, repeats, thread_counts, prime=None):
    """Time every kernel and path; ``prime``: MB to write once first (None: four times
    the exact output, which covers the Cartesian one and a call's worth; 0: none)."""
    grid = make_grid(cells)
    box = make_box(cells)
    origins, directions = make_rays(n_rays)
    # Warm-up compiles (or loads) every kernel before anything is timed.
    for parallel in (False, True):
        lt.trace_many(grid, origins[:4096], directions[:4096], parallel=parallel)
        box.trace_many(origins[:4096], directions[:4096], parallel=parallel)

    most = numba.get_num_threads()
    buffers = lt.TraceBuffers()  # the robot's case: the same arrays every frame
    segments = lt.trace_many(grid, origins, directions, out=buffers).cells.shape[0]
    primed = prime_memory(4 * segments * _batching.SEGMENT_BYTES / 2**20 if prime is None
                          else prime)
    runs = {}
    for _ in range(repeats):  # alternate everything so that all see the same noise
        for threads in thread_counts:
            numba.set_num_threads(min(threads, most))
            parallel = threads > 1
            calls = [
                ("exact", lambda: lt.trace_many(grid, origins, directions, parallel=parallel)),
                ("amanatides_woo", lambda: box.trace_many(origins, directions, parallel=parallel)),
                ("exact_buffers", lambda: lt.trace_many(grid, origins, directions,
                                                        parallel=parallel, out=buffers)),
            ]
            for name, call in calls:
                runs[name, threads] = timed(call, runs.get((name, threads)),
                                            keep=lambda traces: int(traces.cells.shape[0]))
    numba.set_num_threads(most)

    def summary(name, threads):
        run = runs[name, threads]
        one = runs[name, 1]["seconds"]
        return {
            "threads": threads,
            "seconds": run["seconds"],
            "voxels": run["kept"],
            "voxels_per_ray": run["kept"] / n_rays,
            "ns_per_voxel": run["seconds"] / run["kept"] * 1e9,
            "rays_per_second": n_rays / run["seconds"],
            "speedup_over_one_thread": one / run["seconds"],
            "phases_s": run["phases"],
            # What runs on one thread whatever the thread count: Python between
            # the kernels, the ordered chunks' sampled bounds and the final shrink, and
            # the input check, against the one-thread time.
            "serial_part_of_one_thread": sum(run["phases"].get(p, 0.0) for p in SERIAL) / one,
        }

    exact = [summary("exact", t) for t in thread_counts]
    reference = [summary("amanatides_woo", t) for t in thread_counts]
    reused = [summary("exact_buffers", t) for t in thread_counts]
    return {
        "rays": n_rays,
        "cells_per_axis": cells,
        "repeats": repeats,
        "primed_mb_s": primed,
        "exact": exact,
        "amanatides_woo": reference,
        "exact_into_reused_buffers": reused,
        "exact_over_amanatides_woo_per_voxel": [
            e["ns_per_voxel"] / r["ns_per_voxel"] for e, r in zip(exact, reference)],
    }


# "check": the input checks, on all threads from 32,768 rays; counted as serial all the
# same (the coercion and the small batches' checks are), so the serial part is an upper
# bound.
PHASES = ("check", "bound", "trace", "allocate", "shrink", "other")
SERIAL = ("check", "bound", "shrink", "other")


def table(result, first_call):
    exact, aw = result["exact"][0], result["amanatides_woo"][0]
    lines = [
        f"{result['rays']:,} random rays, {result['cells_per_axis']}^3 cells, "
        f"best of {result['repeats']} alternated rounds; both kernels write the same output "
        "(cell, t_enter, t_exit per voxel) in one appending pass; "
        + prime_note(result.get("primed_mb_s")),
        "",
        "| kernel, 1 thread | voxels/ray | ns/voxel | rays/s |",
        "|---|---:|---:|---:|",
        f"| exact log-spherical | {exact['voxels_per_ray']:.1f} | {exact['ns_per_voxel']:.1f} "
        f"| {exact['rays_per_second']:,.0f} |",
        f"| Amanatides-Woo (Cartesian) | {aw['voxels_per_ray']:.1f} | {aw['ns_per_voxel']:.1f} "
        f"| {aw['rays_per_second']:,.0f} |",
        "",
        f"exact / Amanatides-Woo per voxel, 1 thread: "
        f"{result['exact_over_amanatides_woo_per_voxel'][0]:.2f}x",
        "",
        "| kernel | threads | ms | speed-up | " + " | ".join(f"{p} ms" for p in PHASES)
        + " | serial part |",
        "|---|---:|---:|---:|" + "---:|" * len(PHASES) + "---:|",
    ]
    for name, rows in (("exact", result["exact"]), ("Amanatides-Woo", result["amanatides_woo"]),
                       ("exact, out=TraceBuffers", result["exact_into_reused_buffers"])):
        for row in rows:
            phases = " | ".join(f"{row['phases_s'].get(p, 0.0) * 1e3:.1f}" for p in PHASES)
            lines.append(f"| {name} | {row['threads']} | {row['seconds'] * 1e3:.1f} "
                         f"| {row['speedup_over_one_thread']:.2f}x | {phases} "
                         f"| {100 * row['serial_part_of_one_thread']:.1f}% |")
    lines += ["", "speed-up: over the same call on 1 thread; serial part: the phases that run "
              "on one thread whatever the thread count (bound, shrink, other) and the input check "
              "(check: on all threads from 32,768 rays, counted all the same), as a share of the "
              "one-thread time; out=TraceBuffers: the same arrays reused every call"]
    if first_call:
        lines += [
            "",
            f"import + first trace: cold cache {first_call['cold_import_and_first_trace_s']:.1f} s "
            "(+ parallel build: "
            f"{first_call['cold_import_first_trace_and_first_parallel_batch_s']:.1f} s "
            f"in all), warm cache {first_call['warm_import_and_first_trace_s']:.2f} s",
        ]
    return "\n".join(lines)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rays", type=int, default=100_000)
    parser.add_argument("--cells", type=int, default=128)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--threads", default=f"1,{numba.get_num_threads()}",
                        help="comma-separated thread counts (default: 1 and all)")
    parser.add_argument("--no-first-call", action="store_true",
                        help="skip the cold/warm start timing")
    add_prime_option(parser, "four times the exact output")
    parser.add_argument("--out", type=Path, default=RESULTS / "traversal.json")
    args = parser.parse_args(argv)

    counts = thread_counts(args.threads)
    result = measure(args.rays, args.cells, args.repeats, counts, args.prime)
    first_call = None if args.no_first_call else first_call_times()
    text = table(result, first_call)
    write_results("run", argv, text, {"result": result, "first_call": first_call},
                  out=args.out)


if __name__ == "__main__":
    main()
