"""The CUDA backend (``device="cuda"``) against the CPU.

CI has no GPU: the equality checks run under Numba's CUDA simulator in a
subprocess (``NUMBA_ENABLE_CUDASIM=1`` and ``NUMBA_DISABLE_JIT=1``, so the
per-ray code runs as Python inside the simulated kernels). On a machine with
a GPU the same checks run on the device; without one that test skips.
"""

import importlib.util
import os
import re
import subprocess
import sys
from pathlib import Path

import numba
import numpy as np
import pytest
from cuda_check import (
    cases,
    compare,
    cone_cases,
    cpu_cells,
    cpu_cones,
    cpu_gpu_inputs,
    cpu_maps,
    cpu_traces,
    gpu_input_cases,
    map_cases,
    point_cases,
)

import logsph_trace as lt

TESTS = Path(__file__).resolve().parent
REPO = TESTS.parent
GRID = lt.Grid(0.3, 10.0, 12, 24, 12)


def _all_equal_on_the_simulator(tmp_path, **arrays):
    """Save the CPU's answers, check the simulated GPU against them."""
    path = tmp_path / "cases.npz"
    np.savez(path, **arrays)
    result = _simulated([str(path)], tmp_path)
    assert result.returncode == 0, result.stdout + result.stderr
    assert result.stdout.strip() == "all equal"


def _python_path():
    """The tests and the repository first, then the caller's own PYTHONPATH (a
    machine may bring its packages that way, a numpy that numba-cuda takes)."""
    return os.pathsep.join([str(TESTS), str(REPO)]
                           + [p for p in os.environ.get("PYTHONPATH", "").split(os.pathsep) if p])


def _simulated(args, tmp_path):
    env = dict(os.environ, NUMBA_ENABLE_CUDASIM="1", NUMBA_DISABLE_JIT="1",
               PYTHONPATH=_python_path())
    return subprocess.run([sys.executable, str(TESTS / "cuda_check.py"), *args],
                          capture_output=True, text=True, env=env, cwd=tmp_path, timeout=600)


def test_simulated_gpu_traces_equal_the_cpu(tmp_path):
    # Every grid kind, random rays (a third cut by t_max) and the near-singular
    # classes on and just off their sets: cells identical, distances within
    # 1e-12 relative.
    _all_equal_on_the_simulator(tmp_path, **cpu_traces(cases(n_random=150, n_singular=10)))


def test_simulated_gpu_cones_and_cells_of_points_equal_the_cpu(tmp_path):
    # Batches of cones on every grid kind (from outside, from the gap and the
    # centre, across the seam, along y, one ray, random): the same cells in
    # the same order, weights and first reaches within 1e-12 relative. And
    # Grid.cell_of of points on every edge, an ulp either side and random.
    _all_equal_on_the_simulator(tmp_path, **cpu_cones(cone_cases()), **cpu_cells(point_cases()))


def test_simulated_gpu_inputs_are_read_and_checked_on_the_device(tmp_path):
    # Origins, directions and t_max already on the GPU (float64, float32, one
    # (m, 6) array): the CPU's traces; bad rows: the CPU's error messages.
    _all_equal_on_the_simulator(tmp_path, **cpu_gpu_inputs(gpu_input_cases()))


def test_simulated_gpu_map_equals_the_cpu(tmp_path):
    # Scans in a row into one map on every grid kind -- from the centre, 10 cm
    # off, from the gap and from inside the region, every other one cut at a
    # max_range, a third of the points on spheres -- then decay, fixation and
    # gaze targets: the maps identical after every step.
    _all_equal_on_the_simulator(tmp_path, **cpu_maps(map_cases()))


@pytest.mark.parametrize("limits", [["7"], ["7", "tiny"]])
def test_simulated_gpu_in_small_batches_and_parts(tmp_path, limits):
    # 7 rays in flight; then no memory to spare (one ray in flight, a part per
    # ray): every loop of the batch runs many times, and the parts are joined
    # on the device.
    # With no memory to spare, a batch of cones is also taken a cone at a time.
    path = tmp_path / "cases.npz"
    all_cases = cases(n_random=20, n_singular=1)
    cones = cone_cases()
    np.savez(path, **cpu_traces({key: all_cases[key] for key in ("log random", "log centre",
                                                                  "paper random")}),
             **cpu_cones({key: cones[key] for key in ("log cones named",
                                                      "partial cones random")}))
    result = _simulated([str(path), *limits], tmp_path)
    assert result.returncode == 0, result.stdout + result.stderr


