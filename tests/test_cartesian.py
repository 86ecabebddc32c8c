"""The Amanatides-Woo baseline against a brute-force Cartesian oracle."""

import numpy as np
import pytest
from oracle import box_oracle_trace, compare

from logsph_trace.cartesian import BOX_KERNELS, CartesianGrid
from logsph_trace.kernels.baselines import amanatides_woo as _kernels


@pytest.mark.parametrize("shape", [(1, 1, 1), (7, 8, 9), (16, 16, 16)])
def test_amanatides_woo_matches_brute_force(shape):
    low, high = (-3.0, -2.0, -1.0), (3.0, 2.5, 4.0)
    box = CartesianGrid(low, high, shape)
    rng = np.random.default_rng(sum(shape))
    origins = rng.uniform(-6, 6, (1500, 3))
    directions = rng.normal(size=(1500, 3))
    # Axis-parallel rays and rays through voxel corners too.
    directions[:100, 1:] = 0.0
    origins[100:200] = np.round(origins[100:200])
    traces = box.trace_many(origins, directions)
    serial = box.trace_many(origins, directions, parallel=False)
    np.testing.assert_array_equal(traces.cells, serial.cells)
    for row in range(len(origins)):
        one = traces[row]
        want = box_oracle_trace(origins[row], directions[row], low, high, shape)
        message = compare((one.cells, one.t_enter, one.t_exit), want, 6.0)
        assert message is None, f"ray {row}: {message}"


def test_bad_box():
    with pytest.raises(ValueError, match="low must be < high"):
        CartesianGrid((0, 0, 0), (1, 0, 1), (2, 2, 2))
    with pytest.raises(ValueError, match=r"shape\[1\] must be a positive integer"):
        CartesianGrid((0, 0, 0), (1, 1, 1), (2, 0, 2))


@pytest.mark.parametrize("chunk_segments, margin", [(1 << 18, 1.25), (50, 0.05)])
def test_parallel_chunks_equal_the_serial_pass(monkeypatch, chunk_segments, margin):
    # The baseline batches like the exact method: one appending pass on one
    # thread, ordered chunks on more. With 50 segments a
    # chunk is one ray, and with 5% of the bounds reserved the output grows
    # many times.
    import numba

    from logsph_trace import _batching, _validate

    monkeypatch.setattr(_batching, "ORDERED_SEGMENTS", chunk_segments)
    monkeypatch.setattr(_batching, "RESERVE_MARGIN", margin)
    box = CartesianGrid((-1.0, -1.0, -1.0), (1.0, 2.0, 1.5), (13, 17, 11))
    rng = np.random.default_rng(7)
    origins = rng.uniform(-1.0, 1.0, (3000, 3))
    directions = rng.normal(size=(3000, 3))
    origins[:300] = [0.0, 0.0, 50.0]  # far away, pointing out: no voxels
    directions[:300] = [0.0, 0.0, 1.0]
    serial = box.trace_many(origins, directions, parallel=False)
    previous = numba.get_num_threads()
    try:
        numba.set_num_threads(min(2, numba.config.NUMBA_NUM_THREADS))
        results = [box.trace_many(origins, directions, parallel=True)]
    finally:
        numba.set_num_threads(previous)
    o, d = _validate.rays(origins, directions)
    inputs = (o, d, box.low, box.voxel_size, box._shape)
    ordered = _batching.run_ordered(BOX_KERNELS, inputs, inputs, len(o), sum(box.shape), 5)
    assert serial.cells.shape[0] > 5 * len(origins)
    for result in results + [ordered]:
        for name in ("offsets", "cells", "t_enter", "t_exit"):
            np.testing.assert_array_equal(getattr(result, name), getattr(serial, name))
            assert getattr(ordered, name).base is None  # it owns exactly its data


@pytest.mark.parametrize("shape", [(1, 1, 1), (7, 8, 9), (32, 32, 32)])
def test_the_box_bound_is_never_below_the_voxels_a_ray_crosses(shape):
    # bench.gpu sizes each ray's region with it: too small would overwrite the
    # next ray. Random rays, axis-parallel ones, and ones from voxel corners.
    box = CartesianGrid((-3.0, -2.0, -1.0), (3.0, 2.5, 4.0), shape)
    rng = np.random.default_rng(len(shape) + shape[0])
    origins = rng.uniform(-6, 6, (3000, 3))
    directions = rng.normal(size=(3000, 3))
    directions[:300, 1:] = 0.0
    directions[300:600] = np.eye(3)[rng.integers(0, 3, 300)] * rng.choice([-1.0, 1.0], (300, 1))
    origins[600:900] = np.round(origins[600:900] * 2.0) / 2.0
    directions /= np.linalg.norm(directions, axis=1)[:, None]
    counts = np.diff(box.trace_many(origins, directions, parallel=False).offsets)
    low = np.asarray(box.low, dtype=np.float64)
    size = np.asarray(box.voxel_size, dtype=np.float64)
    bounds = np.array([_kernels.box_bound(origins, directions, row, low, size,
                                          np.asarray(shape, dtype=np.int64))
                       for row in range(origins.shape[0])])
    assert np.all(bounds >= counts)
    assert np.all(bounds <= sum(shape))
    assert np.mean(bounds - counts) < 1.0  # tight: regions barely bigger than the output
