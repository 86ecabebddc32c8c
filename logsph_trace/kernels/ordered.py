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
(``stream.stream_segments``).

Fresh output is faulted in by the same workers while they trace, in
blocks of ``TOUCH_ROWS`` rows claimed in order from a second counter
(``touch_ahead``, ``touched``): before it takes a chunk, a worker faults in
blocks up to where the chunks taken so far will end, by the segments a
chunk has had, plus a lead. It holds no chunk then, so no worker waits for
it meanwhile (a block takes longer to fault in than a chunk to trace).
A block is faulted in by one thread, so no two
threads clear the same fresh (huge) page at once, as they do when the
chunks' copies fault it in; and the faulting runs between the tracing
instead of as a phase of its own, in which every thread would wait on the
memory bandwidth that clearing pages takes. A chunk is copied only into
blocks already faulted in (``touched``: the placer claims them itself
when the workers have not got that far), so a block is never cleared after
a chunk was written into it.

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
one sees the other's store and carries the chain on. A block being faulted
in is finished by the thread that claimed it, which waits for nothing
meanwhile.

Waiting: a worker spins on its load a short while (``SPINS`` loads), then
yields its CPU before each further one (``pause``). Waits are short when
every worker has a CPU of its own. With more threads than CPUs (a loaded
machine, or ``NUMBA_NUM_THREADS`` above the cores under the OpenMP or
workqueue layers, which start that many threads), the worker being waited
for may be off its CPU; spinning would keep it off for a whole time slice,
and 16 threads on 2 cores were 2.9x slower than one thread before the yield.
"""

import numpy as np

from .._jit import jit
from .atomic import fetch_add, load_ordered, store_ordered, yield_thread
from .stream import stream_segments

# Output rows faulted in at a time by one worker: 1 MiB of each float64 array
# and 1.5 MiB of the cells. Read by ``_batching.run_ordered`` at each call and
# passed to the kernels, never frozen into them: a test sets it to 5.
TOUCH_ROWS = 1 << 17
# Loads a wait spins for before it yields its CPU on every further load.
SPINS = 64
# The layout of ``chain``'s ``fresh``.
FRESH_FIRST = 0
FRESH_END = 1
CLAIMED = 2
BLOCK_ROWS = 3
DONE = 4


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
def pause(spins):
    """One round of a wait: after ``SPINS`` rounds, offer the CPU to another
    thread (the one being waited for, when there are more threads than CPUs).

    Returns the rounds so far.
    """
    if spins >= SPINS:
        yield_thread()
    return spins + 1


@jit(inline="always")
def start_of(chunk, starts):
    """Where ``chunk`` begins, once every chunk before it is counted (waits)."""
    start = load_ordered(starts, chunk)
    spins = 0
    while start < 0:
        spins = pause(spins)
        start = load_ordered(starts, chunk)
    return start


@jit(inline="always")
def chain(first_row, last_row, chunk_rays, used, fresh_end, block_rows):
    """A call's shared state: (n_chunks, counts, starts, reached, counter, fresh).

    ``counts`` and ``starts`` as in ``post`` (chunk 0 starts at ``used``);
    ``reached[c]``: the first of chunk c's rows not placed; ``counter``: the
    next chunk to take. ``fresh``: the output rows ``used..fresh_end-1``,
    not yet faulted in, as ``touched`` takes them, in one array: their first
    row (``FRESH_FIRST``), their end (``FRESH_END``), the next block to
    claim (``CLAIMED``), the rows a block (``BLOCK_ROWS``: ``block_rows``,
    the caller's ``TOUCH_ROWS``), and from ``DONE`` on per block 1 once
    faulted in.

    The block size is the call's, read from here by every function that
    takes blocks, not a global: Numba freezes a global into each kernel
    that reads it and caches each non-inlined kernel on its own, so kernels
    compiled while the global had another value (a test sets it to 5) once
    met cached ones compiled with this one, and waited for blocks that did
    not exist.
    """
    n_chunks = (last_row - first_row + chunk_rays - 1) // chunk_rays
    counts = np.full(n_chunks, -1, dtype=np.int64)
    starts = np.full(n_chunks + 1, -1, dtype=np.int64)
    starts[0] = used
    reached = np.empty(n_chunks, dtype=np.int64)
    counter = np.zeros(1, dtype=np.int64)
    n_blocks = (max(fresh_end - used, 0) + block_rows - 1) // block_rows
    fresh = np.zeros(DONE + n_blocks, dtype=np.int64)
    fresh[FRESH_FIRST] = used
    fresh[FRESH_END] = max(fresh_end, used)
    fresh[BLOCK_ROWS] = block_rows
    return n_chunks, counts, starts, reached, counter, fresh


@jit(inline="always")
def touch_rows(cells, t_enter, t_exit, first, last):
    """Write a zero into every 4 KiB page of rows ``first..last-1``: the OS gives
    a page its memory on its first write."""
    step = 512  # float64 values per 4 KiB page; cells rows are 12 bytes, so 512 rows span 1.5
    for row in range(first, last, step):
        cells[row, 0] = 0
        cells[min(row + step // 2, last - 1), 0] = 0
        t_enter[row] = 0.0
        t_exit[row] = 0.0


@jit(inline="always")
def _claim_block(fresh, cells, t_enter, t_exit):
    """Claim the next block of ``fresh`` and fault it in (nothing when none is left)."""
    block = fetch_add(fresh, CLAIMED, 1)
    if block < fresh.shape[0] - DONE:
        row = fresh[FRESH_FIRST] + block * fresh[BLOCK_ROWS]
        touch_rows(cells, t_enter, t_exit, row, min(fresh[FRESH_END], row + fresh[BLOCK_ROWS]))
        store_ordered(fresh, DONE + block, 1)


@jit
def touched(first, last, fresh, cells, t_enter, t_exit):
    """Return once output rows ``first..last-1`` are faulted in (those that are fresh).

    Claims and faults in blocks itself up to the last it needs, then waits
    for any that another worker claimed and is faulting in.
    """
    fresh_first = fresh[FRESH_FIRST]
    low = max(first, fresh_first)
    high = min(last, fresh[FRESH_END])
    if low >= high:
        return
    block_low = (low - fresh_first) // fresh[BLOCK_ROWS]
    block_high = (high - 1 - fresh_first) // fresh[BLOCK_ROWS]
    while load_ordered(fresh, CLAIMED) <= block_high:
        _claim_block(fresh, cells, t_enter, t_exit)
    spins = 0
    for block in range(block_low, block_high + 1):
        while load_ordered(fresh, DONE + block) == 0:
            spins = pause(spins)


@jit
def touch_ahead(chunk, lead, starts, fresh, cells, t_enter, t_exit):
    """Fault in fresh blocks up to where chunk ``chunk + lead`` will about end
    (the last chunk at most).

    Paced by the segments a chunk has had: by a start already published,
    that of chunk ``chunk - lead`` (nothing is faulted in while it is not).
    """
    known = chunk - lead
    if known < 1:
        return
    known_start = load_ordered(starts, known)
    if known_start < 0:
        return
    per_chunk = (known_start - starts[0]) / known
    ahead = min(chunk + lead + 1, starts.shape[0] - 1)
    target = min(fresh[FRESH_END], starts[0] + int(per_chunk * ahead))
    while True:
        block = load_ordered(fresh, CLAIMED)
        if (block >= fresh.shape[0] - DONE
                or fresh[FRESH_FIRST] + block * fresh[BLOCK_ROWS] >= target):
            return
        _claim_block(fresh, cells, t_enter, t_exit)


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
def place(chunk, source, first_row, last_row, chunk_rays, counts, starts, reached, fresh,
          loose_cells, loose_enter, loose_exit, cells, t_enter, t_exit, offsets):
    """Copy traced ``chunk`` (none when -1) from row ``source`` of the scratch to its
    place in the output, once its start is known; set ``reached[chunk]``.

    The chunk's rays wrote their ends as scratch positions into
    ``offsets``; they become output positions. A chunk that would end past
    the output is not placed (``reached[chunk]`` is then its first row).
    Fresh rows are faulted in first (``touched``).
    """
    if chunk < 0:
        return
    first, last = rows_of(chunk, first_row, chunk_rays, last_row)
    count = counts[chunk]
    target = start_of(chunk, starts)
    if target + count > cells.shape[0]:
        reached[chunk] = first
        return
    touched(target, target + count, fresh, cells, t_enter, t_exit)
    stream_segments(loose_cells, loose_enter, loose_exit, source, count, cells, t_enter, t_exit,
                    target)
    shift = target - source
    for row in range(first + 1, last + 1):
        offsets[row] += shift
    reached[chunk] = last


@jit(inline="always")
def advance(chunk, waiting, worker, side, room, first_row, last_row, chunk_rays, workers, counter,
            counts, starts, reached, fresh, loose_cells, loose_enter, loose_exit, cells, t_enter,
            t_exit, offsets):
    """A worker's step after tracing ``chunk`` (-1: none was left) into its buffer
    ``side``: place the chunk ``waiting`` in its other buffer, fault in fresh
    output ahead of the next chunk to take (``touch_ahead``, ``workers``
    chunks on), and take it.

    The faulting comes before the take: a block takes longer to fault in
    than a chunk to trace, and a worker holding a chunk not yet traced would
    keep every worker that places a later chunk waiting for its count; one
    holding none keeps no one waiting.

    Returns the next round's (waiting, side, chunk); the worker is done when
    both chunks are -1.
    """
    place(waiting, buffer_of(worker, 1 - side, room), first_row, last_row, chunk_rays, counts,
          starts, reached, fresh, loose_cells, loose_enter, loose_exit, cells, t_enter, t_exit,
          offsets)
    if chunk < 0:
        return chunk, 1 - side, -1
    touch_ahead(load_ordered(counter, 0), workers, starts, fresh, cells, t_enter, t_exit)
    return chunk, 1 - side, take(counter, counts.shape[0])


# The parallel loops whose items cost unequal amounts (rays walked from
# different shells, columns in and out of view) are not cut into one equal
# share per thread, Numba's schedule: the costly items lie together, where
# the scan looks, and would fall to a few of the shares. Instead each
# thread, a worker, takes blocks of items in turn from a counter
# (``ordered.take``), about ``TAKES_PER_WORKER`` blocks each.
TAKES_PER_WORKER = 64


@jit(inline="always")
def in_turn(n_items, workers, most):
    """Blocks of ``n_items`` for ``workers`` to take in turn: (items a block,
    blocks, the counter to ``ordered.take`` them from). A block holds
    ``most`` items, or fewer down to 16, so that each worker takes about
    ``TAKES_PER_WORKER`` of them."""
    step = max(min(most, n_items // (TAKES_PER_WORKER * workers)), 16)
    return step, (n_items + step - 1) // step, np.zeros(1, dtype=np.int64)
