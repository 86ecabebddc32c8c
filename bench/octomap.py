"""Our map against OctoMap: the same real cloud into both, in one run.

    python -m bench.octomap [--repeats 5] [--sample 5000]

The Middlebury 2014 Motorcycle frame (343,274 points) goes into OctoMap 1.10
through ``pyoctomap`` (``insertPointCloud``, its default sensor model, one
thread) at 0.05 and 0.07 m, and into our 64 x 360 x 180 log map (rho 0.3-8
m) on all Numba threads and on one, with the camera at the centre and 10 cm
off it; alternated, best of ``--repeats``. Agreement is counted on a sample
of points: the end point's cell occupied, and the point 80% of the way from
the camera free, in each map. Needs the ``bench`` extra (pyoctomap,
scikit-image). Writes bench/results/octomap.json and octomap.md.
"""

import argparse
import time

import numba
import numpy as np

import logsph_trace as lt
from bench.workload import motorcycle_points, write_results

SENSORS = (("at the centre", (0.0, 0.0, 0.0)), ("10 cm off", (0.06, 0.08, 0.0)))
RESOLUTIONS = (0.05, 0.07)


def _octree(points, sensor, resolution):
    import pyoctomap

    tree = pyoctomap.OcTree(resolution)
    tree.insertPointCloud(points, np.asarray(sensor, dtype=np.float64))
    return tree


def _octree_state(tree, points):
    """1 occupied, 0 free, -1 unknown, per point."""
    states = np.empty(points.shape[0], dtype=np.int8)
    for row, point in enumerate(points):
        node = tree.search(point)
        states[row] = -1 if node is None else int(tree.isNodeOccupied(node))
    return states


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--sample", type=int, default=5000)
    args = parser.parse_args(argv)
    grid = lt.Grid(0.3, 8.0, 64, 360, 180)
    most = numba.get_num_threads()
    rng = np.random.default_rng(0)
    rows = []
    for label, sensor in SENSORS:
        points = motorcycle_points(sensor)
        origin = np.asarray(sensor, dtype=np.float64)
        sample = points[rng.choice(points.shape[0], args.sample, replace=False)]
        before = origin + 0.8 * (sample - origin)
        lt.OccupancyGrid(grid).integrate(points, sensor)  # compiled before timing
        best = {}
        for _ in range(args.repeats):
            for threads in sorted({1, most}):
                numba.set_num_threads(threads)
                occupancy = lt.OccupancyGrid(grid)
                start = time.perf_counter()
                occupancy.integrate(points, sensor)
                seconds = time.perf_counter() - start
                name = f"ours, {threads} thread" + ("s" if threads > 1 else "")
                best[name] = min(best.get(name, np.inf), seconds)
            numba.set_num_threads(most)
            for resolution in RESOLUTIONS:
                start = time.perf_counter()
                tree = _octree(points, sensor, resolution)
                name = f"OctoMap {resolution} m"
                best[name] = min(best.get(name, np.inf), time.perf_counter() - start)
        ours_end = occupancy.log_odds[tuple(grid.cell_of(sample).T)]
        ours_before = occupancy.log_odds[tuple(grid.cell_of(before).T)]
        agreement = {"ours": (float(np.mean(ours_end > 0)), float(np.mean(ours_before < 0)))}
        for resolution in RESOLUTIONS:
            tree = _octree(points, sensor, resolution)
            agreement[f"OctoMap {resolution} m"] = (
                float(np.mean(_octree_state(tree, sample) == 1)),
                float(np.mean(_octree_state(tree, before) == 0)))
        for name, seconds in best.items():
            occupied, free = agreement["ours" if name.startswith("ours") else name]
            rows.append({"sensor": label, "map": name, "ms": 1e3 * seconds,
                         "rays_per_s": points.shape[0] / seconds,
                         "end_occupied": occupied, "before_free": free})
    lines = [
        f"Middlebury 2014 Motorcycle, {points.shape[0]:,} points; ours: {grid}; "
        f"best of {args.repeats}, alternated; agreement on {args.sample:,} sampled points",
        "",
        "| camera | map | time (ms) | rays/s | end point occupied | 80% point free | "
        "OctoMap 0.05 m / this |",
        "|---|---|---:|---:|---:|---:|---:|",
    ]
    for row in rows:
        octomap = next(r["ms"] for r in rows if r["sensor"] == row["sensor"]
                       and r["map"] == "OctoMap 0.05 m")
        lines.append(f"| {row['sensor']} | {row['map']} | {row['ms']:.1f} | "
                     f"{row['rays_per_s']:.3g} | {100 * row['end_occupied']:.1f}% | "
                     f"{100 * row['before_free']:.1f}% | {octomap / row['ms']:.1f}x |")
    write_results("octomap", argv, "\n".join(lines), {"rows": rows})


if __name__ == "__main__":
    main()
