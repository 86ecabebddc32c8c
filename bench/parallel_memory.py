"""Peak memory and time of a parallel trace_many against its output.

Run from a checkout: ``python bench/parallel_memory.py [N_RAYS]`` (default 300,000 random
rays on the 128^3 grid of bench.run). For the serial pass, the public parallel call (ordered
chunks) and the ordered chunks forced (at least three workers), it prints
the best time of two calls and, over one more call, as multiples of the output's bytes:

* resident: the growth of the process's peak resident memory (Linux's ``VmHWM``, restarted
  through ``/proc/self/clear_refs``), what the issue's memory target is about;
* allocated: tracemalloc's peak, which counts address space reserved but never touched;
* held: the bytes the result's arrays keep allocated (their bases).

Resident figures include the pages at the output's edges (huge pages of 2 MiB); the
ordered chunks' scratch is kept between calls, so a call after the first adds none.
"""

import sys
import time
import tracemalloc

sys.path.insert(0, ".")  # the checkout this is run from, not an installed copy

import numba  # noqa: E402
import numpy as np  # noqa: E402

import logsph_trace as lt  # noqa: E402
from logsph_trace import _batching, _validate  # noqa: E402


def status(field):
    """A ``/proc/self/status`` figure (``VmRSS``, ``VmHWM``) in bytes."""
    with open("/proc/self/status") as lines:
        for line in lines:
            if line.startswith(field + ":"):
                return int(line.split()[1]) * 1024
    raise KeyError(field)


def reset_peak():
    """Restart the kernel's count of peak resident memory (``VmHWM``); False where it cannot."""
    try:
        with open("/proc/self/clear_refs", "w") as clear_refs:
            clear_refs.write("5")
        return True
    except OSError:
        return False


def resident_growth(call):
    """(result, growth of peak resident memory during ``call()``), or (result, None)."""
    if not reset_peak():
        return call(), None
    before = status("VmRSS")
    result = call()
    return result, status("VmHWM") - before


def main(n_rays):
    grid = lt.Grid(0.1, 10.0, 128, 128, 128)
    rng = np.random.default_rng(1)
    origins, directions = _validate.rays(rng.uniform(-8, 8, (n_rays, 3)),
                                         rng.normal(size=(n_rays, 3)))
    far = np.full(n_rays, np.inf)
    workers = max(3, numba.get_num_threads())
    paths = {
        "serial": lambda: lt.trace_many(grid, origins, directions, parallel=False),
        "parallel": lambda: lt.trace_many(grid, origins, directions, parallel=True),
        f"ordered ({workers} workers)": lambda: _batching.run_exact_ordered(
            grid, origins, directions, far, workers),
    }
    print(f"{n_rays:,} rays, 128^3 cells, {numba.get_num_threads()} threads")
    for name, call in paths.items():
        call()  # compile, scratch
        best = min(_timed(call) for _ in range(2))
        traces, grown = resident_growth(call)
        arrays = (traces.offsets, traces.cells, traces.t_enter, traces.t_exit)
        output = sum(a.nbytes for a in arrays)
        held = sum((a if a.base is None else a.base).nbytes for a in arrays)
        del traces, arrays
        tracemalloc.start()
        call()
        peak = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
        resident = "n/a" if grown is None else f"{grown / output:.3f}"
        print(f"{name:>20}: {best * 1e3:6.0f} ms  output {output / 2**20:.0f} MiB  "
              f"resident/output {resident}  allocated/output {peak / output:.3f}  "
              f"held/output {held / output:.3f}")


def _timed(call):
    start = time.perf_counter()
    call()
    return time.perf_counter() - start


if __name__ == "__main__":
    main(int(sys.argv[1]) if len(sys.argv) > 1 else 300_000)
