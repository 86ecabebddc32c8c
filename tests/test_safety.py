"""Misuse that could crash, lose data or mislead, each as a regression test."""

import os

import numpy as np
import pytest

import logsph_trace as lt
from logsph_trace.occupancy import OccupancyGrid

SMALL = lt.Grid(0.3, 10, 16, 36, 18)


def _points(n=200, seed=0):
    rng = np.random.default_rng(seed)
    directions = rng.normal(size=(n, 3))
    directions /= np.linalg.norm(directions, axis=1)[:, None]
    return directions * rng.uniform(1.0, 9.0, (n, 1))


# ---- the map's attributes -------------------------------------------------

def test_a_maps_grid_cannot_be_replaced():
    bvm = OccupancyGrid(SMALL)
    with pytest.raises(AttributeError):
        bvm.grid = lt.Grid(0.3, 10, 64, 360, 180)  # used to write out of bounds (exit 139)
    bvm.integrate(_points(), [0, 0, 0])
    assert bvm.grid is SMALL


def test_a_grid_cannot_be_changed_in_place():
    grid = lt.Grid(0.3, 10, 16, 36, 18)
    with pytest.raises(AttributeError, match="immutable"):
        grid.rho_edges = np.linspace(0.3, 10, 100)
    with pytest.raises(ValueError):
        grid.theta_edges[0] = 1.0  # read-only array
    # The kernels' bundle too: it is cached and shared by every later call,
    # so a sine overwritten there silently changed every later trace.
    for array in grid.kernel_args():
        if isinstance(array, np.ndarray):
            with pytest.raises(ValueError, match="read-only"):
                array[0] = 1.0


@pytest.mark.parametrize("bad", [np.zeros((16, 36)), np.zeros((64, 360, 180)),
                                 np.zeros(16 * 36 * 18)])
def test_log_odds_of_the_wrong_shape_is_refused(bad):
    bvm = OccupancyGrid(SMALL)
    with pytest.raises(ValueError, match="log_odds has shape"):
        bvm.log_odds = bad
    bvm.integrate(_points(), [0, 0, 0])
    assert bvm.log_odds.shape == SMALL.shape


def test_log_odds_assigned_non_contiguous_still_receives_updates():
    bvm = OccupancyGrid(SMALL)
    wide = np.zeros(SMALL.shape[:2] + (2 * SMALL.shape[2],), dtype=np.float32)
    bvm.log_odds = wide[:, :, ::2]  # right shape, not contiguous: was silently copied
    bvm.integrate(_points(), [0, 0, 0])
    assert np.count_nonzero(bvm.log_odds) > 0
    assert bvm.log_odds.flags.c_contiguous and bvm.log_odds.dtype == np.float32


def test_read_only_or_integer_log_odds_is_copied_not_refused():
    frozen = np.zeros(SMALL.shape, dtype=np.float32)
    frozen.setflags(write=False)
    bvm = OccupancyGrid(SMALL, log_odds=frozen)
    bvm.integrate(_points(), [0, 0, 0])  # was a numba TypingError
    assert np.count_nonzero(bvm.log_odds) > 0 and not np.any(frozen)
    bvm.log_odds = np.zeros(SMALL.shape, dtype=np.int64)
    assert bvm.log_odds.dtype == np.float32


@pytest.mark.parametrize("bad, match", [
    ("abc", "log_odds must be an array of numbers"),
    (np.full(SMALL.shape, np.nan), "log_odds must be finite"),
])
def test_bad_log_odds_values_name_the_argument(bad, match):
    with pytest.raises(ValueError, match=match):
        OccupancyGrid(SMALL, log_odds=bad)


def _widen(array):
    array.dtype = np.float64  # in place: half as many cells, each 8 bytes


def _flatten(array):
    array.shape = (array.size,)


def _freeze(array):
    array.setflags(write=False)


def _probability(bvm):
    return bvm.probability


