"""``python -m logsph_trace``: trace the paper's worked example (Fig. 3) and print its cells.

The gaze of section 3.1: origin (0, 20, 20), direction (-0.3, -0.01, 0), in
decimetres, rho in (10, 80), full theta and phi, the paper's radial spacing
(Eq. 3) with N = 10 and 10-degree angular increments.
"""

import sys
import time

import numpy as np

from . import Grid, trace, trace_many


def main(argv=None):
    """Print the worked example's cells and time a 100,000-ray batch."""
    grid = Grid.from_increments(10.0, 80.0, 10, d_theta=10.0, d_phi=10.0, spacing="paper")
    origin, direction = (0.0, 20.0, 20.0), (-0.3, -0.01, 0.0)
    start = time.perf_counter()
    result = trace(grid, origin, direction)
    elapsed = time.perf_counter() - start
    print(f"{grid}")
    print(f"gaze origin {origin} dm, direction {direction}: {len(result)} cells "
          f"(first call {elapsed:.2f} s: compiling the kernels, or loading them from the cache)")
    print(f"{'i':>3} {'j':>3} {'k':>3}  {'t_enter':>8} {'t_exit':>8}  {'theta deg':>16} {'phi deg':>14}")
    bounds = grid.cell_bounds(result.cells)
    for (i, j, k), t0, t1, b in zip(result.cells, result.t_enter, result.t_exit, bounds):
        theta = f"[{np.degrees(b[2]):.0f}, {np.degrees(b[3]):.0f})"
        phi = f"[{np.degrees(b[4]):.0f}, {np.degrees(b[5]):.0f})"
        print(f"{i:3d} {j:3d} {k:3d}  {t0:8.3f} {t1:8.3f}  {theta:>16} {phi:>14}")
    rng = np.random.default_rng(0)
    origins = rng.uniform(-60, 60, (100_000, 3))
    directions = rng.normal(size=(100_000, 3))
    trace_many(grid, origins[:4096], directions[:4096])  # compile (or load) the parallel kernels
    start = time.perf_counter()
    traces = trace_many(grid, origins, directions)
    elapsed = time.perf_counter() - start
    print(f"batch: {len(traces):,} random rays, {traces.cells.shape[0]:,} segments "
          f"in {elapsed * 1e3:.0f} ms ({len(traces) / elapsed:,.0f} rays/s, all threads)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
