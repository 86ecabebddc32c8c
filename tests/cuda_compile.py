"""Compile every GPU kernel with numba-cuda, for an H100, on a machine without a GPU.

The simulator checks (``cuda_check.py``) run the per-ray code as Python, so
they cannot tell whether numba-cuda compiles it: an allocation, a numpy call
or a CPU-only intrinsic reached from a kernel passes there and fails on the
device. This module closes that gap in two steps, each in its own process:

``record FILE``
    Under the CUDA simulator, drive every GPU entry point of the package
    once and save the argument types each kernel of ``logsph_trace._cuda``
    was launched with.
``compile FILE``
    With numba-cuda itself, compile each kernel with those types to PTX for
    compute capability 9.0 (``numba.cuda.compile_ptx``, no GPU needed), and
    assemble the PTX with ``ptxas`` from the CUDA wheels; print per kernel
    its registers and spills, and exit non-zero unless every kernel did both.

``tests/test_cuda.py`` runs the two when numba-cuda is installed (CI does it
in a virtual environment of its own: ``.ci/run``).
"""

import os
import pickle
import re
import subprocess
import sys
import tempfile

CC = (9, 0)  # the H100 of the project's device


def _host(value):
    """A simulator device array as the numpy array it holds (tuples too)."""
    if hasattr(value, "_ary"):
        return value._ary
    if isinstance(value, tuple):
        parts = [_host(v) for v in value]
        return type(value)(*parts) if hasattr(value, "_fields") else tuple(parts)
    return value


def _kernel_names(module, simulated):
    """Names of the module's CUDA kernels (simulated: ``FakeCUDAKernel``)."""
    if simulated:
        return {name for name, value in vars(module).items()
                if type(value).__name__ == "FakeCUDAKernel"}
    from numba.cuda.dispatcher import CUDADispatcher

    return {name for name, value in vars(module).items() if isinstance(value, CUDADispatcher)}


def record(path):
    """Drive every GPU entry point under the simulator; save each kernel's argument types."""
    import numba
    import numpy as np
    from numba import cuda, types

    import logsph_trace as lt
    from logsph_trace import _cuda

    assert numba.config.ENABLE_CUDASIM, "record runs under NUMBA_ENABLE_CUDASIM=1"
    seen = {}
    launch = _cuda._launch

    def recording(kernel, n, *args):
        signature = []
        for arg in args:
            kind = numba.typeof(_host(arg))
            if isinstance(kind, types.Array):  # device arrays are never read-only
                kind = kind.copy(readonly=False)
            signature.append(kind)
        seen.setdefault(kernel.fn.__name__, set()).add(tuple(signature))
        return launch(kernel, n, *args)

    _cuda._launch = recording
    rng = np.random.default_rng(1)
    grid = lt.Grid(0.3, 10.0, 8, 16, 8)
    origins = rng.normal(scale=4.0, size=(40, 3))
    directions = rng.normal(size=(40, 3))
    lt.trace_many(grid, origins, directions, device="cuda")
    lt.trace_many(grid, origins[:1], directions, t_max=np.full(40, 3.0), device="cuda")
    lt.trace_many(grid, cuda.to_device(origins.astype(np.float32)), cuda.to_device(directions),
                  t_max=cuda.to_device(np.full(40, 3, dtype=np.float32)), device="cuda")
    grid.cell_of(origins, device="cuda")
    grid.cell_of(cuda.to_device(origins), device="cuda")
    lt.trace_cones(grid, [0.1, 0.2, 0.3], directions[:3], 0.05, n_rays=30, device="cuda")
    occupancy = lt.OccupancyGrid(grid, device="cuda")
    points = rng.normal(scale=3.0, size=(200, 3))
    occupancy.integrate(points, [0.0, 0.0, 0.0])
    occupancy.integrate(points, [0.1, 0.0, 0.05], max_range=2.0)
    occupancy.decay(0.9)
    lt.fixation_probability(occupancy, [0.1, 0.2, 0.3], [0.0, 0.0, 1.0], 0.05)
    lt.gaze_targets(occupancy, [0.1, 0.2, 0.3], [0.0, 0.0, 1.0], threshold=0.5)
    missing = _kernel_names(_cuda, simulated=True) - set(seen)
    assert not missing, f"kernels no entry point launched: {sorted(missing)}"
    with open(path, "wb") as file:
        pickle.dump({name: sorted(signatures, key=str) for name, signatures in seen.items()},
                    file)


