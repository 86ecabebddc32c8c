"""Occupancy integration kernel by kernel: where a scan's time goes per thread count.

    python -m bench.integrate_kernels [--threads 1,2,4,...] [--repeats 10]

``bench.occupancy`` times each scan whole and in three phases; this splits
the same four scans (the table scene and the Motorcycle frame, the sensor at
the centre and 10 cm off) into the kernels ``OccupancyGrid.integrate`` calls,
so that a kernel that stops scaling on many cores shows by name. Each kernel
(and each input check) is wrapped in a timer for the run; the off-centre
scan's ``mark_scan`` is split by its walk (all rays, the samples, the
others). "Python" is the rest of the call: argument handling, scratch and
glue, all on one thread. Best of ``--repeats`` scans per thread count
(alternated), with that scan's kernels; the speed-up of a kernel is its
one-thread time over its time at that count. Writes
bench/results/integrate_kernels.json and .md.
"""

import contextlib
import time
import types

import numba

import logsph_trace as lt
from bench.occupancy import scans
from bench.workload import thread_arguments, write_results
from logsph_trace import occupancy as occupancy_module

KERNELS = ("mark_radial", "apply_radial", "ray_extent", "bin_rays", "mark_scan", "ray_cone",
           "columns_in_view", "near_masks", "mark_candidates", "apply_scan")
CHECKS = ("vectors", "finite_rows", "point", "choice")
# The occupancy module's attributes the kernels are read through, and its checks'.
MODULES = ("_coherent", "_radial", "_update", "validate")
# mark_scan's walk argument (the 7th), by the kernels' names for it.
WALKS = ("WALK_ALL", "WALK_SAMPLES", "WALK_OTHERS")


@contextlib.contextmanager
def kernel_timers(times):
    """Time every kernel and input check ``integrate`` calls into ``times`` (ms), while open.

    The occupancy module reads its kernels and checks through module
    attributes (``MODULES``); they are swapped for namespaces of timed
    wrappers and put back on exit.
    """
    originals = {name: getattr(occupancy_module, name) for name in MODULES}
    walks = {getattr(originals["_coherent"], name): name[5:].lower() for name in WALKS}

    def timer(function, label, walk=False):
        def timed(*args, **kwargs):
            start = time.perf_counter()
            result = function(*args, **kwargs)
            name = f"{label} ({walks.get(args[6], '?')})" if walk else label
            times[name] = times.get(name, 0.0) + (time.perf_counter() - start) * 1e3
            return result
        return timed

    for attribute, module in originals.items():
        proxy = types.SimpleNamespace(**{
            name: getattr(module, name) for name in dir(module) if not name.startswith("__")})
        for name in (CHECKS if attribute == "validate" else KERNELS):
            if hasattr(module, name):
                label = f"check: {name}" if attribute == "validate" else name
                setattr(proxy, name, timer(getattr(module, name), label, name == "mark_scan"))
        setattr(occupancy_module, attribute, proxy)
    try:
        yield
    finally:
        for attribute, module in originals.items():
            setattr(occupancy_module, attribute, module)


def main(argv=None):
    args, counts = thread_arguments(__doc__.splitlines()[0], 10, argv)
    grid = lt.Grid(0.3, 10.0, 64, 360, 180)
    rows, lines = [], [f"{grid}; best of {args.repeats} scans per thread count, alternated; "
                       "ms, and in brackets the speed-up over the same part on 1 thread", ""]
    for scene, label, sensor, points in scans():
        occupancy = lt.OccupancyGrid(grid)
        occupancy.integrate(points, sensor)  # compiles or loads the kernels
        best = {}
        times = {}
        with kernel_timers(times):
            for _ in range(args.repeats):
                for threads in counts:
                    numba.set_num_threads(threads)
                    times.clear()
                    start = time.perf_counter()
                    occupancy.integrate(points, sensor)
                    total = (time.perf_counter() - start) * 1e3
                    if threads not in best or total < best[threads]["total_ms"]:
                        parts = dict(times)
                        parts["Python"] = total - sum(parts.values())
                        best[threads] = {"total_ms": total, "parts_ms": parts}
        numba.set_num_threads(max(counts))
        names = list(best[1]["parts_ms"])
        lines += [f"**{scene}, sensor {label}** ({points.shape[0]:,} points)", "",
                  "| part | " + " | ".join(f"{t} thread{'s' * (t > 1)}" for t in counts) + " |",
                  "|---|" + "---:|" * len(counts)]
        for name in ["total", *names]:
            one = best[1]["total_ms"] if name == "total" else best[1]["parts_ms"][name]
            cells = []
            for threads in counts:
                ms = (best[threads]["total_ms"] if name == "total"
                      else best[threads]["parts_ms"].get(name, 0.0))
                cells.append(f"{ms:.2f}" if threads == 1 or ms <= 0
                             else f"{ms:.2f} ({one / ms:.1f}x)")
            lines.append(f"| {name} | " + " | ".join(cells) + " |")
        lines.append("")
        rows.append({"scene": scene, "sensor": label, "points": int(points.shape[0]),
                     "best": {str(t): best[t] for t in counts}})
    lines.append("Python: the call's time outside the timed kernels and checks (one thread); "
                 "check: the input checks (the finite check of the points runs on all threads "
                 "from 32,768 rows)")
    write_results("integrate_kernels", argv, "\n".join(lines),
                  {"threads": counts, "rows": rows})


if __name__ == "__main__":
    main()
