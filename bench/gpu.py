"""GPU timings, with the device named and the baselines in the same run.

    python -m bench.gpu [--rays 1000000] [--cells 128] [--repeats 10]
    NUMBA_ENABLE_CUDASIM=1 NUMBA_DISABLE_JIT=1 python -m bench.gpu --smoke

On a machine with an NVIDIA GPU and numba-cuda (``pip install -e ".[cuda]"``):

- **Batches:** exact ``trace_many(device="cuda")`` of ``--rays`` random rays
  through the ``--cells``^3 grid of ``bench.run``, end to end (rays from the
  host, results left on the device), against an Amanatides-Woo traversal of
  the same-size Cartesian box run the same way on the GPU (an O(1) bound per
  ray, a prefix sum, each ray into its region, a prefix sum, a copy to exact
  size), and against one CPU thread (``parallel=False``) on a part of the rays.
- **Integration:** a 640 x 480 scan of the table scene (and the Motorcycle
  frame, with scikit-image), sensor at the centre and 10 cm off it, into a
  map on the GPU, next to the CPU map on all threads.
- **Cones:** 1,000- and 10,000-ray cones with ``trace_cone`` and
  ``fixation_probability`` on the GPU.
- **Start:** a fresh process's first ``device="cuda"`` call with an empty
  kernel cache, then again with the cache it wrote.

Every GPU time is the best of ``--repeats`` calls, each ended by
``cuda.synchronize()``. ``--smoke`` runs every step at toy sizes (under the
CUDA simulator, to check this script) and writes nothing. Writes
bench/results/gpu.json and gpu.md.
"""

import argparse
import json
import time

import numba
import numpy as np
from numba import cuda

import logsph_trace as lt
from bench.cone import GAZE, ORIGIN, fixation_map
from bench.occupancy import scans
from bench.workload import fresh_processes, make_box, make_grid, make_rays, write_results
from logsph_trace import _cuda
from logsph_trace.kernels.baselines import amanatides_woo as cartesian

# ---- the Amanatides-Woo baseline, run as the exact backend runs --------------------------------


@_cuda.kernel
def _box_bound_kernel(origins, directions, low, size, shape, bounds):
    row = cuda.grid(1)
    if row < origins.shape[0]:
        bounds[row] = cartesian.box_bound(origins, directions, row, low, size, shape)


@_cuda.kernel
def _box_trace_kernel(origins, directions, low, size, shape, regions, cells, t_enter, t_exit,
                      counts):
    row = cuda.grid(1)
    if row < origins.shape[0]:
        counts[row] = cartesian.trace_box_ray(origins, directions, row, low, size, shape, cells,
                                              t_enter, t_exit, regions[row])


def box_many(box, origins, directions):
    """Amanatides-Woo of unit rays on the GPU, into exact-size CSR arrays on the device.

    With the exact backend's workspace, scan and compaction, so that the two
    differ in their traversals only.
    """
    n = origins.shape[0]
    low, size = np.asarray(box.low, dtype=np.float64), np.asarray(box.voxel_size, dtype=np.float64)
    shape = np.asarray(box.shape, dtype=np.int64)
    with _cuda.working() as workspace:
        d_origins = _cuda._on_device(workspace, "origins", origins)
        d_directions = _cuda._on_device(workspace, "directions", directions)
        d_low, d_size, d_shape = (_cuda._on_device(workspace, name, value) for name, value in
                                  (("low", low), ("size", size), ("shape", shape)))
        bounds = workspace.take("bounds", (n,), np.int64)
        _cuda._launch(_box_bound_kernel, n, d_origins, d_directions, d_low, d_size, d_shape,
                      bounds)
        regions = _cuda.exclusive_scan(bounds, workspace.take("regions", (n + 1,), np.int64),
                                       workspace)
        room = max(int(_cuda._fetch(regions[n:])[0]), 1)
        loose_cells = workspace.take("loose cells", (room, 3), np.int32)
        loose_enter = workspace.take("loose enter", (room,), np.float64)
        loose_exit = workspace.take("loose exit", (room,), np.float64)
        counts = workspace.take("counts", (n,), np.int64)
        _cuda._launch(_box_trace_kernel, n, d_origins, d_directions, d_low, d_size, d_shape,
                      regions, loose_cells, loose_enter, loose_exit, counts)
        offsets = _cuda.exclusive_scan(counts, cuda.device_array(n + 1, dtype=np.int64),
                                       workspace)
        total = int(_cuda._fetch(offsets[n:])[0])
        cells = cuda.device_array((max(total, 1), 3), dtype=np.int32)
        t_enter, t_exit = cuda.device_array(max(total, 1)), cuda.device_array(max(total, 1))
        _cuda._launch(_cuda._compact_kernel, n, regions, offsets, loose_cells, loose_enter,
                      loose_exit, cells, t_enter, t_exit)
    return offsets, cells[:total], t_enter[:total], t_exit[:total]


# ---- timing ------------------------------------------------------------------------------------

