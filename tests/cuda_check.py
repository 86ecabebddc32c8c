"""Rays for the CUDA backend's equality checks, and the check itself.

Used in two ways: ``tests/test_cuda.py`` writes the rays and the CPU's
traces to a file and runs this module under Numba's CUDA simulator in a
subprocess (``python tests/cuda_check.py FILE``), where the per-ray code runs
as Python inside the simulated kernels; on a machine with a GPU the same
check runs in the test process itself.
"""

import sys

import numpy as np
from singular import CLASSES, singular_rays

import logsph_trace as lt

GRIDS = {
    "log": lambda: lt.Grid(0.3, 10.0, 12, 24, 12),
    "partial": lambda: lt.Grid(0.5, 6.0, 10, 16, 8, theta_range=(-1.0, 2.5),
                               phi_range=(-0.6, 1.1), spacing="uniform"),
    "paper": lambda: lt.Grid(1.0, 30.0, 12, 36, 18, spacing="paper"),
}


def cases(n_random, n_singular, seed=5):
    """{name: (grid name, origins, directions, t_max)} over every grid kind:
    random rays, a third of them cut short, and each near-singular class."""
    rng = np.random.default_rng(seed)
    out = {}
    for name, make in GRIDS.items():
        grid = make()
        reach = 1.3 * grid.rho_max
        origins = rng.uniform(-reach, reach, (n_random, 3))
        directions = rng.normal(size=(n_random, 3))
        t_max = np.full(n_random, np.inf)
        t_max[::3] = rng.uniform(0.0, 2.0 * reach, t_max[::3].shape)
        out[f"{name} random"] = (name, origins, directions, t_max)
        for kind in CLASSES:
            o, d, _ = singular_rays(rng, grid, kind, n_singular, offsets=(0.0, 1e-12, 1e-6))
            out[f"{name} {kind}"] = (name, o, d, np.full(o.shape[0], np.inf))
    return out


def cpu_traces(all_cases):
    """The CPU's traces of every case, as arrays to save."""
    arrays = {}
    for key, (grid_name, origins, directions, t_max) in all_cases.items():
        traces = lt.trace_many(GRIDS[grid_name](), origins, directions, t_max=t_max)
        for field in ("offsets", "cells", "t_enter", "t_exit"):
            arrays[f"{key}|{field}"] = getattr(traces, field)
        arrays[f"{key}|rays"] = np.c_[origins, directions, t_max]
        arrays[f"{key}|grid"] = np.array(grid_name)
    return arrays


def compare(arrays):
    """Trace every case with ``device="cuda"``; return the mismatches found (a list of str)."""
    problems = []
    keys = sorted({key.split("|")[0] for key in arrays})
    for key in keys:
        rays = arrays[f"{key}|rays"]
        grid = GRIDS[str(arrays[f"{key}|grid"])]()
        got = lt.trace_many(grid, rays[:, :3], rays[:, 3:6], t_max=rays[:, 6],
                            device="cuda").to_host()
        if not np.array_equal(got.offsets, arrays[f"{key}|offsets"]):
            problems.append(f"{key}: segment counts differ")
            continue
        if not np.array_equal(got.cells, arrays[f"{key}|cells"]):
            problems.append(f"{key}: cells differ")
        for field in ("t_enter", "t_exit"):
            want = arrays[f"{key}|{field}"]
            scale = np.maximum(np.abs(want), 1.0)
            error = np.max(np.abs(getattr(got, field) - want) / scale, initial=0.0)
            if error > 1e-12:
                problems.append(f"{key}: {field} differs by {error:.2e} (relative)")
    return problems


if __name__ == "__main__":
    from logsph_trace import _cuda

    with np.load(sys.argv[1]) as saved:
        arrays = dict(saved)
    if len(sys.argv) > 2:  # few rays in flight: many rounds of the trace loop
        _cuda.RAYS_IN_FLIGHT = int(sys.argv[2])
    if len(sys.argv) > 3:  # no memory to spare: one ray in flight, one part per ray
        _cuda.MEMORY_SHARE = 1e-15
    problems = compare(arrays)
    print("\n".join(problems) if problems else "all equal")
    sys.exit(1 if problems else 0)
