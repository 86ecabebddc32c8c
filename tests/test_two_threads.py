"""The batch path of two threads: ordered chunks on two workers (``_batching.run_ordered``).

Every test compares with the serial pass bit for bit. The chunks are run on
two workers directly, so the tests do not depend on the machine's core count
(two workers run on one thread too); the last ones go through
``trace_many`` with two threads where the machine has them.
"""

import numba
import numpy as np
import pytest
from conftest import GRIDS, random_rays
from singular import CLASSES, singular_rays

import logsph_trace as lt
from logsph_trace import _batching, _validate

FIELDS = ("offsets", "cells", "t_enter", "t_exit")


def assert_same(result, want):
    for name in FIELDS:
        np.testing.assert_array_equal(getattr(result, name), getattr(want, name))


def two_workers(grid, origins, directions, t_max=None, buffers=None):
    """Ordered chunks of the exact method on two workers, inputs checked as ``trace_many`` does."""
    o, d = _validate.rays(origins, directions)
    t_max = _validate.distances(t_max, len(o))
    return _batching.run_exact_ordered(grid, o, d, t_max, 2, buffers)


@pytest.mark.parametrize("name", sorted(GRIDS))
@pytest.mark.parametrize("cut", [False, True])
def test_two_workers_equal_the_serial_pass_on_every_grid(name, cut):
    # Rays from inside, the gap and outside (a quarter miss the region); with
    # t_max anywhere along them, or to the end. The grids range from one
    # sector (a ray's worst case is a few segments, so a chunk holds
    # thousands of rays) to the paper's (hundreds).
    grid = GRIDS[name]()
    rng = np.random.default_rng(sorted(GRIDS).index(name) + 100 * cut)
    origins, directions = random_rays(rng, grid, 3000)
    t_max = rng.uniform(0.0, 2.5 * grid.rho_max, len(origins)) if cut else None
    want = lt.trace_many(grid, origins, directions, parallel=False, t_max=t_max)
    got = two_workers(grid, origins, directions, t_max)
    assert_same(got, want)
    assert got.offsets[0] == 0 and got.cells.flags.c_contiguous


@pytest.mark.parametrize("kind", CLASSES)
def test_two_workers_equal_the_serial_pass_on_near_singular_rays(kind):
    # Rays through or a hair (1e-15 .. 1e-3 of the scene) beside the centre,
    # the y axis, tangents and corners, from random eyes, in one batch each.
    grid = GRIDS["log_full"]()
    rng = np.random.default_rng(CLASSES.index(kind) + 77)
    origins, directions, _ = singular_rays(rng, grid, kind, 100)
    want = lt.trace_many(grid, origins, directions, parallel=False)
    assert_same(two_workers(grid, origins, directions), want)


def test_two_workers_with_rays_that_miss_at_either_end():
    # No segments at all for the first and the last third: the sampled
    # bounds are zero there.
    grid = GRIDS["thin_shell"]()
    rng = np.random.default_rng(3)
    origins, directions = random_rays(rng, grid, 3000)
    origins[:1000] = origins[2000:] = [0.0, 0.0, 50.0]
    directions[:1000] = directions[2000:] = [0.0, 0.0, 1.0]
    want = lt.trace_many(grid, origins, directions, parallel=False)
    assert_same(two_workers(grid, origins, directions), want)
    origins[:] = [0.0, 0.0, 50.0]
    directions[:] = [0.0, 0.0, 1.0]
    nothing = two_workers(grid, origins, directions)
    assert nothing.cells.shape == (0, 3) and np.all(nothing.offsets == 0)


@pytest.mark.parametrize("n_rays", [2, 3, 17, 600])
def test_two_workers_on_small_batches(n_rays):
    grid = GRIDS["paper_dm"]()
    origins, directions = random_rays(np.random.default_rng(n_rays), grid, n_rays)
    want = lt.trace_many(grid, origins, directions, parallel=False)
    assert_same(two_workers(grid, origins, directions), want)


@pytest.mark.parametrize("margin", [0.05, 0.6])
def test_an_output_reserved_too_small_grows(monkeypatch, margin):
    # With the sampled bounds scaled far down the reservation is too small:
    # the rows placed so far stay, the output grows, and the rest is traced
    # again, on two workers and through trace_many's two threads.
    grid = GRIDS["log_full"]()
    origins, directions = random_rays(np.random.default_rng(12), grid, 4000)
    want = lt.trace_many(grid, origins, directions, parallel=False)
    monkeypatch.setattr(_batching, "RESERVE_MARGIN", margin)
    assert_same(two_workers(grid, origins, directions), want)
    monkeypatch.setattr(numba, "get_num_threads", lambda: 2)
    assert_same(lt.trace_many(grid, origins, directions, parallel=True), want)


def test_a_reservation_that_does_not_fit_in_memory_is_not_made(monkeypatch):
    grid = GRIDS["log_full"]()
    origins, directions = random_rays(np.random.default_rng(13), grid, 2000)
    want = lt.trace_many(grid, origins, directions, parallel=False)
    # Only a large reservation is checked (reading the figure costs ~0.1 ms),
    # and only a large batch is split: both thresholds down to this one.
    monkeypatch.setattr(_batching, "CHECKED_BYTES", 0)
    monkeypatch.setattr(_validate, "SMALL_REQUEST_BYTES", 0)
    monkeypatch.setattr(_batching, "PARALLEL_MIN_RAYS", 512)
    monkeypatch.setattr(numba, "get_num_threads", lambda: 2)
    # Not even the bounds' estimate fits: a MemoryError before any tracing.
    monkeypatch.setattr(_validate, "available_memory", lambda: 10_000)
    with pytest.raises(MemoryError, match="origins: tracing 2,000 rays"):
        two_workers(grid, origins, directions)
    with pytest.raises(MemoryError, match="origins: tracing 2,000 rays"):
        lt.trace_many(grid, origins, directions, parallel=True)
    # The estimate fits, the reservation with its margin does not: the
    # ordered chunks reserve what there is, which holds the output.
    strata, bounds = _batching._sampled_bounds(
        _batching.EXACT_KERNELS, (*_validate.rays(origins, directions), grid.kernel_args()),
        2000)
    estimate = float(np.dot(bounds, np.diff(strata))) * _batching.SEGMENT_BYTES + 8 * 2000
    monkeypatch.setattr(_validate, "available_memory", lambda: int(1.05 * estimate))
    assert_same(two_workers(grid, origins, directions), want)
    assert_same(lt.trace_many(grid, origins, directions, parallel=True), want)


@pytest.mark.skipif(numba.config.NUMBA_NUM_THREADS < 2, reason="needs two threads")
def test_trace_many_on_two_threads_takes_the_ordered_chunks():
    # The public path: with two threads a batch of rays is traced in ordered
    # chunks, its output reserved from sampled bounds and shrunk to size.
    grid = GRIDS["log_full"]()
    origins, directions = random_rays(np.random.default_rng(15), grid, 5000)
    want = lt.trace_many(grid, origins, directions, parallel=False)
    previous = numba.get_num_threads()
    try:
        numba.set_num_threads(2)
        with _batching.phase_times() as phases:
            got = lt.trace_many(grid, origins, directions, parallel=True)
    finally:
        numba.set_num_threads(previous)
    assert_same(got, want)
    assert "bound" in phases and "shrink" in phases