@pytest.mark.parametrize("change", [_widen, _flatten, _freeze])
@pytest.mark.parametrize("use", [
    lambda bvm: bvm.integrate(_points(), [0, 0, 0]),
    lambda bvm: bvm.integrate(_points(20_000), [0.05, -0.02, 0.01]),
    lambda bvm: bvm.decay(0.5),
    lambda bvm: lt.fixation_probability(bvm, [0.1, 0, 0], [1.0, 0.2, 0.1], 0.05),
    _probability,
], ids=["integrate_centre", "integrate_off_centre", "decay", "fixation", "probability"])
def test_log_odds_changed_in_place_is_refused_before_any_kernel(change, use):
    # numpy lets an array's dtype, shape and flags change in place. Widening
    # the dtype to float64 halved the map, and integrating then wrote past
    # its end (glibc aborted: "free(): invalid size"); a read-only map was a
    # Numba TypingError. Each use checks the map again, in O(1).
    bvm = OccupancyGrid(SMALL)
    change(bvm.log_odds)
    if change is _freeze and use is _probability:  # reading needs no writes
        np.testing.assert_array_equal(use(bvm), 0.5)
        return
    with pytest.raises(ValueError, match="log_odds was changed in place"):
        use(bvm)
    bvm.log_odds = np.zeros(SMALL.shape, dtype=np.float32)  # assigning is the way
    use(bvm)


@pytest.mark.parametrize("name, bad", [("p_hit", 2.0), ("p_hit", 0.3), ("p_miss", 0.6),
                                       ("p_min", 0.9), ("p_max", "high"), ("p_max", np.nan)])
def test_update_probabilities_are_checked_when_assigned(name, bad):
    # They were plain attributes: p_hit = 2.0 made every updated cell NaN
    # without an error.
    bvm = OccupancyGrid(SMALL)
    with pytest.raises(ValueError, match=name):
        setattr(bvm, name, bad)
    bvm.integrate(_points(), [0, 0, 0])
    assert np.all(np.isfinite(bvm.log_odds))


def test_update_probabilities_assigned_later_are_used():
    fresh, changed = OccupancyGrid(SMALL, p_hit=0.9), OccupancyGrid(SMALL)
    changed.p_hit = 0.9
    assert changed.p_hit == 0.9
    for bvm in (fresh, changed):
        bvm.integrate(_points(), [0, 0, 0])
    np.testing.assert_array_equal(changed.log_odds, fresh.log_odds)


# ---- files ----------------------------------------------------------------

def test_a_failed_save_keeps_the_old_map_and_leaves_no_partial_file(tmp_path, monkeypatch):
    path = tmp_path / "map.npz"
    old = OccupancyGrid(SMALL)
    old.integrate(_points(), [0, 0, 0])
    assert old.save(path) == path
    before = path.read_bytes()

    def disk_full(stream, array, **options):
        stream.write(b"x" * 1000)
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(np.lib.format, "write_array", disk_full)
    with pytest.raises(OSError, match="No space"):
        OccupancyGrid(SMALL).save(path)
    assert path.read_bytes() == before
    assert os.listdir(tmp_path) == ["map.npz"]


def test_a_failed_figure_keeps_the_old_file_and_leaves_no_partial_file(tmp_path):
    # The demo's figures (and the benchmarks' records) go through the same
    # temporary file as a map: a figure that fails half-written leaves the
    # old one as it was.
    matplotlib = pytest.importorskip("matplotlib")
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from logsph_trace._files import save_figure, write_text

    path = tmp_path / "figure.png"
    figure = plt.figure()
    save_figure(figure, path, dpi=20)
    before = path.read_bytes()
    assert before.startswith(b"\x89PNG")

    def broken(stream, **options):
        stream.write(b"x" * 1000)
        raise OSError(28, "No space left on device")

    figure.savefig = broken
    with pytest.raises(OSError, match="No space"):
        save_figure(figure, path)
    plt.close(figure)
    assert path.read_bytes() == before
    write_text(tmp_path / "record.md", "ok\n")
    assert (tmp_path / "record.md").read_text() == "ok\n"
    assert sorted(os.listdir(tmp_path)) == ["figure.png", "record.md"]


def test_an_interrupted_save_keeps_the_old_map(tmp_path, monkeypatch):
    path = tmp_path / "map.npz"
    OccupancyGrid(SMALL).save(path)
    before = path.read_bytes()

    def interrupted(stream, array, **options):
        stream.write(b"partial")
        raise KeyboardInterrupt

    monkeypatch.setattr(np.lib.format, "write_array", interrupted)
    with pytest.raises(KeyboardInterrupt):
        OccupancyGrid(SMALL).save(path)
    assert path.read_bytes() == before
    assert os.listdir(tmp_path) == ["map.npz"]


