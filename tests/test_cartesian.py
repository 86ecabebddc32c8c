"""The Amanatides-Woo baseline against a brute-force Cartesian oracle."""

import numpy as np
import pytest
from oracle import box_oracle_trace, compare

from logsph_trace.cartesian import CartesianGrid


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
