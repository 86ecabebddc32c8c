"""pytest-benchmark suite: ``pytest bench/ --benchmark-only`` (not part of the test suite).

Timings are machine-dependent; compare each exact-kernel row with the
Amanatides-Woo row of the same run, never with numbers from another machine.
"""

import numba
import pytest

import logsph_trace as lt
from bench.workload import make_box, make_grid, make_rays

N_RAYS = 20_000


@pytest.fixture(scope="module")
def rays():
    return make_rays(N_RAYS)


@pytest.fixture(scope="module", params=[32, 128])
def cells(request):
    return request.param


@pytest.fixture
def one_thread():
    before = numba.get_num_threads()
    numba.set_num_threads(1)
    yield
    numba.set_num_threads(before)


def test_exact_serial(benchmark, rays, cells):
    grid = make_grid(cells)
    benchmark.group = f"traversal {cells}^3, {N_RAYS} rays, serial"
    traces = benchmark(lt.trace_many, grid, *rays, parallel=False)
    benchmark.extra_info["voxels"] = int(traces.cells.shape[0])


def test_amanatides_woo_serial(benchmark, rays, cells):
    box = make_box(cells)
    benchmark.group = f"traversal {cells}^3, {N_RAYS} rays, serial"
    traces = benchmark(box.trace_many, *rays, parallel=False)
    benchmark.extra_info["voxels"] = int(traces.cells.shape[0])


def test_exact_parallel(benchmark, rays, cells):
    grid = make_grid(cells)
    benchmark.group = f"traversal {cells}^3, {N_RAYS} rays, all threads"
    traces = benchmark(lt.trace_many, grid, *rays, parallel=True)
    benchmark.extra_info["voxels"] = int(traces.cells.shape[0])


def test_exact_single_ray(benchmark, one_thread):
    grid = make_grid(128)
    benchmark.group = "single gaze ray (latency)"
    benchmark(lt.trace, grid, [0.5, 1.5, 1.0], [-0.3, -0.2, 1.0])


def test_gaze_cone_1000_rays(benchmark):
    grid = lt.Grid(0.3, 10.0, 64, 360, 180)
    benchmark.group = "gaze cone, 1,000 rays, 64 x 360 x 180, all threads"
    cone = benchmark(lt.trace_cone, grid, [0.4, 1.5, 1.2], [-0.1, -0.4, 1.0], 0.0873, n_rays=1000)
    benchmark.extra_info["cells"] = len(cone)


def test_integrate_depth_image(benchmark):
    from logsph_trace.scene import table_scene

    grid = lt.Grid(0.3, 10.0, 64, 360, 180)
    points, _, _ = table_scene()[0].depth_points()
    occupancy = lt.OccupancyGrid(grid)
    benchmark.group = "occupancy: 640 x 480 depth image into 64 x 360 x 180, all threads"
    benchmark(occupancy.integrate, points, [0.0, 0.0, 0.0])