def test_save_adds_npz_like_numpy_and_says_so(tmp_path):
    written = OccupancyGrid(SMALL).save(tmp_path / "map")
    assert written == tmp_path / "map.npz" and written.is_file()
    assert (os.stat(written).st_mode & 0o777) == 0o666 & ~_umask()


def test_a_save_into_a_missing_directory_names_it_not_a_temporary_file(tmp_path):
    target = tmp_path / "no" / "such" / "map.npz"
    with pytest.raises(FileNotFoundError, match="no such directory") as error:
        OccupancyGrid(SMALL).save(target)
    assert error.value.filename == str(target) and ".part" not in str(error.value)


def _umask():
    mask = os.umask(0)
    os.umask(mask)
    return mask


def _saved(tmp_path, **changes):
    path = tmp_path / "map.npz"
    OccupancyGrid(SMALL).save(path)
    with np.load(path) as data:
        arrays = dict(data)
    arrays.update(changes)
    np.savez(path, **arrays)
    return path


@pytest.mark.parametrize("changes, match", [
    (dict(rho_edges=SMALL.rho_edges[::-1]), "strictly increasing"),
    (dict(theta_edges=np.r_[np.nan, SMALL.theta_edges[1:]]), "must be finite"),
    (dict(theta_edges=np.linspace(-5, 5, 37)), "an azimuth range is at most 2"),
    (dict(phi_edges=np.linspace(-3, 3, 19)), r"must lie in \[-pi/2, pi/2\]"),
    (dict(log_odds=np.zeros((2, 2, 2), dtype=np.float32)), "log_odds must have the grid's shape"),
    (dict(probabilities=np.array([0.7, 0.4])), "probabilities must hold 4"),
    (dict(probabilities=np.array([0.2, 0.4, 0.1, 0.9])), "p_hit must be in"),
    (dict(spacing=np.array("spiral")), "spacing must be one of"),
])
def test_load_validates_like_new_input(tmp_path, changes, match):
    path = _saved(tmp_path, **changes)
    with pytest.raises(ValueError, match=match) as error:
        OccupancyGrid.load(path)
    assert str(path) in str(error.value)


def test_a_file_without_the_arrays_names_the_file(tmp_path):
    path = tmp_path / "other.npz"
    np.savez(path, something=np.zeros(3))
    with pytest.raises(ValueError, match=r"other\.npz is not a valid OccupancyGrid file"):
        OccupancyGrid.load(path)


