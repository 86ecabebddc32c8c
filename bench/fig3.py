"""Fig. 3 of the paper, reproduced: the worked example's cells, as a table and four panels.

    python -m bench.fig3

The gaze of section 3.1, in decimetres: origin (0, 20, 20), direction
(-0.3, -0.01, 0); rho in (10, 80), full theta and phi. The paper does not give
N or the increments; we choose N = 10 radial cells with the paper's spacing
(Eq. 3) and 10-degree increments (36 x 18 angular cells). Writes
bench/results/fig3.png and fig3.md (the cells of every method).
"""

import sys
from pathlib import Path

import numpy as np

import logsph_trace as lt
from bench.workload import write_results
from logsph_trace._files import save_figure

RESULTS = Path(__file__).resolve().parent / "results"
ORIGIN = (0.0, 20.0, 20.0)
DIRECTION = (-0.3, -0.01, 0.0)


def main(argv=None):
    import matplotlib

    matplotlib.use("Agg")
    from logsph_trace.plot import trace_figure

    grid = lt.Grid.from_increments(10.0, 80.0, 10, d_theta=10.0, d_phi=10.0, spacing="paper")
    exact = lt.trace(grid, ORIGIN, DIRECTION)
    bisect = lt.trace(grid, ORIGIN, DIRECTION, method="bisect")  # the paper's default_t
    thibaudeau = lt.trace(grid, ORIGIN, DIRECTION, method="thibaudeau")
    same = np.array_equal(thibaudeau.cells, exact.cells)
    bisect_keys = {tuple(c) for c in bisect.cells.tolist()}
    bounds = grid.cell_bounds(exact.cells)
    lines = [
        f"{grid}; gaze origin {ORIGIN} dm, direction {DIRECTION}.",
        "",
        "| # | i | j | k | t_enter (dm) | t_exit (dm) | rho range (dm) | theta (deg) | phi (deg) "
        "| bisect (default_t = 1.5531) |",
        "|---:|---:|---:|---:|---:|---:|---|---|---|---|",
    ]
    rows = zip(exact.cells, exact.t_enter, exact.t_exit, bounds)
    for n, ((i, j, k), t0, t1, b) in enumerate(rows):
        lines.append(
            f"| {n} | {i} | {j} | {k} | {t0:.3f} | {t1:.3f} | {b[0]:.2f}-{b[1]:.2f} "
            f"| {np.degrees(b[2]):.0f} to {np.degrees(b[3]):.0f} "
            f"| {np.degrees(b[4]):.0f} to {np.degrees(b[5]):.0f} "
            f"| {'reported' if (i, j, k) in bisect_keys else '**missed**'} |"
        )
    lines += ["", f"exact: {len(exact)} cells; bisect with the paper's default_t: {len(bisect)} "
                  f"cells ({len(exact) - len(bisect)} missed); thibaudeau "
                  f"{'reports the same cells as exact' if same else 'DIFFERS from exact'}."]
    text = "\n".join(lines)
    write_results("fig3", argv, text, {
        "cells": exact.cells.tolist(), "t_enter": exact.t_enter.tolist(),
        "t_exit": exact.t_exit.tolist(), "bisect_cells": bisect.cells.tolist()})
    fig = trace_figure(grid, ORIGIN, DIRECTION, exact, unit="dm",
                       title="Gaze tracing example (paper Fig. 3), exact method, decimetres")
    save_figure(fig, RESULTS / "fig3.png", dpi=110)
    print(f"wrote {RESULTS / 'fig3.png'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
