"""Peak memory and time of a parallel trace_many against its output (issue 11).

Run from a checkout: ``python bench/parallel_memory.py [N_RAYS]`` (default 300,000 random
rays on the 128^3 grid of bench.run). Prints the best of two serial and two parallel calls,
tracemalloc's peak over one parallel call divided by the output's bytes, and the bytes the
result keeps alive (its arrays' bases) divided by the output's bytes.
"""

import sys
import time
import tracemalloc

sys.path.insert(0, ".")  # the checkout this is run from, not an installed copy

import numpy as np  # noqa: E402

import logsph_trace as lt  # noqa: E402


def main(n_rays):
    grid = lt.Grid(0.1, 10.0, 128, 128, 128)
    rng = np.random.default_rng(1)
    origins = rng.uniform(-8, 8, (n_rays, 3))
    directions = rng.normal(size=(n_rays, 3))
    lt.trace_many(grid, origins[:2000], directions[:2000], parallel=True)  # compile
    best = {}
    for parallel in (False, True, False, True):
        start = time.perf_counter()
        traces = lt.trace_many(grid, origins, directions, parallel=parallel)
        best[parallel] = min(best.get(parallel, np.inf), time.perf_counter() - start)
    arrays = lambda t: (t.offsets, t.cells, t.t_enter, t.t_exit)  # noqa: E731
    output = sum(a.nbytes for a in arrays(traces))
    del traces
    tracemalloc.start()
    traces = lt.trace_many(grid, origins, directions, parallel=True)
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    held = sum((a if a.base is None else a.base).nbytes for a in arrays(traces))
    print(f"serial {best[False] * 1e3:.0f} ms  parallel {best[True] * 1e3:.0f} ms  "
          f"x{best[False] / best[True]:.2f}  "
          f"ns/voxel par {best[True] / traces.cells.shape[0] * 1e9:.1f}  "
          f"peak/output {peak / output:.3f}  held/output {held / output:.3f}")


if __name__ == "__main__":
    main(int(sys.argv[1]) if len(sys.argv) > 1 else 300_000)
