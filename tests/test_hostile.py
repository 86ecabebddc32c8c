"""Hostile use: maps shared by threads, files with modes and links, labels and
dtypes at their limits, text where numbers belong, huge counts and scales.

Each case gets a right result or one clear error of the documented type.
"""

import copy
import os
import pickle
import stat
import threading
import time

import numpy as np
import pytest

import logsph_trace as lt
from logsph_trace.cone import default_ray_count

GRID = lt.Grid(0.3, 10.0, 12, 24, 12)


def _scan(seed=0, n=4000):
    return np.random.default_rng(seed).normal(size=(n, 3)) * 3.0


# ---- one map shared by threads ----


def test_threads_sharing_a_map_take_turns(monkeypatch):
    """Two scans of one map never run their kernels at once (a lost update
    otherwise: both read a cell's log-odds, each adds its own, one wins)."""
    from logsph_trace import occupancy as module

    spans = []
    kernel = module._radial.mark_radial

    def slow(*args):
        start = time.perf_counter()
        time.sleep(0.2)  # long enough for the other thread to arrive
        kernel(*args)
        spans.append((start, time.perf_counter()))

    monkeypatch.setattr(module._radial, "mark_radial", slow)
    shared = lt.OccupancyGrid(GRID)
    threads = [threading.Thread(target=shared.integrate, args=(_scan(), [0.0, 0.0, 0.0]))
               for _ in range(2)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    (first_start, first_end), (second_start, _) = sorted(spans)
    assert second_start >= first_end
    serial = lt.OccupancyGrid(GRID)
    for _ in range(2):
        serial.integrate(_scan(), [0.0, 0.0, 0.0])
    np.testing.assert_array_equal(shared.log_odds, serial.log_odds)


@pytest.mark.parametrize("sensor", [[0.0, 0.0, 0.0], [0.12, -0.05, 0.07]])
def test_threads_sharing_a_map_give_the_serial_map(sensor):
    """Four threads, one scan each, while others read the map: the map of the
    four scans one after the other (the same scan, so any order sums alike)."""
    points = _scan(n=20_000)
    serial = lt.OccupancyGrid(GRID)
    for _ in range(4):
        serial.integrate(points, sensor)
    for _ in range(5):
        shared = lt.OccupancyGrid(GRID)
        barrier = threading.Barrier(4)

        def work():
            barrier.wait()
            shared.integrate(points, sensor)
            lt.fixation_probability(shared, [0.2, 0.1, 0.0], [1.0, 0.1, 0.2], 0.05)

        threads = [threading.Thread(target=work) for _ in range(4)]
        for thread in threads:
            thread.start()
        for thread in threads:
            thread.join()
        np.testing.assert_array_equal(shared.log_odds, serial.log_odds)


def test_a_map_pickles_and_copies_with_a_lock_of_its_own():
    bvm = lt.OccupancyGrid(GRID).integrate(_scan(), [0.0, 0.0, 0.0])
    for other in (pickle.loads(pickle.dumps(bvm)), copy.deepcopy(bvm)):
        np.testing.assert_array_equal(other.log_odds, bvm.log_odds)
        assert other._lock is not bvm._lock
        other.integrate(_scan(1), [0.0, 0.0, 0.0])


# ---- files: atomic, keeping their mode, written through links ----


def test_save_keeps_the_mode_of_the_file_it_replaces(tmp_path):
    bvm = lt.OccupancyGrid(GRID)
    path = bvm.save(tmp_path / "map.npz")
    os.chmod(path, 0o600)
    bvm.integrate(_scan(), [0.0, 0.0, 0.0]).save(path)
    assert stat.S_IMODE(os.stat(path).st_mode) == 0o600
    np.testing.assert_array_equal(lt.OccupancyGrid.load(path).log_odds, bvm.log_odds)


def test_a_new_file_gets_the_umask_mode(tmp_path):
    mask = os.umask(0o027)
    try:
        path = lt.OccupancyGrid(GRID).save(tmp_path / "map.npz")
    finally:
        os.umask(mask)
    assert stat.S_IMODE(os.stat(path).st_mode) == 0o640


def test_save_through_a_symlink_writes_its_target_and_keeps_the_link(tmp_path):
    target = tmp_path / "maps" / "map.npz"
    target.parent.mkdir()
    lt.OccupancyGrid(GRID).save(target)
    link = tmp_path / "latest.npz"
    link.symlink_to(target)
    bvm = lt.OccupancyGrid(GRID).integrate(_scan(), [0.0, 0.0, 0.0])
    bvm.save(link)
    assert link.is_symlink() and os.readlink(link) == str(target)
    np.testing.assert_array_equal(lt.OccupancyGrid.load(target).log_odds, bvm.log_odds)
    assert sorted(p.name for p in target.parent.iterdir()) == ["map.npz"]  # no leftovers


# ---- labels that do not fit are refused, on every path ----


@pytest.mark.parametrize("bad", [2**31, 2**32 + 5, 2**62, np.uint32(0xFFFFFFFF),
                                 np.uint64(2**64 - 1)])
def test_labels_beyond_int32_are_refused_on_every_path(bad, tmp_path):
    points = _scan(n=50)
    labels = np.full(50, bad, dtype=np.asarray(bad).dtype if np.ndim(bad) == 0 and
                     isinstance(bad, np.generic) else np.int64)
    bvm = lt.OccupancyGrid(GRID)
    match = r"labels must be at most 2,147,483,647 .* got " + str(int(bad))
    with pytest.raises(ValueError, match=match):
        bvm.integrate(points, [0.0, 0.0, 0.0], labels=labels)
    depth = np.full((4, 5), 2.0)
    with pytest.raises(ValueError, match=match):
        bvm.integrate_depth(depth, (3.0, 3.0, 2.0, 1.5), labels=np.full(depth.shape, bad,
                                                                          dtype=labels.dtype))
    with pytest.raises(ValueError, match=match):
        bvm.labels = np.full(GRID.shape, bad, dtype=labels.dtype)
    path = bvm.save(tmp_path / "map.npz")
    with np.load(path) as data:
        arrays = dict(data)
    arrays["labels"] = np.full(GRID.shape, bad, dtype=labels.dtype)
    np.savez(path, **arrays)
    with pytest.raises(ValueError, match="not a valid OccupancyGrid file: " + match):
        lt.OccupancyGrid.load(path)
    assert not np.any(bvm.labels)  # nothing was stored


def test_the_largest_label_is_kept_exactly():
    points = _scan(n=400)
    bvm = lt.OccupancyGrid(GRID).integrate(points, [0.0, 0.0, 0.0],
                                           labels=np.full(400, 2**31 - 1, dtype=np.uint32))
    assert set(np.unique(bvm.labels)) == {0, 2**31 - 1}


# ---- inputs of every dtype the docs promise; text is not a number ----


@pytest.mark.parametrize("dtype", [np.float16, ">u2", ">f4", "<f8", ">i4"])
def test_depth_images_of_any_numeric_dtype_and_byte_order(dtype):
    depth = np.random.default_rng(5).uniform(0.5, 4.0, (6, 8))
    if np.dtype(dtype).kind in "iu":
        depth = np.round(depth * 1000.0)
    scale = 0.001 if np.dtype(dtype).kind in "iu" else 1.0
    want = lt.depth_to_points(depth.astype(np.dtype(dtype).newbyteorder("=")), (5.0, 5.0, 4.0, 3.0),
                              depth_scale=scale)
    got = lt.depth_to_points(depth.astype(dtype), (5.0, 5.0, 4.0, 3.0), depth_scale=scale)
    np.testing.assert_array_equal(got.points, want.points)
    bvm = lt.OccupancyGrid(GRID).integrate_depth(depth.astype(dtype), (5.0, 5.0, 4.0, 3.0),
                                                 depth_scale=scale)
    assert bvm.last_scan.rays == 48


@pytest.mark.parametrize("call", [
    lambda: lt.OccupancyGrid(GRID).integrate(_scan(n=5), [0, 0, 0], max_range="5"),
    lambda: lt.trace_cone(GRID, [0, 0, 0], [0, 0, 1], "0.1"),
    lambda: lt.OccupancyGrid(GRID).decay("0.5"),
    lambda: lt.Grid("0.3", 10.0, 4, 4, 4),
    lambda: lt.trace(GRID, np.array(["0.1", "0", "0"], dtype=object), [0, 0, 1]),
    lambda: lt.Grid.from_edges([1, 2], [0, 1 + 0.5j], [0, 1]),
    lambda: lt.Grid.from_edges(["1", "2"], [0, 1], [0, 1]),
])
def test_text_and_complex_numbers_are_a_type_error(call):
    with pytest.raises(TypeError, match="must be"):
        call()


# ---- smaller defects ----


def test_a_cone_over_a_cell_of_1e_200_rad_gets_the_capped_ray_count():
    narrow = lt.Grid.from_edges([0.3, 10.0], [0.0, 1e-200, 1.0], [-0.5, 0.5])
    assert default_ray_count(narrow, [0, 0, 0], 0.1) == 1_000_000


def test_a_scan_beside_a_cell_of_5e_324_rad_integrates():
    tiny = lt.Grid.from_edges([0.3, 10.0], [-np.pi, 5e-324, np.pi], [-np.pi / 2, np.pi / 2])
    # Enough rays from inside the gap for the coherent scan, whose bins follow
    # the narrowest cell: at most its largest number of bins here.
    bvm = lt.OccupancyGrid(tiny).integrate(_scan(n=30_000), [0.01, 0.0, 0.01])
    assert np.all(np.isfinite(bvm.log_odds)) and np.any(bvm.log_odds > 0)


def test_a_tiny_sigma_puts_the_weight_on_the_rays_nearest_the_axis():
    cone = lt.trace_cone(GRID, [0.0, 0.0, 0.0], [0.0, 0.1, 1.0], 0.1, sigma=1e-170)
    assert np.all(np.isfinite(cone.weights)) and cone.weights.sum() == pytest.approx(1.0)


@pytest.mark.parametrize("call, error, match", [
    (lambda: lt.trace_cone(GRID, [0, 0, 0], [0, 0, 1], 0.1, n_rays=2**63), MemoryError,
     "n_rays: a cone of 9,223,372,036,854,775,808 rays"),
    (lambda: lt.trace(GRID, [0, 0, 0], [0, 0, 1], method="bisect", max_iter=2**70), ValueError,
     "max_iter must be a positive integer up to"),
    (lambda: lt.gaze_objects(lt.OccupancyGrid(GRID), [0, 0, 0], [0, 0, 1], dense=True),
     TypeError, "gaze_objects.. takes no 'dense'"),
    (lambda: lt.Grid(1e-30, 1.0, 4, 4, 4), ValueError,
     "radial cells must be at least 1e-11 rho_max wide"),
    (lambda: lt.Grid.from_edges([1.0, 1.0 + 1e-12, 2.0], [0, 1], [0, 1]), ValueError,
     "radial cells must be at least 1e-11 rho_max wide, got cell 0"),
])
def test_huge_counts_and_options_are_one_clear_error(call, error, match):
    with pytest.raises(error, match=match):
        call()


def test_a_half_life_assigned_later_is_checked():
    memory = lt.GazeAccumulator(2.0)
    with pytest.raises(ValueError, match="half_life must be positive, got 0"):
        memory.half_life = 0
    assert memory.half_life == 2.0


@pytest.mark.parametrize("scale", [1e-200, 1e-100, 1.0, 1e100, 1e200])
def test_spherical_coordinates_and_planes_at_any_scale(scale):
    rho, theta, phi = lt.cartesian_to_spherical(np.full(3, scale))
    assert rho == pytest.approx(np.sqrt(3.0) * scale, rel=1e-15)
    assert (theta, phi) == pytest.approx((np.pi / 4, np.arctan(1 / np.sqrt(2.0))), rel=1e-15)
    points = np.random.default_rng(2).normal(size=(60, 3))
    points[:, 1] = 0.2 * points[:, 0] + 0.5
    plane = lt.fit_plane(points * scale, tolerance=0.02 * scale)
    assert abs(plane.normal @ [0.2, -1.0, 0.0]) == pytest.approx(np.sqrt(1.04), rel=1e-12)
    assert plane.inliers.all()


def test_a_plane_tolerance_in_another_unit_than_the_points_is_said():
    points = np.random.default_rng(2).normal(size=(60, 3)) * 1e200
    points[:, 1] = 0.2 * points[:, 0]
    with pytest.raises(ValueError, match="no plane has 3 points within tolerance=0.02"):
        lt.fit_plane(points)


@pytest.mark.parametrize("how", [pickle.loads, copy.deepcopy])
def test_a_copied_grid_stays_read_only(how):
    other = how(pickle.dumps(GRID)) if how is pickle.loads else how(GRID)
    for array in (other.rho_edges, other.theta_edges, other.phi_edges):
        assert not array.flags.writeable
    np.testing.assert_array_equal(lt.trace(other, [0.1, 0, 0], [0, 0.2, 1]).cells,
                                  lt.trace(GRID, [0.1, 0, 0], [0, 0.2, 1]).cells)


# ---- memory: the error comes before the allocation ----


def _no_memory(monkeypatch, free):
    from logsph_trace import _validate

    monkeypatch.setattr(_validate, "available_memory", lambda: free)


@pytest.mark.parametrize("parallel", [True, False])
def test_a_batch_that_cannot_fit_fails_before_it_is_traced(monkeypatch, parallel):
    from logsph_trace import _batching

    rays = np.random.default_rng(0).normal(size=(200_000, 6)) * [3, 3, 3, 1, 1, 1]
    grid = lt.Grid(0.3, 10.0, 64, 90, 45)
    want = lt.trace_many(grid, rays[:50_000], parallel=parallel)
    _no_memory(monkeypatch, 40 * 2**20)
    traced = []  # the parallel paths' kernels must not run
    kernels = _batching.EXACT_KERNELS
    monkeypatch.setattr(_batching, "EXACT_KERNELS", kernels._replace(
        ordered=lambda *a: traced.append("ordered")))
    with pytest.raises(MemoryError, match=r"origins: tracing 200,000 rays \(about [\d,]+ "
                                          r"segments\) needs about"):
        lt.trace_many(grid, rays, parallel=parallel)
    assert traced == []
    monkeypatch.undo()
    again = lt.trace_many(grid, rays[:50_000], parallel=parallel)
    np.testing.assert_array_equal(again.cells, want.cells)


def test_cones_that_cannot_fit_fail_before_they_are_traced(monkeypatch):
    from logsph_trace import _batching

    grid = lt.Grid(0.3, 10.0, 64, 90, 45)
    rng = np.random.default_rng(1)
    _no_memory(monkeypatch, 60 * 2**20)
    monkeypatch.setattr(_batching, "EXACT_KERNELS", _batching.EXACT_KERNELS._replace(
        ordered=None))
    with pytest.raises(MemoryError, match="needs about"):
        lt.trace_cones(grid, rng.normal(size=(20, 3)), rng.normal(size=(20, 3)), 0.1,
                       n_rays=20_000)


def test_a_grid_counts_all_its_axes_in_the_memory_it_needs(monkeypatch):
    _no_memory(monkeypatch, 200 * 2**20)
    with pytest.raises(MemoryError, match=r"grid: a grid of 4 x 3,000,000 x 4 cells \(its "
                                          r"tables and a trace's scratch\) needs about"):
        lt.Grid(0.3, 10.0, 4, 3_000_000, 4)


def _npz_declaring(path, arrays, declared):
    """An .npz of ``arrays`` whose member ``declared[0]`` claims shape ``declared[1]``."""
    import io
    import zipfile

    with zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED) as archive:
        for name, array in arrays.items():
            stream = io.BytesIO()
            if name == declared[0]:
                np.lib.format.write_array_header_2_0(
                    stream, {"descr": "<f4", "fortran_order": False, "shape": declared[1]})
                stream.write(b"\0" * 64)
            else:
                np.save(stream, array)
            archive.writestr(name + ".npy", stream.getvalue())