def gpu_best(call, repeats):
    """(best seconds of ``repeats`` calls, each synchronised, the last result)."""
    best, result = np.inf, None
    for _ in range(repeats):
        cuda.synchronize()
        start = time.perf_counter()
        result = call()
        cuda.synchronize()
        best = min(best, time.perf_counter() - start)
    return best, result


def cpu_best(call, repeats):
    best, result = np.inf, None
    for _ in range(repeats):
        start = time.perf_counter()
        result = call()
        best = min(best, time.perf_counter() - start)
    return best, result


def device_name():
    if numba.config.ENABLE_CUDASIM:
        return "CUDA simulator"
    name = cuda.get_current_device().name
    return name.decode() if isinstance(name, bytes) else str(name)


def batches(n_rays, cells, repeats, cpu_rays):
    grid, box = make_grid(cells), make_box(cells)
    origins, directions = make_rays(n_rays)
    lt.trace_many(grid, origins[:64], directions[:64], device="cuda")  # compile first
    box_many(box, origins[:64], directions[:64])
    exact_s, traces = gpu_best(lambda: lt.trace_many(grid, origins, directions, device="cuda"),
                               repeats)
    box_s, (offsets, box_cells, _, _) = gpu_best(lambda: box_many(box, origins, directions),
                                                 repeats)
    # The baseline's cells are the CPU's (checked on a sample, so a wrong
    # bound cannot flatter it).
    sample = slice(0, min(n_rays, 2000))
    want = box.trace_many(origins[sample], directions[sample], parallel=False)
    got = box_cells.copy_to_host()[: int(offsets[sample.stop])]
    if not np.array_equal(got, want.cells):
        raise AssertionError("the GPU Amanatides-Woo disagrees with the CPU's")
    voxels, box_voxels = int(traces.cells.shape[0]), int(box_cells.shape[0])
    part = slice(0, min(n_rays, cpu_rays))
    cpu_s, cpu_traces = cpu_best(
        lambda: lt.trace_many(grid, origins[part], directions[part], parallel=False), 1)
    return {
        "rays": n_rays, "cells_per_axis": cells,
        "exact_s": exact_s, "exact_voxels": voxels,
        "exact_ns_per_voxel": 1e9 * exact_s / voxels, "exact_rays_per_s": n_rays / exact_s,
        "box_s": box_s, "box_voxels": box_voxels, "box_ns_per_voxel": 1e9 * box_s / box_voxels,
        "cpu_rays": part.stop, "cpu_s": cpu_s,
        "cpu_ns_per_voxel": 1e9 * cpu_s / cpu_traces.cells.shape[0],
    }


def integration(repeats, smoke):
    grid = lt.Grid(0.3, 10.0, 64, 360, 180) if not smoke else lt.Grid(0.3, 10.0, 8, 12, 6)
    rows = []
    for scene, label, sensor, points in scans():
        if smoke:
            points = points[::2000]
        on_gpu = lt.OccupancyGrid(grid, device="cuda").integrate(points, sensor)
        on_cpu = lt.OccupancyGrid(grid).integrate(points, sensor)
        if not np.array_equal(on_gpu.to_host().log_odds, on_cpu.log_odds):
            raise AssertionError(f"{scene}, {label}: the GPU map differs from the CPU's")
        gpu_s, _ = gpu_best(lambda: on_gpu.integrate(points, sensor), repeats)
        cpu_s, _ = cpu_best(lambda: on_cpu.integrate(points, sensor), repeats)
        rows.append({"scan": scene, "sensor": label, "points": int(points.shape[0]),
                     "gpu_ms": 1e3 * gpu_s, "cpu_ms": 1e3 * cpu_s,
                     "cpu_threads": numba.get_num_threads()})
    return rows


def cones(repeats, smoke):
    grid = lt.Grid(0.3, 10.0, 64, 360, 180) if not smoke else lt.Grid(0.3, 10.0, 8, 12, 6)
    on_cpu = fixation_map(grid)
    on_gpu = lt.OccupancyGrid(grid, log_odds=on_cpu.log_odds, device="cuda")
    half_angle = np.radians(5.0)
    rows = []
    for n_rays in ((20, 40) if smoke else (1000, 10_000)):
        cone_s, cone = gpu_best(lambda: lt.trace_cone(grid, ORIGIN, GAZE, half_angle,
                                                      n_rays=n_rays, device="cuda"), repeats)
        fix_s, fixation = gpu_best(lambda: lt.fixation_probability(
            on_gpu, ORIGIN, GAZE, half_angle=half_angle, n_rays=n_rays), repeats)
        want = lt.trace_cone(grid, ORIGIN, GAZE, half_angle, n_rays=n_rays)
        if not np.array_equal(cone.cells, want.cells):
            raise AssertionError(f"{n_rays}-ray cone: the GPU's cells differ from the CPU's")
        cpu_s, _ = cpu_best(lambda: lt.fixation_probability(
            on_cpu, ORIGIN, GAZE, half_angle=half_angle, n_rays=n_rays), repeats)
        rows.append({"rays": n_rays, "cells": len(cone), "cone_ms": 1e3 * cone_s,
                     "fixation_ms": 1e3 * fix_s, "cpu_fixation_ms": 1e3 * cpu_s,
                     "top_cell": fixation.cells[0].tolist() if len(fixation) else None})
    return rows


