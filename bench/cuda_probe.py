"""Does the exact kernel's per-ray source compile and agree under numba-cuda?

    python -m bench.cuda_probe                 # on a machine with a CUDA GPU and numba-cuda
    NUMBA_ENABLE_CUDASIM=1 NUMBA_DISABLE_JIT=1 python -m bench.cuda_probe --rays 200 --cells 16

Calls ``kernels.exact.trace_span`` -- the same source the CPU runs -- from a
``numba.cuda`` kernel, one thread per ray, with per-ray scratch in global
memory, and compares every ray with ``trace_many`` on the CPU: cells equal,
distances within 1e-12 relative (a GPU may contract multiply-adds). This is a
compile-and-agree probe, not the CUDA backend: nothing here is tuned.
Writes ``bench/results/cuda_probe.md``, except under the simulator.
"""

import argparse
import os
import time

import numpy as np
from numba import cuda

import logsph_trace as lt
from bench.workload import write_results
from logsph_trace.kernels import exact, geometry


@cuda.jit
def trace_kernel(origins, directions, t_max, grid, times, zones, lookups, cells, t_enter, t_exit,
                 ends, counts, worst):
    """One thread per ray: the CPU's ``exact.trace_span`` of one ray, writing from
    ``row * worst`` on.

    ``grid`` is the ``GridArrays`` bundle, its arrays on the device.
    """
    row = cuda.grid(1)
    if row < origins.shape[0]:
        end, _ = exact.trace_span(row, row + 1, origins, directions, t_max, grid, times[row],
                                  zones[row], lookups[row], False, cells, t_enter, t_exit,
                                  ends, row * worst, (row + 1) * worst)
        counts[row] = end - row * worst


def probe(n_rays, cells):
    grid = lt.Grid(0.1, 10.0, cells, cells, cells)
    rng = np.random.default_rng(9)
    origins = rng.uniform(-12.0, 12.0, (n_rays, 3))
    directions = rng.normal(size=(n_rays, 3))
    directions /= np.linalg.norm(directions, axis=1)[:, None]
    # A tenth of the rays aimed at the centre and at the y axis, from random eyes.
    origins[: n_rays // 20] = rng.uniform(-3.0, 3.0, (n_rays // 20, 3))
    directions[: n_rays // 20] = -origins[: n_rays // 20]
    directions[: n_rays // 20] /= np.linalg.norm(directions[: n_rays // 20], axis=1)[:, None]
    axis_rows = slice(n_rays // 20, n_rays // 10)
    target = np.zeros((n_rays // 10 - n_rays // 20, 3))
    target[:, 1] = rng.uniform(-5.0, 5.0, target.shape[0])
    directions[axis_rows] = target - origins[axis_rows]
    directions[axis_rows] /= np.linalg.norm(directions[axis_rows], axis=1)[:, None]

    args = grid.kernel_args()
    size = int(geometry.scratch_size(*grid.shape))
    worst = int(geometry.max_segments(*grid.shape))
    device = type(args)(*[cuda.to_device(np.ascontiguousarray(a)) if isinstance(a, np.ndarray)
                           else a for a in args])
    d_origins = cuda.to_device(origins)
    d_directions = cuda.to_device(directions)
    times = cuda.device_array((n_rays, 3, size), dtype=np.float64)
    zones = cuda.device_array((n_rays, 3, size), dtype=np.int64)
    lookups = cuda.device_array((n_rays, 8), dtype=np.int64)
    cells_out = cuda.device_array((n_rays * worst, 3), dtype=np.int32)
    enter_out = cuda.device_array(n_rays * worst, dtype=np.float64)
    exit_out = cuda.device_array(n_rays * worst, dtype=np.float64)
    counts = cuda.device_array(n_rays, dtype=np.int64)
    ends = cuda.device_array(n_rays + 1, dtype=np.int64)
    t_max = cuda.to_device(np.full(n_rays, np.inf))
    threads = 128
    blocks = (n_rays + threads - 1) // threads
    start = time.perf_counter()
    trace_kernel[blocks, threads](d_origins, d_directions, t_max, device, times, zones, lookups,
                                  cells_out, enter_out, exit_out, ends, counts, worst)
    cuda.synchronize()
    first_call = time.perf_counter() - start

    counts = counts.copy_to_host()
    cells_gpu = cells_out.copy_to_host()
    enter_gpu = enter_out.copy_to_host()
    exit_gpu = exit_out.copy_to_host()
    cpu = lt.trace_many(grid, origins, directions)
    mismatched, worst_error = 0, 0.0
    for row in range(n_rays):
        want = cpu[row]
        got = slice(row * worst, row * worst + int(counts[row]))
        if not np.array_equal(cells_gpu[got], want.cells):
            mismatched += 1
            continue
        if len(want):
            scale = np.maximum(np.abs(want.t_exit), 1.0)
            error_exit = np.max(np.abs(exit_gpu[got] - want.t_exit) / scale)
            error_enter = np.max(np.abs(enter_gpu[got] - want.t_enter) / scale)
            worst_error = max(worst_error, float(error_exit), float(error_enter))
    name = "CUDA simulator" if os.environ.get("NUMBA_ENABLE_CUDASIM") == "1" else \
        cuda.get_current_device().name
    if isinstance(name, bytes):
        name = name.decode()
    return {
        "device": str(name), "rays": n_rays, "cells_per_axis": cells,
        "segments": int(counts.sum()), "rays_with_other_cells": mismatched,
        "max_relative_distance_error": worst_error,
        "first_call_s_compile_included": first_call,
    }


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rays", type=int, default=20_000)
    parser.add_argument("--cells", type=int, default=32)
    args = parser.parse_args(argv)
    result = probe(args.rays, args.cells)
    text = "\n".join([
        f"device: {result['device']}",
        f"{result['rays']:,} rays (a tenth aimed at the centre or the y axis), "
        f"{result['cells_per_axis']}^3 cells, {result['segments']:,} segments",
        f"rays whose cells differ from the CPU's: {result['rays_with_other_cells']}",
        f"largest relative distance difference: {result['max_relative_distance_error']:.2e}",
        f"first launch, compilation included: {result['first_call_s_compile_included']:.1f} s",
    ])
    if result["device"] == "CUDA simulator":
        # A check of the probe itself: the record stays the device's.
        print(text + "\n(simulator: bench/results/cuda_probe.md left as it is)")
    else:
        write_results("cuda_probe", argv, text, result)


if __name__ == "__main__":
    main()