@pytest.mark.parametrize("shape, match", [
    ((1000, 1000, 1000), r"log_odds must have the grid's shape \(12, 24, 12\), got "
                         r"\(1000, 1000, 1000\)"),
    ((2**64,), r"log_odds must have the grid's shape"),
    ((12, 24, 12, 2**40), r"log_odds must have the grid's shape"),
])
def test_load_reads_the_declared_shapes_before_any_array(tmp_path, shape, match):
    path = lt.OccupancyGrid(GRID).save(tmp_path / "map.npz")
    with np.load(path) as data:
        arrays = dict(data)
    _npz_declaring(tmp_path / "bad.npz", arrays, ("log_odds", shape))
    with pytest.raises(ValueError, match="bad.npz is not a valid OccupancyGrid file: " + match):
        lt.OccupancyGrid.load(tmp_path / "bad.npz")


def test_load_refuses_edges_declared_too_large_to_read(tmp_path, monkeypatch):
    path = lt.OccupancyGrid(GRID).save(tmp_path / "map.npz")
    with np.load(path) as data:
        arrays = dict(data)
    _npz_declaring(tmp_path / "bad.npz", arrays, ("theta_edges", (2**40,)))
    with pytest.raises(ValueError, match="log_odds must have the grid's shape"):
        lt.OccupancyGrid.load(tmp_path / "bad.npz")


