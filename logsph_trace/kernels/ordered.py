"""Chunks of rays taken in order and placed by the threads that traced them.

The batch path on three threads or more (``exact.trace_ordered``,
``cartesian.box_ordered``; ``_batching.run_ordered``). A trace's length is
unknown before it is traced, so where a chunk of rays belongs in the output
is known only once every chunk before it has been traced. Here each thread
(a *worker*) takes the next chunk from a shared counter (``take``), traces
it into one of its two scratch buffers, and posts the chunk's segment count
(``post``). Posting also settles the chain of positions: chunk c starts
where chunk c - 1 ends, so whichever thread posts the last count a start
depends on publishes that start, and the ones after it that are already
counted. The worker then copies the chunk it traced before, waiting in
its other buffer, to its place (``start_of``, ``place``); by then its
start is almost always known, so a worker waits only for a chunk taken
before its own that is still being traced, and a slow chunk stalls no
one for longer than one chunk of tracing.

Compared with tracing a round of chunks into scratch and then gathering
them (the path this replaced), nothing waits for the slowest thread of a
round, no phase runs on one thread, and the output is written once, by
non-temporal stores from a scratch small enough to stay in the cache
(``stream.stream_segments``). Its pages are faulted in ahead of the
chunks, on all threads, each a contiguous stretch (``touch_pages``), once
the first chunks have shown how many the batch needs.

A chunk is sized to fit its buffer whatever its rays do (``max_segments``
per ray), so tracing never stops inside a chunk. The output is reserved
in advance from sampled bounds; a chunk that would end past it is not
placed, and neither is any chunk after it (their starts are larger):
``reached`` says which rows were placed, and the caller grows the output
and traces the rest again.

Progress: a worker waits only for the start of a chunk it took, which
depends on the counts of chunks taken earlier, each by a worker that was
running when it took it and posts that count before it waits for
anything. Counts and starts are sequentially consistent atomics, so of a
thread posting a count and one publishing the start before it, at least
one sees the other's store and carries the chain on.
"""

import numpy as np
from numba import prange

from .._jit import jit
from .atomic import fetch_add, load_ordered, store_ordered
from .stream import stream_segments


@jit(inline="always")
def take(counter, n_chunks):
    """The next chunk to trace, or -1 when every chunk has been taken."""
    chunk = fetch_add(counter, 0, 1)
    return chunk if chunk < n_chunks else -1


@jit(inline="always")
def post(chunk, count, counts, starts):
    """Post ``chunk``'s segment ``count`` and publish every start it settles.

    ``starts[c]`` is where chunk c begins in the output (-1 until known),
    ``counts[c]`` its segments (-1 until traced).
    """
    store_ordered(counts, chunk, count)
    n_chunks = counts.shape[0]
    while chunk < n_chunks:
        start = load_ordered(starts, chunk)
        if start < 0:
            return  # an earlier chunk is still being traced: its poster carries on
        count = load_ordered(counts, chunk)
        if count < 0:
            return  # this one is: its poster carries on
        store_ordered(starts, chunk + 1, start + count)
        chunk += 1


@jit(inline="always")
def start_of(chunk, starts):
    """Where ``chunk`` begins, once every chunk before it is counted (waits)."""
    start = load_ordered(starts, chunk)
    while start < 0:
        start = load_ordered(starts, chunk)
    return start


@jit(inline="always")
def chain(first_row, last_row, chunk_rays, used):
    """A call's shared state: (n_chunks, counts, starts, reached, counter).

    ``counts`` and ``starts`` as in ``post`` (chunk 0 starts at ``used``);
    ``reached[c]``: the first of chunk c's rows not placed; ``counter``: the
    next chunk to take.
    """
    n_chunks = (last_row - first_row + chunk_rays - 1) // chunk_rays
    counts = np.full(n_chunks, -1, dtype=np.int64)
    starts = np.full(n_chunks + 1, -1, dtype=np.int64)
    starts[0] = used
    reached = np.empty(n_chunks, dtype=np.int64)
    counter = np.zeros(1, dtype=np.int64)
    return n_chunks, counts, starts, reached, counter


@jit(inline="always")
def rows_of(chunk, first_row, chunk_rays, last_row):
    """Chunk ``chunk``'s rays: rows first..last-1."""
    first = first_row + chunk * chunk_rays
    return first, min(last_row, first + chunk_rays)


@jit(inline="always")
def buffer_of(worker, side, room):
    """The first scratch row of ``worker``'s buffer ``side`` (0 or 1)."""
    return (2 * worker + side) * room


@jit(inline="always")
def place(chunk, source, first_row, last_row, chunk_rays, counts, starts, reached, loose_cells,
          loose_enter, loose_exit, cells, t_enter, t_exit, offsets):
    """Copy traced ``chunk`` (none when -1) from row ``source`` of the scratch to its
    place in the output, once its start is known; set ``reached[chunk]``.

    The chunk's rays wrote their ends as scratch positions into
    ``offsets``; they become output positions. A chunk that would end past
    the output is not placed (``reached[chunk]`` is then its first row).
    """
    if chunk < 0:
        return
    first, last = rows_of(chunk, first_row, chunk_rays, last_row)
    count = counts[chunk]
    target = start_of(chunk, starts)
    if target + count > cells.shape[0]:
        reached[chunk] = first
        return
    stream_segments(loose_cells, loose_enter, loose_exit, source, count, cells, t_enter, t_exit,
                    target)
    shift = target - source
    for row in range(first + 1, last + 1):
        offsets[row] += shift
    reached[chunk] = last


@jit(inline="always")
def advance(chunk, waiting, worker, side, room, first_row, last_row, chunk_rays, counter, counts,
            starts, reached, loose_cells, loose_enter, loose_exit, cells, t_enter, t_exit,
            offsets):
    """A worker's step after tracing ``chunk`` (-1: none was left) into its buffer
    ``side``: place the chunk ``waiting`` in its other buffer, and take the next.

    Returns the next round's (waiting, side, chunk); the worker is done when
    both chunks are -1.
    """
    place(waiting, buffer_of(worker, 1 - side, room), first_row, last_row, chunk_rays, counts,
          starts, reached, loose_cells, loose_enter, loose_exit, cells, t_enter, t_exit, offsets)
    return chunk, 1 - side, take(counter, counts.shape[0]) if chunk >= 0 else -1


@jit(parallel=True)
def touch_pages(cells, t_enter, t_exit, first, last):
    """Write a zero into every 4 KiB page of rows ``first..last-1`` of fresh output.

    The OS gives a page its memory on its first write. Done here, spread
    over the threads in contiguous stretches, a (huge) page is faulted in by
    one thread; done by the chunks' copies, several threads that place
    neighbouring chunks fault the same huge page at once, and each clears a
    page of its own before all but one are thrown away. No other thread
    may write these rows meanwhile.
    """
    step = 512  # float64 values per 4 KiB page; cells rows are 12 bytes, so 512 rows span 1.5
    for block in prange((last - first + step - 1) // step):
        row = first + block * step
        cells[row, 0] = 0
        cells[min(row + step // 2, last - 1), 0] = 0
        t_enter[row] = 0.0
        t_exit[row] = 0.0