def _assemble(ptx, ptxas):
    """Assemble ``ptx`` for ``CC``; return (registers, spill bytes) or raise with ptxas' words."""
    with tempfile.TemporaryDirectory() as folder:
        source = os.path.join(folder, "kernel.ptx")
        with open(source, "w") as file:
            file.write(ptx)
        result = subprocess.run([ptxas, f"-arch=sm_{CC[0]}{CC[1]}", "-v", source, "-o",
                                 os.path.join(folder, "kernel.cubin")],
                                capture_output=True, text=True)
    log = result.stdout + result.stderr
    if result.returncode != 0:
        raise RuntimeError(f"ptxas failed: {log[-2000:]}")
    # One entry function per module (numba-cuda inlines the device functions);
    # ptxas reports any other function before it.
    registers = [int(n) for n in re.findall(r"Used (\d+) registers", log)]
    spills = [int(a) + int(b) for a, b in
              re.findall(r"(\d+) bytes spill stores, (\d+) bytes spill loads", log)]
    return registers[-1], spills[-1]


def compile_all(path):
    """Compile and assemble every recorded kernel; return (rows, failures)."""
    import types as builtin_types

    from cuda.pathfinder import find_nvidia_binary_utility
    from numba.cuda import compile_ptx, dispatcher

    from logsph_trace import _cuda

    # A kernel's calls into the package's @jit functions compile them as
    # device functions, for the current device's compute capability; there
    # is no device here, so that question gets the H100's answer.
    if not hasattr(dispatcher, "get_current_device"):
        raise RuntimeError("this numba-cuda has no dispatcher.get_current_device to answer "
                           "for the missing GPU; the cuda extra pins the versions it was "
                           "written for")
    dispatcher.get_current_device = lambda: builtin_types.SimpleNamespace(compute_capability=CC)
    ptxas = find_nvidia_binary_utility("ptxas")
    if ptxas is None:
        raise RuntimeError("ptxas not found: pip install 'logsph_trace[cuda]' brings it")
    with open(path, "rb") as file:
        seen = pickle.load(file)
    rows, failures = [], []
    missing = _kernel_names(_cuda, simulated=False) - set(seen)
    failures += [f"{name}: not recorded" for name in sorted(missing)]
    for name, signatures in sorted(seen.items()):
        for signature in signatures:
            try:
                ptx, _ = compile_ptx(getattr(_cuda, name).py_func, signature, cc=CC)
                registers, spills = _assemble(ptx, ptxas)
            except Exception as error:  # every kernel is tried; the report names each failure
                failures.append(f"{name}{signature}: {type(error).__name__}: {error}")
            else:
                rows.append((name, len(signature), registers, spills))
    return rows, failures


if __name__ == "__main__":
    step, path = sys.argv[1], sys.argv[2]
    if step == "record":
        record(path)
        print("recorded")
    else:
        rows, failures = compile_all(path)
        print(f"| kernel (sm_{CC[0]}{CC[1]}) | arguments | registers | spill bytes |")
        print("|---|---:|---:|---:|")
        for name, arguments, registers, spills in rows:
            print(f"| {name} | {arguments} | {registers} | {spills} |")
        print("\n".join(failures))
        print(f"compiled {len(rows)} of {len(rows) + len(failures)}")
        sys.exit(1 if failures else 0)