def test_simulated_gpu_calls_stay_within_their_launch_allocation_and_wait_budgets(tmp_path):
    # Each call twice: the second, on the workspace the first made, launches,
    # allocates and waits for the device at most as cuda_check.BUDGETS says
    # (a scan two launches and no wait, a cone two launches and one wait).
    result = _simulated(["budgets"], tmp_path)
    assert result.returncode == 0, result.stdout + result.stderr
    assert result.stdout.strip().endswith("within budget"), result.stdout


def test_gpu_traces_equal_the_cpu_on_a_real_device():
    cuda = pytest.importorskip("numba.cuda")
    if numba.config.ENABLE_CUDASIM or not cuda.is_available():
        pytest.skip("no CUDA GPU here")
    problems = compare({**cpu_traces(cases(n_random=5000, n_singular=100)),
                        **cpu_cones(cone_cases()), **cpu_cells(point_cases()),
                        **cpu_maps(map_cases(n_points=5000)),
                        **cpu_gpu_inputs(gpu_input_cases())})
    assert not problems, problems


@pytest.mark.skipif(importlib.util.find_spec("numba_cuda") is None,
                    reason="needs numba-cuda (the cuda extra; .ci/run installs it for this test)")
def test_every_gpu_kernel_compiles_and_assembles_for_the_device(tmp_path):
    # The simulator runs the per-ray code as Python; this compiles it. Every
    # kernel, with the argument types the entry points launch it with (found
    # under the simulator), goes through numba-cuda to PTX for an H100 and
    # through ptxas to machine code. No GPU is needed.
    path = str(tmp_path / "signatures.pkl")
    env = dict(os.environ, PYTHONPATH=_python_path())
    for name in ("NUMBA_ENABLE_CUDASIM", "NUMBA_DISABLE_JIT"):
        env.pop(name, None)
    script = str(TESTS / "cuda_compile.py")
    recorded = subprocess.run([sys.executable, script, "record", path], capture_output=True,
                              text=True, cwd=tmp_path, timeout=600,
                              env=dict(env, NUMBA_ENABLE_CUDASIM="1", NUMBA_DISABLE_JIT="1"))
    assert recorded.returncode == 0, recorded.stdout + recorded.stderr
    compiled = subprocess.run([sys.executable, script, "compile", path], capture_output=True,
                              text=True, cwd=tmp_path, timeout=600, env=env)
    assert compiled.returncode == 0, compiled.stdout + compiled.stderr
    assert re.search(r"compiled (\d+) of \1$", compiled.stdout.strip()), compiled.stdout


_RELAXED_STORES = """
import types, numpy as np
from numba import cuda
from numba import types as nb
from numba.cuda import compile_ptx, dispatcher
from cuda.pathfinder import find_nvidia_binary_utility
from cuda_compile import CC, _assemble
from logsph_trace.kernels.atomic import store_relaxed
dispatcher.get_current_device = lambda: types.SimpleNamespace(compute_capability=CC)

def kernel(a, b, c, d, e):
    i = cuda.grid(1)
    if i < a.shape[0]:
        store_relaxed(a, i, 1)
        store_relaxed(b, i, i)
        store_relaxed(c, i, i)
        store_relaxed(d, i, i)
        store_relaxed(e, i, 0.5)

ptx, _ = compile_ptx(kernel, (nb.uint8[::1], nb.int16[::1], nb.int32[::1], nb.int64[::1],
                              nb.float64[::1]), cc=CC)
_assemble(ptx, find_nvidia_binary_utility("ptxas"))
print(sorted(line.split()[0] for line in ptx.splitlines() if line.strip().startswith("st.")))
"""


@pytest.mark.skipif(importlib.util.find_spec("numba_cuda") is None,
                    reason="needs numba-cuda (the cuda extra; .ci/run installs it for this test)")
def test_a_relaxed_store_compiles_to_a_ptx_volatile_store_and_assembles():
    # NVVM takes no LLVM atomic store; the walk, which also runs on the GPU,
    # stores its flags relaxed: there PTX's st.volatile (relaxed, sys scope).
    env = dict(os.environ, PYTHONPATH=_python_path())
    for name in ("NUMBA_ENABLE_CUDASIM", "NUMBA_DISABLE_JIT"):
        env.pop(name, None)
    result = subprocess.run([sys.executable, "-c", _RELAXED_STORES], capture_output=True,
                            text=True, cwd=TESTS, timeout=600, env=env)
    assert result.returncode == 0, result.stdout + result.stderr
    assert result.stdout.split("\n")[-2] == str(sorted(
        ["st.volatile.u8", "st.volatile.u16", "st.volatile.u32", "st.volatile.u64",
         "st.volatile.u64"])), result.stdout


