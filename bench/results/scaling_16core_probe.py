import sys, time, numba, numpy as np
sys.path.insert(0, '.')
import logsph_trace as lt
from logsph_trace import _batching, _validate
from bench.workload import make_grid, make_rays
grid = make_grid(128); o, d = make_rays(1_000_000)
o, d = _validate.rays(o, d); args = grid.kernel_args(); far = np.full(len(o), np.inf)
lt.trace_many(grid, o[:5000], d[:5000], parallel=True); lt.trace_many(grid, o[:5000], d[:5000], parallel=False)
def best(f, n=3):
    b = 1e9
    for _ in range(n):
        t = time.perf_counter(); r = f(); b = min(b, time.perf_counter() - t)
    return b, r
numba.set_num_threads(1)
serial, tr = best(lambda: lt.trace_many(grid, o, d, parallel=False))
print(f"serial: {serial:.3f} s, {tr.cells.shape[0]:,} segments, {serial / tr.cells.shape[0] * 1e9:.1f} ns/voxel")
keep = {}
for n in (1, 2, 4, 8, 16):
    numba.set_num_threads(n)
    call, _ = best(lambda: lt.trace_many(grid, o, d, parallel=True))
    # the kernel alone into reused, pre-touched arrays
    held = {}
    def seg(length):
        if 'a' not in held or held['a'][0].shape[0] < length:
            held['a'] = _batching.segment_arrays(length)
            for a in held['a']: a.fill(0)
        return held['a']
    _batching.trace_regions(grid, o, d, far, args, n, seg)
    kernel, _ = best(lambda: _batching.trace_regions(grid, o, d, far, args, n, seg))
    print(f"{n:2d} threads: trace_many {call:.3f} s ({serial / call:.1f}x), kernel into pre-touched arrays {kernel:.3f} s ({serial / kernel:.1f}x)")
