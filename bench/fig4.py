"""Fig. 4 of the paper, reproduced: time per ray against voxels crossed, four methods.

    python -m bench.fig4                       # 6 resolutions, 200 rays, 200 repetitions
    python -m bench.fig4 --sizes 8 16 32 --repetitions 20

For each grid resolution N (N^3 cells; rho 0.1-10 m, log spacing, full angles)
the same 200 random rays are traced by ``exact``, ``bisect`` (the paper's
default_t = 1.5531 m) and ``thibaudeau``, and through an N^3 Cartesian cube by
Amanatides-Woo, each ``--repetitions`` times (200 in the paper), single
thread. A point is the median time per ray against the mean number of voxels
a ray crosses (for the log-spherical methods the voxels it truly crosses, so
a method that skips cells is not credited with fewer). Writes
bench/results/fig4.json and fig4.png, and a table of ns per voxel at the
largest size with exact's speed-up over each method, all from one run.
"""

import argparse
import time
from pathlib import Path

import numba
import numpy as np

import logsph_trace as lt
from bench.workload import make_box, make_grid, make_rays, write_results
from logsph_trace._files import save_figure

RESULTS = Path(__file__).resolve().parent / "results"
METHODS = ("exact", "bisect", "thibaudeau", "amanatides_woo")
LABELS = {
    "exact": "exact (this library)",
    "bisect": "Algorithm 1, bisection (default_t = 1.5531 m)",
    "thibaudeau": "Thibaudeau-style (sort all crossings)",
    "amanatides_woo": "Amanatides-Woo (Cartesian)",
}


def _median_time(func, repetitions):
    times = np.empty(repetitions)
    for rep in range(repetitions):
        start = time.perf_counter()
        func()
        times[rep] = time.perf_counter() - start
    return float(np.median(times))


def measure(sizes, n_rays, repetitions):
    numba.set_num_threads(1)
    origins, directions = make_rays(n_rays, seed=4)
    points = {name: [] for name in METHODS}
    for size in sizes:
        grid = make_grid(size)
        box = make_box(size)
        runs = {
            "exact": lambda: lt.trace_many(grid, origins, directions, parallel=False),
            "bisect": lambda: lt.trace_many(grid, origins, directions, method="bisect",
                                            parallel=False),
            "thibaudeau": lambda: lt.trace_many(grid, origins, directions, method="thibaudeau",
                                                parallel=False),
            "amanatides_woo": lambda: box.trace_many(origins, directions, parallel=False),
        }
        crossed = runs["exact"]().cells.shape[0] / n_rays
        for name, run in runs.items():
            result = run()  # warm-up (compilation) and the voxel count
            voxels = result.cells.shape[0] / n_rays if name == "amanatides_woo" else crossed
            seconds = _median_time(run, repetitions) / n_rays
            points[name].append({
                "cells_per_axis": size,
                "voxels_per_ray": voxels,
                "reported_per_ray": result.cells.shape[0] / n_rays,
                "ms_per_ray": seconds * 1e3,
                "ns_per_voxel": seconds / voxels * 1e9,
            })
        print(f"N = {size}: " + ", ".join(
            f"{name} {points[name][-1]['ms_per_ray'] * 1e3:.1f} us/ray" for name in METHODS
        ), flush=True)
    return points


def plot(points, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.4, 4.4))
    for name, marker in zip(METHODS, "osD^"):
        xs = [p["voxels_per_ray"] for p in points[name]]
        ys = [p["ms_per_ray"] for p in points[name]]
        ax.loglog(xs, ys, marker=marker, label=LABELS[name])
    ax.set_xlabel("voxels crossed per ray")
    ax.set_ylabel("time per ray (ms), single thread")
    ax.set_title("Traversal time vs voxels crossed (cf. paper Fig. 4)")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    save_figure(fig, path, dpi=120)
    plt.close(fig)


def table(points):
    last = {name: points[name][-1] for name in METHODS}
    exact_ns = last["exact"]["ns_per_voxel"]
    lines = [
        f"At {last['exact']['cells_per_axis']}^3 cells "
        f"({last['exact']['voxels_per_ray']:.0f} voxels "
        "crossed per ray), single thread, one run:",
        "",
        "| method | voxels reported / crossed per ray | ns per voxel | ns per voxel / exact's |",
        "|---|---:|---:|---:|",
    ]
    for name in METHODS:
        p = last[name]
        lines.append(
            f"| {LABELS[name]} | {p['reported_per_ray']:.1f} / {p['voxels_per_ray']:.1f} "
            f"| {p['ns_per_voxel']:.0f} | {p['ns_per_voxel'] / exact_ns:.2f}x |"
        )
    return "\n".join(lines)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=[8, 16, 32, 64, 128, 256])
    parser.add_argument("--rays", type=int, default=200)
    parser.add_argument("--repetitions", type=int, default=200)
    parser.add_argument("--out", type=Path, default=RESULTS / "fig4.json")
    args = parser.parse_args(argv)

    points = measure(args.sizes, args.rays, args.repetitions)
    text = table(points)
    write_results("fig4", argv, text, {
        "rays": args.rays, "repetitions": args.repetitions, "points": points,
    }, out=args.out)
    plot(points, args.out.with_suffix(".png"))
    print(f"wrote {args.out}, {args.out.with_suffix('.png')}")


if __name__ == "__main__":
    main()
