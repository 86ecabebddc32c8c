"""A fuzz of the exact kernel over every grid kind: no crash, hang, NaN, overlap or bad cell.

Origins range over twelve orders of magnitude (1e-6 to 1e6 of the grid's
scale) and directions over axis-aligned, nearly axis-aligned and random ones.
The default, 200,000 rays, takes a few seconds; ``pytest tests/test_fuzz.py
--fuzz-rays 5000000`` runs a longer one.
"""

import numpy as np
from conftest import GRIDS

import logsph_trace as lt


def _fuzz_rays(rng, grid, n):
    scale = grid.rho_max * 10.0 ** rng.uniform(-6, 6, n)
    origins = rng.normal(size=(n, 3))
    origins *= (scale / np.linalg.norm(origins, axis=1))[:, None]
    directions = rng.normal(size=(n, 3))
    axes = rng.random(n) < 0.2  # along an axis, or within a tiny angle of one
    m = int(axes.sum())
    directions[axes] = np.eye(3)[rng.integers(0, 3, m)] * rng.choice([-1, 1], (m, 1))
    directions[axes] += rng.normal(size=(m, 3)) * 10.0 ** rng.uniform(-17, -8, (m, 1))
    toward = rng.random(n) < 0.2  # at the centre, or just beside it
    directions[toward] = -origins[toward] + rng.normal(size=(toward.sum(), 3)) * grid.rho_min * 1e-9
    return origins, directions


def test_fuzz_every_grid_kind(fuzz_rays):
    rng = np.random.default_rng(11)
    per_grid = max(1, fuzz_rays // len(GRIDS))
    for name in sorted(GRIDS):
        grid = GRIDS[name]()
        origins, directions = _fuzz_rays(rng, grid, per_grid)
        serial = lt.trace_many(grid, origins, directions, parallel=False)
        parallel = lt.trace_many(grid, origins, directions, parallel=True)
        for field in ("offsets", "cells", "t_enter", "t_exit"):
            np.testing.assert_array_equal(getattr(parallel, field), getattr(serial, field))
        cells, t_enter, t_exit = serial.cells, serial.t_enter, serial.t_exit
        assert np.all(np.isfinite(t_enter)) and np.all(np.isfinite(t_exit)), name
        assert np.all(t_enter >= 0.0) and np.all(t_exit >= t_enter), name
        assert np.all(cells >= 0) and np.all(cells < np.array(grid.shape)), name
        same_ray = np.diff(serial.ray_index) == 0
        assert np.all(t_exit[:-1][same_ray] <= t_enter[1:][same_ray]), name  # no overlap
        assert np.all(serial.counts <= 2 * sum(grid.shape) + 8), name
