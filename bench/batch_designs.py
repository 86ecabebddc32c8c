"""Two designs for a parallel batch, timed in one run: the ordered chunks against regions.

    python -m bench.batch_designs             # 2 threads (all this machine has, at most)
    python -m bench.batch_designs --threads 16 --rounds 12

``trace_many`` on two threads or more traces small chunks of rays, taken in
order by the threads, each into a small scratch that its thread copies to
the chunk's place once the chunks before it are counted
(``_batching.run_ordered``). The plainer design it is measured against:
a bound pass over every ray (``_batching.bound_counts``), its prefix sum,
each chunk traced into its own region of a reused scratch
(``exact.trace_chunks``), then one parallel copy that closes the gaps
into the output (``compact``, below). Both write fresh output arrays, as
``trace_many`` does, and give the same traces (checked). Rounds alternate
the two, after the serial pass; best and median of the rounds. Writes
``bench/results/batch_designs.json`` (and ``.md``).
"""

import argparse
import statistics
import time

import numba
import numpy as np
from numba import prange

import logsph_trace as lt
from bench.workload import make_grid, make_rays, write_results
from logsph_trace import _batching, _validate
from logsph_trace.kernels import exact
from logsph_trace.traces import Traces

CHUNK_RAYS = 64


@numba.njit(parallel=True, nogil=True, cache=True)
def compact(starts, regions, ends, offsets, cells, t_enter, t_exit, out_cells, out_enter,
            out_exit, first_out):
    """Copy chunk c's segments (``regions[c]:ends[c]``) to ``first_out[c]`` on; shift offsets."""
    for c in prange(starts.shape[0] - 1):
        shift = regions[c] - first_out[c]
        for s in range(regions[c], ends[c]):
            out_cells[s - shift, 0] = cells[s, 0]
            out_cells[s - shift, 1] = cells[s, 1]
            out_cells[s - shift, 2] = cells[s, 2]
            out_enter[s - shift] = t_enter[s]
            out_exit[s - shift] = t_exit[s]
        for r in range(starts[c] + 1, starts[c + 1] + 1):
            offsets[r] -= shift


def regions_design(grid, origins, directions, t_max):
    """Bound pass, offsets, each chunk into its region of a reused scratch, compaction."""
    n_rays = origins.shape[0]
    starts = np.append(np.arange(0, n_rays, CHUNK_RAYS), n_rays)
    args = grid.kernel_args()
    cumulative = np.zeros(n_rays + 1, dtype=np.int64)
    _batching.bound_counts(origins, directions, args, cumulative[1:])
    np.cumsum(cumulative, out=cumulative)
    regions = cumulative[starts]
    cells, t_enter, t_exit = _batching.scratch_segments(int(regions[-1]), "regions", keep=True)
    offsets = np.empty(n_rays + 1, dtype=np.int64)
    offsets[0] = 0
    ends = exact.trace_chunks(starts, regions, origins, directions, t_max, args, cells, t_enter,
                              t_exit, offsets, exact.TRACE)
    first_out = np.zeros(starts.shape[0], dtype=np.int64)
    np.cumsum(ends - regions[:-1], out=first_out[1:])
    out = _batching.segment_arrays(int(first_out[-1]))
    compact(starts, regions, ends, offsets, cells, t_enter, t_exit, *out, first_out)
    return Traces(offsets, *out)


def measure(rounds, threads):
    """Best and median ms of each design over ``rounds`` alternated rounds."""
    numba.set_num_threads(min(threads, numba.config.NUMBA_NUM_THREADS))
    grid = make_grid()
    origins, directions = make_rays()
    units, unit_directions = _validate.rays(origins, directions)
    far = np.full(len(units), np.inf)
    calls = {
        "serial": lambda: lt.trace_many(grid, origins, directions, parallel=False),
        "ordered chunks (trace_many)": lambda: lt.trace_many(grid, origins, directions),
        "regions and compaction": lambda: regions_design(grid, units, unit_directions, far),
    }
    want = calls["serial"]()
    for name, call in calls.items():  # compile, and check the output is the same
        got = call()
        for field in ("offsets", "cells", "t_enter", "t_exit"):
            np.testing.assert_array_equal(getattr(got, field), getattr(want, field), err_msg=name)
    times = {name: [] for name in calls}
    for _ in range(rounds):
        for name, call in calls.items():
            start = time.perf_counter()
            call()
            times[name].append(time.perf_counter() - start)
    return {"threads": numba.get_num_threads(), "rounds": rounds, "segments": int(len(want.cells)),
            "best_ms": {k: min(v) * 1e3 for k, v in times.items()},
            "median_ms": {k: statistics.median(v) * 1e3 for k, v in times.items()}}


def report(result):
    """Return the record's page."""
    serial = result["best_ms"]["serial"]
    ordered = result["best_ms"]["ordered chunks (trace_many)"]
    lines = [f"bench.run's 100,000 rays ({result['segments']:,} segments), "
             f"{result['threads']} threads, {result['rounds']} alternated rounds; fresh output "
             "arrays.", "",
             "| design | best ms | median ms | speed-up over serial | over the ordered chunks |",
             "|---|---:|---:|---:|---:|"]
    for name, best in result["best_ms"].items():
        lines.append(f"| {name} | {best:.1f} | {result['median_ms'][name]:.1f} "
                     f"| {serial / best:.2f}x | {best / ordered:.2f}x |")
    return "\n".join(lines)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rounds", type=int, default=8)
    parser.add_argument("--threads", type=int, default=numba.config.NUMBA_NUM_THREADS)
    args = parser.parse_args(argv)
    result = measure(args.rounds, args.threads)
    write_results("batch_designs", argv, report(result), result)


if __name__ == "__main__":
    main()
