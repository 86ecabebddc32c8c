"""Do threads contend on the shared grid bundle? (A check, kept for many-core machines.)

    python -m bench.shared_grid

Reading an array out of a ``GridArrays`` bundle takes a reference: an atomic
add on a counter that every thread reading the same bundle shares. This runs
the bound pass (``exact.bound_counts``'s work: each ray's set-up, no
stepping) over 100,000 random rays on 128^3, one task per thread, two ways in
alternating rounds: every task reading the one shared bundle, and every task
reading its own copy. On the 2-core test machine the two scaled alike
(bench/results/shared_grid.md), so the package does not copy; run it on a
many-core machine before concluding the same there. Best of ``--repeats``
rounds, 1 thread and all; writes bench/results/shared_grid.json and .md.
"""

import argparse
import time

import numba
import numpy as np
from numba import prange

from bench.workload import make_grid, make_rays, write_results
from logsph_trace import _validate
from logsph_trace.kernels import geometry
from logsph_trace.kernels.locate import GridArrays, per_log_of


@numba.njit
def private_grid(grid):
    """A copy of the bundle's arrays, for one task."""
    return GridArrays(
        grid.rho_edges.copy(), grid.rho_sq.copy(), grid.rho_kind,
        grid.theta_edges.copy(), grid.theta_sin.copy(), grid.theta_cos.copy(), grid.theta_kind,
        grid.theta_full,
        grid.phi_edges.copy(), grid.phi_tan2.copy(), grid.phi_nappe.copy(), grid.phi_kind,
        grid.phi_sin.copy(), grid.phi_cos.copy(), grid.phi_flat_from, grid.phi_flat_to,
    )


def _bounds(origins, directions, grid, bounds, first, last):
    lookups = np.empty(8, dtype=np.int64)
    per_log = per_log_of(grid.rho_edges, grid.rho_kind)
    for row in range(first, last):
        bounds[row] = geometry.ray_bound(origins, directions, row, grid, per_log, lookups)


_bounds = numba.njit(_bounds)


@numba.njit(parallel=True)
def shared(origins, directions, grid, bounds, tasks):
    n = origins.shape[0]
    for task in prange(tasks):
        _bounds(origins, directions, grid, bounds, task * n // tasks, (task + 1) * n // tasks)


@numba.njit(parallel=True)
def private(origins, directions, grid, bounds, tasks):
    n = origins.shape[0]
    for task in prange(tasks):
        _bounds(origins, directions, private_grid(grid), bounds, task * n // tasks,
                (task + 1) * n // tasks)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rays", type=int, default=100_000)
    parser.add_argument("--repeats", type=int, default=7)
    args = parser.parse_args(argv)
    grid = make_grid(128).kernel_args()
    origins, directions = _validate.rays(*make_rays(args.rays))
    bounds = np.empty(len(origins), dtype=np.int64)
    most = numba.get_num_threads()
    threads = sorted({1, most})
    best = {}
    for kernel in (shared, private):
        kernel(origins[:1000], directions[:1000], grid, bounds, 2)  # compile
    for _ in range(args.repeats):
        for count in threads:
            numba.set_num_threads(count)
            for name, kernel in (("shared", shared), ("private", private)):
                start = time.perf_counter()
                kernel(origins, directions, grid, bounds, count)
                seconds = time.perf_counter() - start
                best[name, count] = min(best.get((name, count), np.inf), seconds)
    numba.set_num_threads(most)
    lines = [f"bound pass, {args.rays:,} rays, 128^3, one task per thread, best of "
             f"{args.repeats} alternated rounds", "",
             "| grid arrays | " + " | ".join(f"{t} thread(s) ms" for t in threads)
             + " | speed-up |", "|---|" + "---:|" * (len(threads) + 1)]
    for name in ("shared", "private"):
        times = [best[name, t] * 1e3 for t in threads]
        lines.append(f"| {name} | " + " | ".join(f"{t:.1f}" for t in times)
                     + f" | {times[0] / times[-1]:.2f}x |")
    write_results("shared_grid", argv, "\n".join(lines),
                  {"threads": threads, "best_s": {f"{n} {t}": v for (n, t), v in best.items()}})


if __name__ == "__main__":
    main()
