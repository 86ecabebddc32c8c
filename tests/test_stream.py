"""The non-temporal copies (``kernels.stream``) move exactly the elements asked for.

A copy is split into plain stores up to the first 32-byte aligned target,
aligned vector stores, and plain stores after the last whole vector. Every
split is exercised here: each alignment of source and target, and counts
from 0 to past several vectors. Elements outside the target range must keep
their sentinel values. The batch path that uses these copies (the ordered
chunks' placing) is checked against the serial trace in
``test_two_threads.py``, ``test_exact.py`` and ``test_safety.py``.
"""

import os
import subprocess
import sys
import textwrap

import numpy as np
import pytest

from logsph_trace.kernels import stream


@pytest.mark.parametrize("dtype", [np.float64, np.int32, np.int64])
def test_stream_copy_every_alignment_and_count(dtype):
    rng = np.random.default_rng(5)
    source = rng.integers(-(2**30), 2**30, 200).astype(dtype)
    per = stream.STREAM_BYTES // source.itemsize
    for count in [0, 1, per - 1, per, per + 1, 2 * per + 3, 5 * per, 37, 61]:
        for source_at in range(per + 1):
            for target_at in range(per + 1):
                target = np.full(count + 2 * per + 16, -7, dtype=dtype)
                stream.stream_copy(source, source_at, target, target_at + 8, count)
                expected = np.full_like(target, -7)
                expected[target_at + 8:target_at + 8 + count] = source[source_at:source_at + count]
                np.testing.assert_array_equal(target, expected,
                                              err_msg=f"{count=} {source_at=} {target_at=}")


def test_stream_copy_to_a_misaligned_target():
    """A float64 view 4 bytes off its alignment never gets an aligned vector store
    (which would crash the process: hence the subprocess)."""
    script = textwrap.dedent(
        """
        import numpy as np
        from logsph_trace.kernels import stream
        raw = np.zeros(8 * 64 + 8, dtype=np.uint8)
        target = np.ndarray(64, dtype=np.float64, buffer=raw,
                            offset=4 + (-raw.ctypes.data) % 8)
        assert target.ctypes.data % 8 == 4
        source = np.arange(64, dtype=np.float64)
        stream.stream_copy(source, 0, target, 0, 64)
        assert (target == source).all()
        """
    )
    subprocess.run([sys.executable, "-c", script], check=True, timeout=120)


def test_stream_segments_moves_rows_and_nothing_else():
    rng = np.random.default_rng(6)
    rows = 300
    cells = rng.integers(0, 1000, (rows, 3)).astype(np.int32)
    t_enter = rng.random(rows)
    t_exit = rng.random(rows)
    for source, count, target in [(0, 0, 5), (3, 1, 0), (0, 257, 11), (17, 100, 200), (1, 299, 1)]:
        out = (np.full((rows + 8, 3), -1, dtype=np.int32), np.full(rows + 8, -1.0),
               np.full(rows + 8, -1.0))
        stream.stream_segments(cells, t_enter, t_exit, source, count, *out, target)
        for got, given in zip(out, (cells, t_enter, t_exit)):
            expected = np.full_like(got, -1)
            expected[target:target + count] = given[source:source + count]
            np.testing.assert_array_equal(got, expected, err_msg=f"{source=} {count=} {target=}")


def test_stream_copy_without_jit():
    """With NUMBA_DISABLE_JIT=1 the vector stores are slice assignments with the same result."""
    script = textwrap.dedent(
        """
        import numpy as np
        from logsph_trace.kernels import stream
        source = np.arange(50, dtype=np.float64)
        for target_at in range(5):
            target = np.full(70, -1.0)
            stream.stream_copy(source, 3, target, target_at, 41)
            expected = np.full(70, -1.0)
            expected[target_at:target_at + 41] = source[3:44]
            assert (target == expected).all(), target_at
        """
    )
    env = dict(os.environ, NUMBA_DISABLE_JIT="1")
    subprocess.run([sys.executable, "-c", script], env=env, check=True, timeout=120)
