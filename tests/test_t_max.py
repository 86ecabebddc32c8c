"""Tracing up to a distance: the full trace cut at t_max, on every path."""

import numpy as np
import pytest
from conftest import GRIDS, random_rays

import logsph_trace as lt


def _cut(trace, t_max):
    keep = trace.t_enter < t_max
    return trace.cells[keep], trace.t_enter[keep], np.minimum(trace.t_exit[keep], t_max)


def test_t_max_cuts_the_full_trace(grid):
    rng = np.random.default_rng(51)
    origins, directions = random_rays(rng, grid, 600)
    t_max = rng.uniform(0.0, 2.5 * grid.rho_max, 600)
    t_max[:20] = 0.0
    t_max[20:40] = np.inf
    full = lt.trace_many(grid, origins, directions)
    # Cut exactly at a crossing of the full trace, too.
    for row in range(40, 80):
        if len(full[row]) > 1:
            t_max[row] = full[row].t_exit[0]
    cut = lt.trace_many(grid, origins, directions, t_max=t_max)
    serial = lt.trace_many(grid, origins, directions, t_max=t_max, parallel=False)
    for name in ("offsets", "cells", "t_enter", "t_exit"):
        np.testing.assert_array_equal(getattr(cut, name), getattr(serial, name))
    for row in range(600):
        cells, t_enter, t_exit = _cut(full[row], t_max[row])
        np.testing.assert_array_equal(cut[row].cells, cells, err_msg=f"ray {row}")
        np.testing.assert_array_equal(cut[row].t_enter, t_enter)
        np.testing.assert_array_equal(cut[row].t_exit, t_exit)


def test_t_max_on_the_parallel_paths():
    from logsph_trace import _batching, _validate

    grid = GRIDS["paper_dm"]()
    rng = np.random.default_rng(52)
    origins, directions = random_rays(rng, grid, 5000)
    t_max = rng.uniform(0.0, 100.0, 5000)
    serial = lt.trace_many(grid, origins, directions, t_max=t_max, parallel=False)
    o, d = _validate.rays(origins, directions)
    for result in (
        lt.trace_many(grid, origins, directions, t_max=t_max),
        _batching.run_exact_ordered(grid, o, d, t_max, workers=3),
    ):
        np.testing.assert_array_equal(result.offsets, serial.offsets)
        np.testing.assert_array_equal(result.t_exit, serial.t_exit)


@pytest.mark.parametrize(
    "t_max, match",
    [
        (-1.0, r"t_max must be >= 0 \(inf allowed\); row 0 is -1.0"),
        (np.nan, "t_max must be >= 0"),
        ([1.0, 2.0], r"t_max must be a number or have shape \(3,\)"),
        ("far", "t_max must be a number or an array of numbers"),
    ],
)
def test_bad_t_max(t_max, match):
    grid = GRIDS["log_full"]()
    with pytest.raises(ValueError, match=match):
        lt.trace_many(grid, np.zeros((3, 3)), np.ones((3, 3)), t_max=t_max)


def test_t_max_is_for_the_exact_method():
    grid = GRIDS["log_full"]()
    with pytest.raises(ValueError, match="t_max is supported by method='exact' only"):
        lt.trace(grid, [1.0, 0.0, 0.0], [0.0, 0.0, 1.0], method="bisect", t_max=2.0)
