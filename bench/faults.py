"""First touch in a parallel trace_many: what fresh output costs per thread count.

    python -m bench.faults                                   # 100,000 rays, 128^3 cells
    python -m bench.faults --rays 1000000 --threads 1,2,4,8,16
    python -m bench.faults --prime 0         # no memory primed first (see below)

A call into fresh arrays pays for the first write to every page of its
output (the OS clears a page then), and so does the serial call that every
speed-up is taken against. Whether ``trace_many`` reaches its target on many
threads turns on how that part scales on the machine, so this times it
apart, alternated in one run, best of ``--repeats`` per thread count:

* the serial call (``parallel=False``) into fresh arrays and into reused,
  already faulted-in buffers (``out=TraceBuffers``): the baselines;
  every call here is timed from the checked, unit rays on (``bench.run``
  times the input check);
* the ordered chunks (``trace_many``'s path from 3 threads on, forced here
  on every thread count, on as many workers) into fresh output faulted in
  ahead of the chunks by the workers (``touch_ahead``, as shipped), into
  fresh output faulted in by the chunks' own copies, and into reused buffers;
* first touch alone: fresh arrays of the output's size, one write per
  4 KiB page (``ordered.touch_rows``, as the workers do it), in blocks of
  ``ordered.TOUCH_ROWS`` rows shared out over the threads (``prange``).

Before timing, twice the output's size of memory is written once and freed
(``--prime MB`` sets it, 0 skips it; ``bench.workload.prime_memory``): on a
fresh virtual machine the first touch of memory is the host's fault too, which is not
what this measures. Writes ``bench/results/faults.json`` and ``.md``.
"""

import numba
import numpy as np

import logsph_trace as lt
from bench.workload import (
    best_time,
    make_grid,
    make_rays,
    prime_memory,
    prime_note,
    thread_arguments,
    write_results,
)
from logsph_trace import _batching, _validate
from logsph_trace.kernels.ordered import TOUCH_ROWS, touch_rows


