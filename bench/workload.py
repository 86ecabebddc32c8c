"""The benchmark workload, shared by the script and the pytest-benchmark suite.

A BVM-like log-spherical grid (rho 0.1..10 m, full circle, full elevation) and
rays whose origins are uniform in its ball and whose directions are uniform on
the sphere: a person standing anywhere in the robot's map, looking anywhere.
The Amanatides-Woo reference traces the same rays through the cube of equal
voxel count that holds the ball.
"""

import time

import numpy as np

import logsph_trace as lt
from logsph_trace.cartesian import CartesianGrid

RHO_MIN = 0.1
RHO_MAX = 10.0


def make_grid(cells=128):
    return lt.Grid(RHO_MIN, RHO_MAX, cells, cells, cells, spacing="log")


def make_box(cells=128):
    return CartesianGrid((-RHO_MAX,) * 3, (RHO_MAX,) * 3, (cells,) * 3)


def make_rays(n_rays=100_000, seed=0):
    rng = np.random.default_rng(seed)
    directions = rng.normal(size=(n_rays, 3))
    directions /= np.linalg.norm(directions, axis=1)[:, None]
    radial = rng.normal(size=(n_rays, 3))
    radial /= np.linalg.norm(radial, axis=1)[:, None]
    origins = radial * RHO_MAX * rng.random(n_rays)[:, None] ** (1 / 3)
    return origins, directions


def best_time(func, repeats):
    """(shortest wall time of ``repeats`` calls, the last result)."""
    best = np.inf
    result = None
    for _ in range(repeats):
        start = time.perf_counter()
        result = func()
        best = min(best, time.perf_counter() - start)
    return best, result


def write_results(name, argv, text, record):
    """Print ``text`` and write bench/results/<name>.json (``record`` plus the
    command and date) and <name>.md (the command, then ``text``)."""
    import json
    import sys
    from pathlib import Path

    results = Path(__file__).resolve().parent / "results"
    arguments = argv if argv is not None else sys.argv[1:]
    command = (f"python -m bench.{name} " + " ".join(arguments)).strip()
    print(text)
    results.mkdir(parents=True, exist_ok=True)
    stamped = {"command": command, "date": time.strftime("%Y-%m-%d %H:%M:%S %Z"), **record}
    (results / f"{name}.json").write_text(json.dumps(stamped, indent=2) + "\n")
    (results / f"{name}.md").write_text(f"`{command}`\n\n{text}\n")