START = """
import time
start = time.perf_counter()
import numpy as np, logsph_trace as lt
imported = time.perf_counter()
lt.trace_many(lt.Grid(0.3, 10.0, 8, 12, 6), [[0, 0, -5.0]], [[0, 0, 1.0]], device="cuda")
from numba import cuda; cuda.synchronize()
print(imported - start, time.perf_counter() - imported)
"""


def start_times():
    """(import s, first device call s) in a fresh process: cold cache, then warm."""
    (cold_import, cold_call), (warm_import, warm_call) = (run[-2:] for run in
                                                          fresh_processes(START))
    return {"cold_import_s": cold_import, "cold_first_call_s": cold_call,
            "cached_import_s": warm_import, "cached_first_call_s": warm_call}


def report(record):
    b = record["batches"]
    lines = [
        f"device: {record['device']}; CPU: {record['cpu_threads']} Numba threads",
        "",
        f"**Batches:** {b['rays']:,} random rays, {b['cells_per_axis']}^3 cells, rays from the "
        "host, results on the device",
        "",
        "| method | voxels | best (ms) | ns/voxel | rays/s | over GPU Amanatides-Woo (per voxel) |",
        "|---|---:|---:|---:|---:|---:|",
        f"| exact, GPU | {b['exact_voxels']:,} | {1e3 * b['exact_s']:.2f} | "
        f"{b['exact_ns_per_voxel']:.3f} | {b['exact_rays_per_s']:.3g} | "
        f"{b['exact_ns_per_voxel'] / b['box_ns_per_voxel']:.2f}x |",
        f"| Amanatides-Woo, GPU | {b['box_voxels']:,} | {1e3 * b['box_s']:.2f} | "
        f"{b['box_ns_per_voxel']:.3f} | {b['rays'] / b['box_s']:.3g} | 1.00x |",
        f"| exact, 1 CPU thread ({b['cpu_rays']:,} rays) | | {1e3 * b['cpu_s']:.1f} | "
        f"{b['cpu_ns_per_voxel']:.1f} | {b['cpu_rays'] / b['cpu_s']:.3g} | |",
        "",
        "**Integration** (640 x 480 scans, the map on the GPU; CPU on all threads):",
        "",
        "| scan | sensor | points | GPU (ms) | CPU (ms) |",
        "|---|---|---:|---:|---:|",
        *[f"| {r['scan']} | {r['sensor']} | {r['points']:,} | {r['gpu_ms']:.2f} | "
          f"{r['cpu_ms']:.1f} |" for r in record["integration"]],
        "",
        "**Cones** (5 degrees, the table scene's map on the GPU):",
        "",
        "| rays | cells | trace_cone (ms) | fixation_probability (ms) | CPU fixation (ms) |",
        "|---:|---:|---:|---:|---:|",
        *[f"| {r['rays']:,} | {r['cells']:,} | {r['cone_ms']:.2f} | {r['fixation_ms']:.2f} | "
          f"{r['cpu_fixation_ms']:.2f} |" for r in record["cones"]],
    ]
    if "start" in record:
        s = record["start"]
        lines += ["", f"**Start:** a fresh process, empty kernel cache: import "
                  f"{s['cold_import_s']:.2f} s, first device call {s['cold_first_call_s']:.1f} s; "
                  f"with the cache it wrote: import {s['cached_import_s']:.2f} s, first call "
                  f"{s['cached_first_call_s']:.1f} s"]
    return "\n".join(lines)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rays", type=int, default=1_000_000)
    parser.add_argument("--cells", type=int, default=128)
    parser.add_argument("--repeats", type=int, default=10)
    parser.add_argument("--cpu-rays", type=int, default=100_000,
                        help="rays for the one-thread CPU baseline (default 100,000)")
    parser.add_argument("--smoke", action="store_true",
                        help="toy sizes, nothing written: checks the script (simulator)")
    args = parser.parse_args(argv)
    _cuda.require()
    if args.smoke:
        args.rays, args.cells, args.repeats, args.cpu_rays = 64, 8, 1, 64
    record = {
        "device": device_name(), "cpu_threads": numba.get_num_threads(),
        "batches": batches(args.rays, args.cells, args.repeats, args.cpu_rays),
        "integration": integration(args.repeats, args.smoke),
        "cones": cones(args.repeats, args.smoke),
    }
    if not args.smoke:
        record["start"] = start_times()
        write_results("gpu", argv, report(record), record)
    else:
        print(report(record))
        print(json.dumps({"smoke": "ok"}))


if __name__ == "__main__":
    main()