# Not cached: it inlines the package's ``touch_rows``, and Numba would check
# a cached copy against this file only (see ``logsph_trace._jit``).
@numba.njit(parallel=True)
def touch_in_blocks(cells, t_enter, t_exit):
    """Fault in every page of the three arrays, a block of ``TOUCH_ROWS`` rows per iteration."""
    rows = t_enter.shape[0]
    for block in numba.prange((rows + TOUCH_ROWS - 1) // TOUCH_ROWS):
        first = block * TOUCH_ROWS
        touch_rows(cells, t_enter, t_exit, first, min(rows, first + TOUCH_ROWS))


def first_touch(length):
    """Fresh output arrays of ``length`` segments, faulted in on all threads."""
    arrays = _batching.segment_arrays(length)
    touch_in_blocks(*arrays)
    return arrays


CALLS = ("ordered_touch_ahead", "ordered_copies_fault", "ordered_reused", "first_touch")


def measure(n_rays, cells, repeats, counts, prime=None):
    """``prime``: MB to write once before timing (None: twice the output; 0: none)."""
    grid = make_grid(cells)
    origins, directions = _validate.rays(*make_rays(n_rays))
    far = np.full(n_rays, np.inf)
    serial_buffers, ordered_buffers = lt.TraceBuffers(), lt.TraceBuffers()
    want = _batching.run_exact(grid, origins, directions, far, False, serial_buffers)
    segments = int(want.cells.shape[0])
    for workers in counts:  # compile, fill the buffers, and check the paths agree
        for got in (_batching.run_exact_ordered(grid, origins, directions, far, workers,
                                                ordered_buffers),
                    _batching.run_exact_ordered(grid, origins, directions, far, workers,
                                                touch_ahead=False)):
            assert np.array_equal(got.offsets, want.offsets)
            assert np.array_equal(got.cells, want.cells)
            assert np.array_equal(got.t_exit, want.t_exit)
    first_touch(TOUCH_ROWS)
    # Two outputs live at once: a call's, and the one before it.
    primed = prime_memory(2 * segments * _batching.SEGMENT_BYTES / 2**20 if prime is None
                          else prime)

    serial_calls = {
        "serial_fresh": lambda: _batching.run_exact(grid, origins, directions, far, False),
        "serial_reused": lambda: _batching.run_exact(grid, origins, directions, far, False,
                                                     serial_buffers),
    }

    def calls(threads):
        return {
            "ordered_touch_ahead": lambda: _batching.run_exact_ordered(
                grid, origins, directions, far, threads),
            "ordered_copies_fault": lambda: _batching.run_exact_ordered(
                grid, origins, directions, far, threads, touch_ahead=False),
            "ordered_reused": lambda: _batching.run_exact_ordered(
                grid, origins, directions, far, threads, ordered_buffers),
            "first_touch": lambda: first_touch(segments),
        }

    most = numba.get_num_threads()
    best = {(name, threads): np.inf for name in CALLS for threads in counts}
    best.update({name: np.inf for name in serial_calls})
    for _ in range(repeats):  # alternated, so that all see the same machine
        for name, call in serial_calls.items():  # one thread whatever the count
            best[name] = min(best[name], best_time(call, 1)[0])
        for threads in counts:
            numba.set_num_threads(threads)
            for name, call in calls(threads).items():
                best[name, threads] = min(best[name, threads], best_time(call, 1)[0])
    numba.set_num_threads(most)
    serial, serial_reused = best["serial_fresh"], best["serial_reused"]
    rows = []
    for threads in counts:
        ms = {name: best[name, threads] * 1e3 for name in CALLS}
        rows.append({
            "threads": threads,
            "ms": ms,
            "ordered_fresh_over_serial_fresh": serial / best["ordered_touch_ahead", threads],
            "ordered_reused_over_serial_reused": serial_reused / best["ordered_reused", threads],
            "faulting_in_the_call_ms": ms["ordered_touch_ahead"] - ms["ordered_reused"],
            "first_touch_speedup": best["first_touch", 1] / best["first_touch", threads],
        })
    return {"rays": n_rays, "cells_per_axis": cells, "repeats": repeats, "segments": segments,
            "output_bytes": segments * _batching.SEGMENT_BYTES,
            "serial_fresh_ms": serial * 1e3, "serial_reused_ms": serial_reused * 1e3,
            "primed_mb_s": primed, "rows": rows}


def table(result):
    lines = [
        f"{result['rays']:,} random rays of bench.run, {result['cells_per_axis']}^3 cells, "
        f"{result['segments']:,} segments ({result['output_bytes'] / 1e6:,.0f} MB of output); "
        f"best of {result['repeats']} alternated rounds, ms; {prime_note(result['primed_mb_s'])}",
        "",
        f"Serial call (parallel=False): {result['serial_fresh_ms']:.1f} ms into fresh arrays, "
        f"{result['serial_reused_ms']:.1f} ms into reused buffers.",
        "",
        "| threads | ordered, fresh, touch ahead | ordered, fresh, copies fault | ordered, reused "
        "| faulting in, within the call | speed-up, fresh | speed-up, reused | first touch alone "
        "| first-touch speed-up |",
        "|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for row in result["rows"]:
        ms = row["ms"]
        lines.append(
            f"| {row['threads']} | {ms['ordered_touch_ahead']:.1f} "
            f"| {ms['ordered_copies_fault']:.1f} | {ms['ordered_reused']:.1f} "
            f"| {row['faulting_in_the_call_ms']:.1f} "
            f"| {row['ordered_fresh_over_serial_fresh']:.2f}x "
            f"| {row['ordered_reused_over_serial_reused']:.2f}x "
            f"| {ms['first_touch']:.1f} | {row['first_touch_speedup']:.2f}x |")
    lines += ["", "ordered: the chunks trace_many takes from 3 threads on, forced on as many "
              "workers as threads; touch ahead: fresh output faulted in by the workers ahead of "
              "the chunks (as shipped); copies fault: by the chunks' copies; reused: into "
              "buffers faulted in already; faulting in, within the call: touch ahead minus "
              "reused; speed-up, fresh: the serial call into fresh arrays over the ordered "
              "touch-ahead call (trace_many's figure from 3 threads on); speed-up, reused: "
              "both into reused buffers; first touch alone: fresh arrays of the output's size "
              "faulted in, page by page, on that many threads"]
    return "\n".join(lines)


def main(argv=None):
    args, counts = thread_arguments(__doc__.splitlines()[0], 7, argv, prime="twice the output",
                                    rays=100_000, cells=128)
    result = measure(args.rays, args.cells, args.repeats, counts, args.prime)
    write_results("faults", argv, table(result), {"result": result})


if __name__ == "__main__":
    main()
