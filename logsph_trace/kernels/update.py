"""The map update of a scan: each flagged cell once, hit over free, clamped (OctoMap's rule).

``apply_scan`` reads the flags the walks stored (``walk.FREE``,
``walk.HIT``) for the columns in view and updates the log-odds of each
flagged cell once, so the map does not depend on the number of threads.
"""

import numpy as np
from numba import prange

from .._jit import jit
from .atomic import store_relaxed
from .locate import BLOCK
from .ordered import in_turn, take
from .walk import FREE, HIT


@jit(inline="always")
def _update(log_odds, cell, hit, free, log_hit, log_miss, log_min, log_max):
    """OctoMap's update of one cell: a hit wins over a miss; clamped.

    Summed in float64 and rounded once to the map's float32, whatever the
    caller's promotion rules (numpy 2 would add a Python float to a float32
    scalar in float32).
    """
    if hit:
        log_odds[cell] = min(np.float64(log_odds[cell]) + log_hit, log_max)
    elif free:
        log_odds[cell] = max(np.float64(log_odds[cell]) + log_miss, log_min)


@jit(inline="always")
def _apply_word(log_odds, words, word, n_rho, n_columns, log_hit, log_miss, log_min, log_max):
    """``apply_scan`` for the eight cells of ``word``: update those flagged,
    then clear the word."""
    any_bits = words[word]
    if any_bits == 0:
        return
    n_cells = n_columns * n_rho
    for index in range(word * 8, min(word * 8 + 8, n_cells)):
        # Byte ``index - 8 word`` of the word (little-endian, as every
        # platform Numba runs on): the cell's flag.
        bits = np.uint8((any_bits >> np.uint64(8 * (index - word * 8))) & np.uint64(0xFF))
        if bits != 0:
            i = index % n_rho
            _update(log_odds, i * n_columns + index // n_rho, (bits & HIT) != 0,
                    (bits & FREE) != 0, log_hit, log_miss, log_min, log_max)
    # Cleared only here, for words that held flags: clearing every word
    # read made the pass branch on every word, most of them zero (apply
    # 1.5 -> 2.6 ms on one thread, table scan 10 cm off).
    words[word] = 0


@jit(inline="always")
def _first_word_of(column, n_rho, view):
    """The first word ``column``'s walk in ``apply_scan`` owns: a word that
    begins in an earlier column belongs to the first column in view it
    touches."""
    word = column * n_rho // 8
    for earlier in range(word * 8 // n_rho, column):
        if view[earlier]:
            return word + 1
    return word


@jit(parallel=True)
def apply_scan(log_odds, free, words, hits, n_rho, view, log_hit, log_miss, log_min, log_max,
               workers):
    """OctoMap's update, once per cell per scan: a hit wins over a miss; clamped.

    ``free`` is indexed column-major, ``(j * n_phi + k) * n_rho + i``, so that
    a ray's run of shells in one column is one cache line rather than a page
    apart each (the map is ``(i * n_theta + j) * n_phi + k``). The walk only
    stores to it: a load-test-store per cell to list the cells it met cost
    more than this pass. ``words`` is ``free`` seen as uint64 (padded to a
    multiple of 8 bytes): most of a scan's cells are untouched, and eight at
    a time are skipped with one test.

    Only the columns in ``view`` (a byte per column) are read: no ray of the
    scan meets the others, so their flags are zero. A word that spans two
    columns is read once, by the first of them in view. The ``workers`` take
    blocks of columns in turn (``in_turn``): the columns in view lie
    together.

    The hits go in first, on all threads: ``HIT`` replaces the byte, since a
    hit wins over a miss, and rays that end in one cell store the same value
    there (``atomic.store_relaxed``). The flags are left zero, ready for the
    next scan: only words that were not are written.
    """
    n_rays = hits.shape[0]
    n_cells = log_odds.shape[0]
    for block in prange((n_rays + BLOCK - 1) // BLOCK):
        for ray in range(block * BLOCK, min(n_rays, (block + 1) * BLOCK)):
            if 0 <= hits[ray] < n_cells:  # -1: no hit (the bound: no store outside the map)
                store_relaxed(free, hits[ray], HIT)
    n_columns = log_odds.shape[0] // n_rho
    step, n_blocks, counter = in_turn(n_columns, workers, BLOCK)
    for worker in prange(workers):
        block = take(counter, n_blocks)
        while block >= 0:
            for column in range(block * step, min(n_columns, (block + 1) * step)):
                if view[column]:
                    for word in range(_first_word_of(column, n_rho, view),
                                      ((column + 1) * n_rho - 1) // 8 + 1):
                        _apply_word(log_odds, words, word, n_rho, n_columns, log_hit, log_miss,
                                    log_min, log_max)
            block = take(counter, n_blocks)