@pytest.mark.parametrize("damage", ["truncate", "garbage", "empty", "pickle"])
def test_a_corrupt_file_is_one_error_type_naming_the_file(tmp_path, damage):
    path = tmp_path / "map.npz"
    OccupancyGrid(SMALL).save(path)
    data = path.read_bytes()
    if damage == "truncate":
        path.write_bytes(data[: len(data) // 2])
    elif damage == "garbage":
        path.write_bytes(data[:40] + os.urandom(len(data) - 40))
    elif damage == "empty":
        path.write_bytes(b"")
    else:
        with np.load(path) as saved:
            arrays = dict(saved)
        arrays["probabilities"] = np.array([object()], dtype=object)
        np.savez(path, **arrays)
    with pytest.raises(ValueError, match="map.npz") as error:
        OccupancyGrid.load(path)
    assert type(error.value) is ValueError


def test_a_missing_file_is_still_file_not_found(tmp_path):
    with pytest.raises(FileNotFoundError):
        OccupancyGrid.load(tmp_path / "nothing.npz")


# ---- unchecked inputs -----------------------------------------------------

TWO_ROWS = [[0.0, 0.0, 0.0], [1.0, 1.0, 1.0]]


@pytest.mark.parametrize("call, match", [
    (lambda: lt.trace_cone(SMALL, TWO_ROWS, [1, 0, 0], 0.05), "origin must be one vector"),
    (lambda: lt.trace_cone(SMALL, [0, 0, 0], TWO_ROWS, 0.05), "direction must be one vector"),
    (lambda: lt.gaze_targets(OccupancyGrid(SMALL), TWO_ROWS, [1, 0, 0]),
     "origin must be one vector"),
    (lambda: lt.gaze_targets(OccupancyGrid(SMALL), [0, 0, 0], TWO_ROWS),
     "direction must be one vector"),
    (lambda: lt.fixation_probability(OccupancyGrid(SMALL), TWO_ROWS, [1, 0, 0]),
     "origin must be one vector"),
    (lambda: OccupancyGrid(SMALL).integrate(_points(), TWO_ROWS),
     "sensor_origin must be one vector"),
    (lambda: OccupancyGrid(SMALL).integrate(_points(), [0, 0, 0], max_range="far"),
     "max_range must be a finite number"),
    (lambda: lt.trace_cones(SMALL, TWO_ROWS, TWO_ROWS, [0.1, 0.1, 0.1]),
     r"half_angles must be one number or one per cone \(2\)"),
    (lambda: lt.trace_cones(SMALL, TWO_ROWS, TWO_ROWS, "wide"), "half_angles must be numbers"),
])
def test_inputs_that_were_silently_misread_are_refused(call, match):
    with pytest.raises(ValueError, match=match):
        call()


def test_no_cones_is_no_result():
    assert lt.trace_cones(SMALL, np.empty((0, 3)), np.empty((0, 3)), 0.1) == []


def test_a_tiny_sigma_gives_finite_weights_not_nan():
    cone = lt.trace_cone(SMALL, [0, 0, 0], [0, 0, 1], np.radians(5), n_rays=50, sigma=1e-6)
    assert np.all(np.isfinite(cone.ray_weights)) and np.isclose(cone.ray_weights.sum(), 1.0)
    assert np.all(np.isfinite(cone.weights))
    assert cone.ray_weights[0] == cone.ray_weights.max()  # the ray nearest the axis


def test_huge_and_tiny_directions_trace_like_unit_ones():
    origin = np.array([0.5, 0.2, -0.1])
    unit = np.array([0.3, -0.2, 0.9]) / np.linalg.norm([0.3, -0.2, 0.9])
    reference = lt.trace(SMALL, origin, unit)
    for scale in (1e200, 1e-200, 1e300):
        other = lt.trace(SMALL, origin, unit * scale)
        np.testing.assert_array_equal(other.cells, reference.cells)
        np.testing.assert_allclose(other.t_exit, reference.t_exit, rtol=1e-14)


# ---- units ----------------------------------------------------------------

def test_a_half_angle_that_looks_like_degrees_warns():
    with pytest.warns(lt.AngleUnitWarning, match=r"np\.radians\(1\)"):
        lt.trace_cone(SMALL, [0, 0, 0], [0, 0, 1], 1.0, n_rays=20)


def test_a_gaze_sized_half_angle_does_not_warn(recwarn):
    lt.trace_cone(SMALL, [0, 0, 0], [0, 0, 1], np.radians(10), n_rays=20)
    assert not [w for w in recwarn if issubclass(w.category, lt.AngleUnitWarning)]


# ---- memory ---------------------------------------------------------------

@pytest.mark.parametrize("workers", [3, 5])
def test_a_batch_in_ordered_chunks_touches_only_its_output(workers):
    # The output is reserved by sampled upper bounds with a margin (here
    # 1.9x what it holds), but only the pages the chunks are written to
    # become resident: peak resident growth within 1.1x the output, plus the
    # pages at its end (huge pages: 2 MiB per array) and the chunks' scratch
    # (kept between calls: this call reuses the first one's). The arrays are
    # then shrunk in place to the exact size. The output (dozens of the
    # blocks the workers fault in ahead of the chunks) equals the serial
    # pass's: no block is cleared after a chunk was copied into it.
    from bench.parallel_memory import reset_peak, status
    from logsph_trace import _batching, _validate

    if not reset_peak():
        pytest.skip("needs Linux's /proc/self/clear_refs")
    grid = lt.Grid(0.1, 10.0, 128, 128, 128)
    rng = np.random.default_rng(3)
    o, d = _validate.rays(rng.uniform(-8, 8, (100_000, 3)), rng.normal(size=(100_000, 3)))
    far = np.full(len(o), np.inf)
    run = lambda n: _batching.run_exact_ordered(grid, o[:n], d[:n], far[:n], workers)  # noqa: E731
    run(len(o))  # compile; scratch
    before = status("VmRSS")
    assert reset_peak()
    traces = run(len(o))
    grown = status("VmHWM") - before
    arrays = (traces.offsets, traces.cells, traces.t_enter, traces.t_exit)
    output = sum(a.nbytes for a in arrays)
    assert grown <= 1.1 * output + 8 * 2**20, (grown / 2**20, output / 2**20)
    assert all(a.base is None for a in arrays)  # no spare capacity kept alive by views
    serial = _batching.run_exact(grid, o, d, far, False)
    for name in ("offsets", "cells", "t_enter", "t_exit"):
        np.testing.assert_array_equal(getattr(traces, name), getattr(serial, name))


def test_requests_that_cannot_fit_fail_before_allocating():
    with pytest.raises(MemoryError, match=r"n_theta: a grid with n_theta=10,000,000,000"):
        lt.Grid(0.3, 10, 64, 10**10, 180)
    with pytest.raises(MemoryError, match="n_rays: a cone of 1,000,000,000 rays"):
        lt.trace_cone(SMALL, [0, 0, 0], [0, 0, 1], 0.05, n_rays=10**9)
    with pytest.raises(MemoryError, match="n_rays: 3 cones of 1,500,000,000 rays in all"):
        lt.trace_cones(SMALL, [0, 0, 0], np.eye(3), 0.05, n_rays=5 * 10**8)
    with pytest.raises(MemoryError, match=r"grid: an occupancy map of \(20000, 20000, 20000\)"):
        OccupancyGrid(lt.Grid(0.3, 10, 20000, 20000, 20000))


def test_an_occupancy_map_counts_its_labels_in_the_memory_it_needs(monkeypatch):
    # log-odds (float32) and labels (int32) per cell, and a flag byte per cell
    # while integrating: memory for all but the labels is too little.
    from logsph_trace import _validate

    grid = lt.Grid(0.3, 10, 8, 12, 6)
    n_cells = 8 * 12 * 6
    without_labels = n_cells * (4 + 1)
    monkeypatch.setattr(_validate, "SMALL_REQUEST_BYTES", 0)  # this map is small
    monkeypatch.setattr(_validate, "available_memory", lambda: without_labels + 100)
    with pytest.raises(MemoryError, match=r"grid: an occupancy map of \(8, 12, 6\) cells"):
        OccupancyGrid(grid)
    monkeypatch.setattr(_validate, "available_memory", lambda: without_labels + 4 * n_cells)
    OccupancyGrid(grid)


def test_only_requests_of_16_mib_or_more_read_the_available_memory(monkeypatch):
    # Reading it costs about 0.05 ms a call, a share of a small cone's time.
    from logsph_trace import _validate

    def unread():
        raise AssertionError("the available memory was read")

    monkeypatch.setattr(_validate, "available_memory", unread)
    _validate.fits("n_rays", (1 << 24) - 1, "a request")
    lt.trace_cone(SMALL, [0, 0, 0], [0, 0, 1], 0.05, n_rays=300)
    monkeypatch.setattr(_validate, "available_memory", lambda: (1 << 24) - 1)
    with pytest.raises(MemoryError, match="n_rays: a request needs about 0.0 GiB"):
        _validate.fits("n_rays", 1 << 24, "a request")


MEMINFO = (b"MemTotal:       24684564 kB\nMemFree:        23100000 kB\n"
           b"MemAvailable:   23500000 kB\nBuffers:            1234 kB\n")


@pytest.mark.parametrize("files, expected", [
    # cgroup v2 with a limit: the smaller of the two.
    ({"/proc/meminfo": MEMINFO, "/sys/fs/cgroup/memory.max": b"1073741824\n",
      "/sys/fs/cgroup/memory.current": b"73741824\n"}, 1_000_000_000),
    # v2 without a limit: MemAvailable, and v1 is not read.
    ({"/proc/meminfo": MEMINFO, "/sys/fs/cgroup/memory.max": b"max\n",
      "/sys/fs/cgroup/memory.current": b"5\n",
      "/sys/fs/cgroup/memory/memory.limit_in_bytes": b"10\n",
      "/sys/fs/cgroup/memory/memory.usage_in_bytes": b"5\n"}, 23_500_000 * 1024),
    # v1 alone, "unlimited" as v1 writes it.
    ({"/proc/meminfo": MEMINFO,
      "/sys/fs/cgroup/memory/memory.limit_in_bytes": b"9223372036854771712\n",
      "/sys/fs/cgroup/memory/memory.usage_in_bytes": b"1000\n"}, 23_500_000 * 1024),
    # MemAvailable as the first line; a cgroup file with garbage is passed over.
    ({"/proc/meminfo": b"MemAvailable: 7 kB\n", "/sys/fs/cgroup/memory.max": b"lots\n",
      "/sys/fs/cgroup/memory.current": b"1\n"}, 7 * 1024),
    # No MemAvailable (an old kernel), no cgroup: unknown.
    ({"/proc/meminfo": b"MemTotal: 10 kB\nMemFree: 5 kB\n"}, None),
    ({}, None),
])
def test_the_available_memory_is_read_from_meminfo_and_the_cgroup(monkeypatch, files, expected):
    from logsph_trace import _validate

    monkeypatch.setattr(_validate, "_read_small", files.get)
    assert _validate.available_memory() == expected


def test_the_available_memory_of_this_machine_is_a_positive_count():
    from logsph_trace import _validate

    available = _validate.available_memory()
    assert available is None or isinstance(available, int) and available > 0
    if os.path.exists("/proc/meminfo"):
        assert _validate._read_small("/proc/meminfo").startswith(b"MemTotal:")
        assert available is not None
    assert _validate._read_small("/no/such/file") is None


def test_a_large_cone_scratch_is_released(monkeypatch):
    from logsph_trace import _batching

    monkeypatch.setattr(_batching, "KEEP_SCRATCH_SEGMENTS", 100)
    monkeypatch.setattr(_batching, "_scratch", type(_batching._scratch)())
    lt.trace_cone(SMALL, [0, 0, 0], [0, 0, 1], 0.05, n_rays=300)
    assert getattr(_batching._scratch, "segments", None) is None


# ---- fork and threads -----------------------------------------------------

_FORK_AFTER_PARALLEL = """
import multiprocessing, numpy as np, logsph_trace as lt
grid = lt.Grid(0.3, 10, 16, 36, 18)
rng = np.random.default_rng(0)
o, d = rng.normal(size=(4000, 3)), rng.normal(size=(4000, 3))
want = lt.trace_many(grid, o, d, parallel=True).cells.shape[0]
def child(seed):
    return lt.trace_many(grid, o, d, parallel=True).cells.shape[0]
with multiprocessing.get_context("fork").Pool(2) as pool:
    assert pool.map(child, range(4)) == [want] * 4
print("ok", __import__("numba").threading_layer())
"""

_THREADS_AT_ONCE = """
import threading, numpy as np, logsph_trace as lt
from logsph_trace import _batching, _validate
grid = lt.Grid(0.3, 10, 16, 36, 18)
rng = np.random.default_rng(0)
o, d = _validate.rays(rng.normal(size=(4000, 3)), rng.normal(size=(4000, 3)))
far = np.full(len(o), np.inf)
want = lt.trace_many(grid, o, d, parallel=False).cells
errors = []
def work():
    for _ in range(20):
        if not np.array_equal(lt.trace_many(grid, o, d, parallel=True).cells, want):
            errors.append("mismatch")
        # The path of three threads or more, whose workers wait on each other.
        if not np.array_equal(_batching.run_exact_ordered(grid, o, d, far, 3).cells, want):
            errors.append("mismatch in ordered chunks")
threads = [threading.Thread(target=work) for _ in range(4)]
for t in threads: t.start()
for t in threads: t.join()
assert not errors, errors
print("ok", __import__("numba").threading_layer())
"""

# More threads than CPUs: the ordered chunks' workers wait on each other, and
# the one waited for may be off its CPU. Fresh output, so the waits for blocks
# faulted in by another worker come up too (a block is 2**17 rows). Every
# layer starts this many threads; workqueue is the one every install has.
_MORE_THREADS_THAN_CPUS = """
import os, numba, numpy as np, logsph_trace as lt
threads = numba.config.NUMBA_NUM_THREADS
assert threads > (os.cpu_count() or 1), threads
grid = lt.Grid(0.05, 10, 64, 72, 36)
rng = np.random.default_rng(5)
o, d = rng.normal(scale=3, size=(30000, 3)), rng.normal(size=(30000, 3))
want = lt.trace_many(grid, o, d, parallel=False)
numba.set_num_threads(threads)
for _ in range(3):
    got = lt.trace_many(grid, o, d, parallel=True)
    for name in ("offsets", "cells", "t_enter", "t_exit"):
        assert np.array_equal(getattr(got, name), getattr(want, name)), name
assert got.cells.shape[0] > 2 ** 18, got.cells.shape
print("ok", numba.threading_layer(), threads)
"""

def _run(script, **env):
    import subprocess
    import sys

    environment = dict(os.environ, LOGSPH_TRACE_CACHE="1", **env)
    return subprocess.run([sys.executable, "-c", script], capture_output=True, text=True,
                          timeout=120, env=environment)


@pytest.mark.skipif(not hasattr(os, "fork"), reason="fork is POSIX only")
def test_fork_after_a_parallel_call_works():
    result = _run(_FORK_AFTER_PARALLEL)
    assert result.returncode == 0, result.stderr[-2000:]
    assert result.stdout.startswith("ok")


def test_python_threads_may_call_in_parallel_on_the_workqueue_layer():
    result = _run(_THREADS_AT_ONCE, NUMBA_THREADING_LAYER="workqueue")
    assert result.returncode == 0, result.stderr[-2000:]
    assert result.stdout.strip() == "ok workqueue"


def test_more_threads_than_cpus_give_the_serial_answer():
    threads = 2 * (os.cpu_count() or 1) + 1
    result = _run(_MORE_THREADS_THAN_CPUS, NUMBA_THREADING_LAYER="workqueue",
                  NUMBA_NUM_THREADS=str(threads))
    assert result.returncode == 0, result.stderr[-2000:]
    assert result.stdout.split() == ["ok", "workqueue", str(threads)]


def test_python_threads_may_call_in_parallel_on_the_default_layer():
    result = _run(_THREADS_AT_ONCE)
    assert result.returncode == 0, result.stderr[-2000:]
    assert result.stdout.startswith("ok")


def test_the_ordered_chunks_scratch_is_kept_between_calls(monkeypatch):
    # The chunks' scratch is reused by the next call in this Python thread,
    # whatever its size (only the pages the chunks write are ever touched),
    # and a call from another Python thread gets its own.
    import threading

    from logsph_trace import _batching, _validate

    monkeypatch.setattr(_batching, "KEEP_SCRATCH_SEGMENTS", 100)
    monkeypatch.setattr(_batching, "_scratch", type(_batching._scratch)())
    o, d = _validate.rays(_points(3000), _points(3000, seed=1))
    far = np.full(len(o), np.inf)
    first = _batching.run_exact_ordered(SMALL, o, d, far, 3)
    held = _batching._scratch.ordered
    second = _batching.run_exact_ordered(SMALL, o, d, far, 3)
    assert _batching._scratch.ordered is held
    other = []
    thread = threading.Thread(target=lambda: other.append(
        (_batching.run_exact_ordered(SMALL, o, d, far, 3), _batching._scratch.ordered)))
    thread.start()
    thread.join()
    assert other[0][1] is not held
    want = _batching.run_exact(SMALL, o, d, far, False)
    for got in (first, second, other[0][0]):
        np.testing.assert_array_equal(got.cells, want.cells)
        np.testing.assert_array_equal(got.t_exit, want.t_exit)


def test_the_fault_in_blocks_are_sized_by_the_call_not_by_a_frozen_constant():
    # The ordered path's helpers that fault in output by blocks (touched,
    # touch_ahead) are cached each on its own. When they read TOUCH_ROWS as a
    # global, frozen in, a copy cached while a test had set it to 5 once met
    # a chain whose blocks were 2^17 rows: it waited for blocks past the end
    # of its array, and every later process that compiled the ordered path
    # hung. The block size is now the call's (an argument, kept in
    # ordered.chain's state), and the helpers read it from there: blocks of
    # 1,000 rows here.
    from logsph_trace.kernels import ordered

    rows, block = 5000, 1000
    cells = np.ones((rows, 3), dtype=np.int32)
    t_enter, t_exit = np.ones(rows), np.ones(rows)

    def fresh_rows():
        fresh = np.zeros(ordered.DONE + rows // block, dtype=np.int64)
        fresh[ordered.FRESH_END] = rows
        fresh[ordered.BLOCK_ROWS] = block
        return fresh

    fresh = fresh_rows()
    ordered.touched(10, rows - 10, fresh, cells, t_enter, t_exit)
    assert fresh[ordered.CLAIMED] == rows // block
    assert np.all(fresh[ordered.DONE:] == 1)
    assert np.all(cells[::block, 0] == 0) and np.all(t_exit[::block] == 0)  # faulted in
    # Paced by chunk 1's start: two chunks of 2,500 rows reach the end.
    fresh = fresh_rows()
    ordered.touch_ahead(2, 1, np.array([0, 2500, -1]), fresh, cells, t_enter, t_exit)
    assert np.all(fresh[ordered.DONE:] == 1)
