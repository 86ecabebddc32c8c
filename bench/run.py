"""Traversal benchmark: exact log-spherical kernel vs Amanatides-Woo, in one run.

    python -m bench.run                 # 128^3 cells, 100,000 rays (issue 2)
    python -m bench.run --rays 20000 --cells 64 --repeats 3

Prints a table and writes ``bench/results/traversal.json`` (and ``.md``).
Machines are noisy: the two kernels are timed in alternating rounds of the
same run and the figure that matters is their ratio. Each timing is the best
of ``--repeats`` rounds of ``trace_many`` (count pass + fill pass, output
arrays included).
"""

import argparse
import json
import os
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numba
import numpy as np

import logsph_trace as lt
from bench.workload import best_time, make_box, make_grid, make_rays

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
    with tempfile.TemporaryDirectory() as cache:
        env = dict(os.environ, NUMBA_CACHE_DIR=cache)
        runs = []
        for _ in range(2):
            out = subprocess.run([sys.executable, "-c", FIRST_CALL], env=env, check=True,
                                 capture_output=True, text=True).stdout.split()
            runs.append([float(v) for v in out])
    (cold_trace, cold_parallel), (warm_trace, warm_parallel) = runs
    return {
        "cold_import_and_first_trace_s": cold_trace,
        "cold_import_first_trace_and_first_parallel_batch_s": cold_parallel,
        "warm_import_and_first_trace_s": warm_trace,
        "warm_import_first_trace_and_first_parallel_batch_s": warm_parallel,
    }


def measure(n_rays, cells, repeats, threads):
    grid = make_grid(cells)
    box = make_box(cells)
    origins, directions = make_rays(n_rays)
    # Warm-up compiles (or loads) every kernel before anything is timed.
    lt.trace_many(grid, origins[:10], directions[:10], parallel=False)
    lt.trace_many(grid, origins[:10], directions[:10], parallel=True)
    box.trace_many(origins[:10], directions[:10], parallel=False)

    timings = {"exact": np.inf, "amanatides_woo": np.inf, "exact_parallel": np.inf}
    voxels = {}
    for _ in range(repeats):  # alternate the kernels so both see the same noise
        numba.set_num_threads(1)
        seconds, traces = best_time(
            lambda: lt.trace_many(grid, origins, directions, parallel=False), 1)
        timings["exact"] = min(timings["exact"], seconds)
        voxels["exact"] = traces.cells.shape[0]
        seconds, traces = best_time(lambda: box.trace_many(origins, directions, parallel=False), 1)
        timings["amanatides_woo"] = min(timings["amanatides_woo"], seconds)
        voxels["amanatides_woo"] = traces.cells.shape[0]
        numba.set_num_threads(threads)
        seconds, traces = best_time(
            lambda: lt.trace_many(grid, origins, directions, parallel=True), 1)
        timings["exact_parallel"] = min(timings["exact_parallel"], seconds)
    numba.set_num_threads(threads)

    def summary(name):
        seconds = timings[name]
        return {
            "seconds": seconds,
            "voxels": int(voxels[name]),
            "voxels_per_ray": voxels[name] / n_rays,
            "ns_per_voxel": seconds / voxels[name] * 1e9,
            "rays_per_second": n_rays / seconds,
        }

    exact, reference = summary("exact"), summary("amanatides_woo")
    return {
        "rays": n_rays,
        "cells_per_axis": cells,
        "repeats": repeats,
        "exact": exact,
        "amanatides_woo": reference,
        "exact_over_amanatides_woo_per_voxel": exact["ns_per_voxel"] / reference["ns_per_voxel"],
        "parallel": {
            "threads": threads,
            "seconds": timings["exact_parallel"],
            "speedup_over_serial": timings["exact"] / timings["exact_parallel"],
        },
    }


def table(result, first_call):
    exact, aw, par = result["exact"], result["amanatides_woo"], result["parallel"]
    lines = [
        f"{result['rays']:,} random rays, {result['cells_per_axis']}^3 cells, "
        f"best of {result['repeats']}, single thread unless noted",
        "",
        "| kernel | voxels/ray | ns/voxel | rays/s |",
        "|---|---:|---:|---:|",
        f"| exact log-spherical | {exact['voxels_per_ray']:.1f} | {exact['ns_per_voxel']:.1f} "
        f"| {exact['rays_per_second']:,.0f} |",
        f"| Amanatides-Woo (Cartesian) | {aw['voxels_per_ray']:.1f} | {aw['ns_per_voxel']:.1f} "
        f"| {aw['rays_per_second']:,.0f} |",
        "",
        f"exact / Amanatides-Woo per voxel: {result['exact_over_amanatides_woo_per_voxel']:.2f}x",
        f"exact, {par['threads']} threads: {par['speedup_over_serial']:.2f}x "
        "the single-thread speed",
    ]
    if first_call:
        lines += [
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
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--no-first-call", action="store_true",
                        help="skip the cold/warm start timing")
    parser.add_argument("--out", type=Path, default=RESULTS / "traversal.json")
    args = parser.parse_args(argv)

    result = measure(args.rays, args.cells, args.repeats, args.threads)
    first_call = None if args.no_first_call else first_call_times()
    text = table(result, first_call)
    print(text)
    record = {
        "command": "python -m bench.run " + " ".join(argv if argv is not None else sys.argv[1:]),
        "date": time.strftime("%Y-%m-%d %H:%M:%S %Z"),
        "machine": {
            "cpu": platform.processor() or platform.machine(),
            "cores": os.cpu_count(),
            "python": platform.python_version(),
            "numpy": np.__version__,
            "numba": numba.__version__,
        },
        "result": result,
        "first_call": first_call,
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(record, indent=2) + "\n")
    args.out.with_suffix(".md").write_text(f"`{record['command'].strip()}`\n\n{text}\n")


if __name__ == "__main__":
    main()
