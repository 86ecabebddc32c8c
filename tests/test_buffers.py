"""``trace_many(..., out=TraceBuffers())``: caller-owned arrays reused between calls."""

import numba
import numpy as np
import pytest
from conftest import GRIDS, random_rays

import logsph_trace as lt
from logsph_trace import _batching, _validate
from logsph_trace.kernels import geometry as _geometry

FIELDS = ("offsets", "cells", "t_enter", "t_exit")


def assert_same(result, want):
    for name in FIELDS:
        np.testing.assert_array_equal(getattr(result, name), getattr(want, name))


def _ordered(grid, origins, directions, buffers):
    """The path of two threads or more into ``buffers``, on any machine (three workers)."""
    o, d = _validate.rays(origins, directions)
    args = grid.kernel_args()
    return _batching.run_ordered(_batching.EXACT_KERNELS, (o, d, np.full(len(o), np.inf), args),
                                 (o, d, args), len(o), int(_geometry.max_segments(*grid.shape)), 3,
                                 buffers)


@pytest.mark.parametrize("path", ["serial", "parallel", "ordered"])
def test_reused_buffers_give_the_fresh_result_on_every_call(monkeypatch, path):
    # Batches of growing and shrinking sizes through one set of buffers: the
    # first call finds them empty, later ones too small (they grow) or big
    # enough (reused as they are); every result equals a fresh trace. The
    # ordered chunks are a few rays each, and their reservation too small:
    # the output grows while they are placed, into fresh arrays.
    monkeypatch.setattr(_batching, "ORDERED_SEGMENTS", 2000)
    if path == "ordered":
        monkeypatch.setattr(_batching, "RESERVE_MARGIN", 0.1)
    grid = GRIDS["log_full"]()
    rng = np.random.default_rng(5)
    buffers = lt.TraceBuffers()
    capacities = []
    batches = [random_rays(rng, grid, n) for n in (700, 3000, 40, 1200)]
    for origins, directions in batches + batches[1:2]:
        want = lt.trace_many(grid, origins, directions, parallel=False)
        if path == "ordered":
            got = _ordered(grid, origins, directions, buffers)
        else:
            got = lt.trace_many(grid, origins, directions, parallel=path == "parallel",
                                out=buffers)
        assert_same(got, want)
        assert np.shares_memory(got.t_enter, buffers.t_enter)
        capacities.append(buffers.capacity)
    assert capacities == sorted(capacities)  # they grow, never shrink
    assert capacities[-1] == capacities[-2]  # the same batch again: no new memory


def test_an_earlier_result_stays_valid_memory_when_buffers_grow():
    # Buffers never resize arrays in place: a result that still views the old
    # arrays keeps them alive (its values are stale only if they were reused).
    grid = GRIDS["log_full"]()
    rng = np.random.default_rng(6)
    buffers = lt.TraceBuffers()
    small = random_rays(rng, grid, 50)
    first = lt.trace_many(grid, *small, out=buffers)
    kept = first.cells.copy()
    big = random_rays(rng, grid, 5000)
    lt.trace_many(grid, *big, out=buffers)  # needs far more room: new arrays
    np.testing.assert_array_equal(first.cells, kept)


def test_ordered_chunks_write_into_buffers_big_enough_from_the_start():
    # Buffers sized by a first call: the ordered chunks are placed straight
    # into them, on 1 to 4 workers, and equal the serial pass.
    grid = GRIDS["uniform_partial_wide"]()
    rng = np.random.default_rng(8)
    origins, directions = random_rays(rng, grid, 4000)
    want = lt.trace_many(grid, origins, directions, parallel=False)
    o, d = _validate.rays(origins, directions)
    far = np.full(len(o), np.inf)
    for workers in (1, 2, 3, 4):
        buffers = lt.TraceBuffers()
        _ordered(grid, origins, directions, buffers)  # sizes them
        capacity = buffers.capacity
        got = _batching.run_ordered(_batching.EXACT_KERNELS, (o, d, far, grid.kernel_args()),
                                    (o, d, grid.kernel_args()), len(o),
                                    int(_geometry.max_segments(*grid.shape)), workers, buffers)
        assert_same(got, want)
        assert np.shares_memory(got.t_enter, buffers.t_enter)
        assert buffers.capacity == capacity


def test_out_is_checked():
    grid = GRIDS["log_full"]()
    with pytest.raises(TypeError, match="out must be a TraceBuffers"):
        lt.trace_many(grid, [0.0, 0.0, 1.0], [1.0, 0.0, 0.0], out=np.empty(10))
    with pytest.raises(ValueError, match="out is supported by method='exact' only"):
        lt.trace_many(grid, [0.0, 0.0, 1.0], [1.0, 0.0, 0.0], method="bisect",
                      out=lt.TraceBuffers())
    assert "0 segments" in repr(lt.TraceBuffers())


def test_buffers_with_threads_set_to_one():
    grid = GRIDS["log_full"]()
    rng = np.random.default_rng(9)
    origins, directions = random_rays(rng, grid, 2000)
    before = numba.get_num_threads()
    numba.set_num_threads(1)
    try:
        got = lt.trace_many(grid, origins, directions, out=lt.TraceBuffers())
    finally:
        numba.set_num_threads(before)
    assert_same(got, lt.trace_many(grid, origins, directions, parallel=False))


def test_buffers_arrays_cannot_be_replaced():
    # The kernels write up to the capacity the buffers report: a shorter
    # array swapped in for one of them was written out of bounds (heap
    # corruption) before these became read-only attributes.
    buffers = lt.TraceBuffers()
    for name in FIELDS:
        with pytest.raises(AttributeError):
            setattr(buffers, name, np.empty(5))


def _reshape(array):
    array.shape = (1, array.size)


def _retype(array):
    array.dtype = np.float32 if array.dtype == np.float64 else np.int16


def _shrink(array):
    array.resize(5, refcheck=False)


@pytest.mark.parametrize("name", FIELDS)
@pytest.mark.parametrize("change, match", [
    (lambda a: a.setflags(write=False), "writeable=False"),
    (_reshape, "changed in place"),
    (_retype, "changed in place"),
    (_shrink, "changed in place"),
])
def test_buffers_changed_in_place_are_refused_before_tracing(name, change, match):
    # numpy lets an array's shape, dtype and flags change in place, so each
    # call reads them again (in O(1)) and refuses what the kernels cannot
    # write into, instead of writing past an array's end or failing in Numba.
    grid = GRIDS["log_full"]()
    origins, directions = random_rays(np.random.default_rng(10), grid, 500)
    buffers = lt.TraceBuffers()
    lt.trace_many(grid, origins, directions, out=buffers)
    array = getattr(buffers, name)
    if change is _shrink and name == "cells":
        array.resize((5, 3), refcheck=False)
    else:
        change(array)
    want = lt.trace_many(grid, origins, directions, parallel=False)
    if change is _shrink and name == "offsets":  # too short: replaced, as when it was empty
        assert_same(lt.trace_many(grid, origins, directions, out=buffers), want)
        return
    for parallel in (False, True):
        with pytest.raises(ValueError, match=match):
            lt.trace_many(grid, origins, directions, parallel=parallel, out=buffers)
    assert_same(lt.trace_many(grid, origins, directions, out=lt.TraceBuffers()), want)