MEMINFO = b"MemTotal: 24684564 kB\nMemAvailable: 23500000 kB\n"


@pytest.mark.parametrize("files, expected", [
    # The process's own cgroup (a container's) holds the limit, v2.
    ({"/proc/meminfo": MEMINFO, "/proc/self/cgroup": b"0::/box/inner\n",
      "/sys/fs/cgroup/memory.max": b"max\n", "/sys/fs/cgroup/memory.current": b"5\n",
      "/sys/fs/cgroup/box/memory.max": b"2000\n", "/sys/fs/cgroup/box/memory.current": b"500\n",
      "/sys/fs/cgroup/box/inner/memory.max": b"max\n",
      "/sys/fs/cgroup/box/inner/memory.current": b"300\n"}, 1500),
    # v1, the memory controller's own line.
    ({"/proc/meminfo": MEMINFO, "/proc/self/cgroup": b"4:memory:/docker/abc\n0::/\n",
      "/sys/fs/cgroup/memory/memory.limit_in_bytes": b"9223372036854771712\n",
      "/sys/fs/cgroup/memory/memory.usage_in_bytes": b"1\n",
      "/sys/fs/cgroup/memory/docker/abc/memory.limit_in_bytes": b"4096\n",
      "/sys/fs/cgroup/memory/docker/abc/memory.usage_in_bytes": b"96\n"}, 4000),
])
def test_the_available_memory_honours_the_process_own_cgroup(monkeypatch, files, expected):
    from logsph_trace import _validate

    monkeypatch.setattr(_validate, "_read_small", files.get)
    monkeypatch.setattr(_validate, "_address_space_room", lambda: None)
    assert _validate.available_memory() == expected


