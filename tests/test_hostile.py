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

GRID = lt.Grid(0.3, 10.0, 12, 24, 12)


def _scan(seed=0, n=4000):
    return np.random.default_rng(seed).normal(size=(n, 3)) * 3.0


# ---- one map shared by threads ----


def test_threads_sharing_a_map_take_turns(monkeypatch):
    """Two scans of one map never run their kernels at once (a lost update
    otherwise: both read a cell's log-odds, each adds its own, one wins)."""
    from logsph_trace import occupancy as module

    spans = []
    kernel = module._kernels.mark_radial

    def slow(*args):
        start = time.perf_counter()
        time.sleep(0.2)  # long enough for the other thread to arrive
        kernel(*args)
        spans.append((start, time.perf_counter()))

    monkeypatch.setattr(module._kernels, "mark_radial", slow)
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