def test_import_and_the_cpu_path_need_no_numba_cuda():
    code = (
        "import sys; sys.modules['numba.cuda'] = None\n"
        "import numpy as np, logsph_trace as lt\n"
        "grid = lt.Grid(0.3, 10.0, 8, 12, 6)\n"
        "assert len(lt.trace_many(grid, [[0, 0, -5.0]], [[0, 0, 1.0]])[0]) > 0\n"
        "try:\n"
        "    lt.trace_many(grid, [[0, 0, -5.0]], [[0, 0, 1.0]], device='cuda')\n"
        "except RuntimeError as error:\n"
        "    print(error)\n"
    )
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                            cwd=REPO, timeout=300)
    assert result.returncode == 0, result.stderr
    assert "needs numba-cuda (pip install 'logsph_trace[cuda]')" in result.stdout


ON_DEVICE = {
    "trace_many": lambda device: lt.trace_many(GRID, [[0, 0, -5.0]], [[0, 0, 1.0]],
                                               device=device),
    "trace_cone": lambda device: lt.trace_cone(GRID, (0, 0, -5.0), (0, 0, 1.0), 0.1,
                                               device=device),
    "trace_cones": lambda device: lt.trace_cones(GRID, [(0, 0, -5.0)], [(0, 0, 1.0)], 0.1,
                                                 device=device),
    "cell_of": lambda device: GRID.cell_of([0.0, 0.0, 1.0], device=device),
    "OccupancyGrid": lambda device: lt.OccupancyGrid(GRID, device=device),
}


@pytest.mark.parametrize("call", ON_DEVICE)
def test_cuda_without_a_gpu_is_one_clear_error(call):
    cuda = pytest.importorskip("numba.cuda")
    if cuda.is_available():
        pytest.skip("a CUDA GPU (or the simulator) is available here")
    with pytest.raises(RuntimeError, match="needs an NVIDIA GPU with a working driver"):
        ON_DEVICE[call]("cuda")


@pytest.mark.parametrize("call", ON_DEVICE)
def test_an_unknown_device_is_a_value_error(call):
    with pytest.raises(ValueError, match=r"device must be one of \('cpu', 'cuda'\), got 'gpu'"):
        ON_DEVICE[call]("gpu")


@pytest.mark.parametrize("kwargs, match", [
    (dict(device="cuda", method="bisect"), "supports method='exact' only"),
    (dict(device="cuda", out=lt.TraceBuffers()), "out is not supported"),
    (dict(device="cuda", t_max=-1.0), "t_max"),
])
def test_bad_cuda_options_are_value_errors_before_any_gpu_is_needed(kwargs, match):
    with pytest.raises(ValueError, match=match):
        lt.trace_many(GRID, [[0, 0, -5.0]], [[0, 0, 1.0]], **kwargs)


class _OnTheGPU:
    """Stands for a CuPy or PyTorch array: only its interface is looked at."""

    __cuda_array_interface__ = {"shape": (1, 3), "typestr": "<f8", "data": (0, False),
                                "version": 3}


@pytest.mark.parametrize("call", [
    lambda: lt.trace_many(GRID, _OnTheGPU(), [[0, 0, 1.0]]),
    lambda: lt.trace_many(GRID, [[0, 0, -5.0]], [[0, 0, 1.0]], t_max=_OnTheGPU()),
    lambda: GRID.cell_of(_OnTheGPU()),
])
def test_gpu_arrays_without_device_cuda_are_a_clear_value_error(call):
    with pytest.raises(ValueError, match="is a GPU array: pass device='cuda'"):
        call()


def test_a_host_map_answers_device_questions(tmp_path):
    occupancy = lt.OccupancyGrid(GRID)
    assert occupancy.device == "cpu" and occupancy.to_host() is occupancy
    path = occupancy.save(tmp_path / "map")
    with pytest.raises(ValueError, match="device must be one of"):
        lt.OccupancyGrid.load(path, device="gpu")
    assert lt.OccupancyGrid.load(path, device="cpu").device == "cpu"


def test_host_traces_answer_device_questions():
    traces = lt.trace_many(GRID, [[0, 0, -5.0]], [[0, 0, 1.0]])
    assert traces.device == "cpu" and traces.to_host() is traces