def test_the_available_memory_honours_rlimit_as():
    import subprocess
    import sys

    script = ("import resource; from logsph_trace import _validate as v\n"
              "resource.setrlimit(resource.RLIMIT_AS, (6 * 2**30, resource.RLIM_INFINITY))\n"
              "print(v.available_memory() <= 6 * 2**30, v._address_space_room() > 0)")
    out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True,
                         timeout=120)
    assert out.stdout.split() == ["True", "True"], out.stderr


@pytest.mark.parametrize("sensor", [[0.0, 0.0, 0.0], [0.12, -0.05, 0.07]])
def test_a_scan_that_cannot_fit_fails_before_the_map_changes(monkeypatch, sensor):
    from logsph_trace import _validate

    bvm = lt.OccupancyGrid(GRID).integrate(_scan(), sensor)
    before = bvm.log_odds.copy()
    monkeypatch.setattr(_validate, "SMALL_REQUEST_BYTES", 0)
    _no_memory(monkeypatch, 1000)
    with pytest.raises(MemoryError, match=r"points: integrating 4,000 points needs about"):
        bvm.integrate(_scan(1), sensor)
    np.testing.assert_array_equal(bvm.log_odds, before)


def test_a_depth_image_that_cannot_fit_fails_before_it_is_back_projected(monkeypatch):
    from logsph_trace import _validate

    monkeypatch.setattr(_validate, "SMALL_REQUEST_BYTES", 0)
    _no_memory(monkeypatch, 1000)
    with pytest.raises(MemoryError, match=r"depth: back-projecting 48 pixels needs about"):
        lt.depth_to_points(np.full((6, 8), 2.0), (5.0, 5.0, 4.0, 3.0))
