"""The atomic helpers shared arrays are updated with (``kernels.atomic``).

A minimum or a maximum must compare as the array's integers do: the coherent
scan's bin limits are uint8, and a signed comparison would take 200 for -56.
"""

import numpy as np
import pytest

from logsph_trace._jit import jit
from logsph_trace.kernels.atomic import fetch_max, fetch_min, lower_to, raise_to

# The kernels here inline the package's helpers, but a file outside the
# package is cached against itself alone (``_jit.cache_by_package``): after an
# edit to ``kernels/atomic.py`` a cached copy would test the old helpers. So
# they are compiled afresh in each run (well under a second).
uncached = jit(cache=False)


@uncached
def _min_then_max(array, index, low, high):
    first = fetch_min(array, index, low)
    second = fetch_max(array, index, high)
    return first, second


@pytest.mark.parametrize("dtype, start, low, high", [
    (np.uint8, 100, 200, 90),       # above 127: signed would take 200 for -56
    (np.uint8, 7, 3, 250),
    (np.uint64, 5, 2**63 + 1, 2**64 - 2),
    (np.int64, -3, -2**62, 2**61),  # signed stays signed
    (np.int32, 5, -9, -1),          # a maximum below what it holds changes nothing
])
def test_fetch_min_and_max_compare_as_the_arrays_integers(dtype, start, low, high):
    array = np.array([11, start, 13], dtype=dtype)
    first, second = _min_then_max(array, 1, dtype(low), dtype(high))
    lowered = min(start, low)
    assert (int(first), int(second)) == (start, lowered)
    assert array.tolist() == [11, max(lowered, high), 13]


@uncached
def _raise_all(array, indices, values):
    for n in range(indices.shape[0]):
        raise_to(array, indices[n], values[n])


@uncached
def _lower_all(array, indices, values):
    for n in range(indices.shape[0]):
        lower_to(array, indices[n], values[n])


def test_raise_to_keeps_the_largest_value_each_index_is_given():
    rng = np.random.default_rng(3)
    indices = rng.integers(0, 50, 2000)
    values = rng.integers(0, 1000, 2000)
    array = np.zeros(50, dtype=np.int64)
    _raise_all(array, indices, values)
    want = np.zeros(50, dtype=np.int64)
    np.maximum.at(want, indices, values)
    np.testing.assert_array_equal(array, want)


def test_lower_to_keeps_the_smallest_value_each_index_is_given():
    rng = np.random.default_rng(4)
    indices = rng.integers(0, 50, 2000)
    values = rng.integers(0, 250, 2000).astype(np.uint8)
    array = np.full(50, 255, dtype=np.uint8)  # unsigned, above 127: as the bins' limits
    _lower_all(array, indices, values)
    want = np.full(50, 255, dtype=np.uint8)
    np.minimum.at(want, indices, values)
    np.testing.assert_array_equal(array, want)
