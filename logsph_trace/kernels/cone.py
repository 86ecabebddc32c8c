"""Aggregate the traces of a cone's rays into weighted cells (``@jit`` only).

A cone's rays stay close to each other, so at each radius the cells they
cross fill a small box of (theta, phi) index space; the boxes are addressed
densely (no hashing, no sort of all segments). The azimuth is shifted by
``j_shift`` first, so a cone straddling the theta seam still makes a compact
box.
"""

import numpy as np
from numba import prange

from .._jit import jit


@jit
def _shifted(j, j_shift, n_theta):
    """(j + j_shift) mod n_theta for 0 <= j, j_shift < n_theta, without a division."""
    shifted = np.int64(j) + j_shift
    return shifted - n_theta if shifted >= n_theta else shifted


@jit(parallel=True)
def aggregate_boxes(offsets, starts, firsts, cells, t_enter, weights, per_segment, n_rho, n_theta,
               j_shift):
    """Per cell: summed weight over the rays crossing it (each ray once), first t.

    Parameters: CSR ``offsets`` (m + 1,) into ``cells`` (K, 3) and ``t_enter``
    (K,): ray ``r``'s segments are ``offsets[r]:offsets[r + 1]``; ``starts``
    (c + 1,): chunks of rays, one ``prange`` iteration each; ``firsts`` (c,):
    where each chunk's first ray begins. Nothing else is read, so the arrays
    may hold gaps between chunks: the regions a parallel trace fills, where
    ``offsets[starts[c]]`` is the end of the previous region, not
    ``firsts[c]``. ``weights``: what a segment adds to its
    cell -- per segment (K,) if ``per_segment`` (a weighted probability),
    else per ray (m,) (the ray's weight); only a ray's first segment in a
    cell counts. Returns (cells (u, 3) int32, weights (u,) float64
    unnormalised, t_first (u,) float64), unsorted.

    Each radial shell gets its own dense (theta, phi) box: at one radius the
    cone's footprint is a compact patch, so the boxes together stay small.
    Each chunk fills its own copy of the boxes (no shared writes); the copies
    are then summed, box by box.
    """
    n_chunks = starts.shape[0] - 1
    big = np.iinfo(np.int64).max
    low_j = np.full((n_chunks, n_rho), big, dtype=np.int64)
    high_j = np.full((n_chunks, n_rho), -1, dtype=np.int64)
    low_k = np.full((n_chunks, n_rho), big, dtype=np.int64)
    high_k = np.full((n_chunks, n_rho), -1, dtype=np.int64)
    for chunk in prange(n_chunks):
        for seg in range(firsts[chunk], offsets[starts[chunk + 1]]):
            i = cells[seg, 0]
            j = _shifted(cells[seg, 1], j_shift, n_theta)
            k = np.int64(cells[seg, 2])
            low_j[chunk, i] = min(low_j[chunk, i], j)
            high_j[chunk, i] = max(high_j[chunk, i], j)
            low_k[chunk, i] = min(low_k[chunk, i], k)
            high_k[chunk, i] = max(high_k[chunk, i], k)
    for chunk in range(1, n_chunks):
        for i in range(n_rho):
            low_j[0, i] = min(low_j[0, i], low_j[chunk, i])
            high_j[0, i] = max(high_j[0, i], high_j[chunk, i])
            low_k[0, i] = min(low_k[0, i], low_k[chunk, i])
            high_k[0, i] = max(high_k[0, i], high_k[chunk, i])
    base = np.zeros(n_rho + 1, dtype=np.int64)
    for i in range(n_rho):
        area = ((high_j[0, i] - low_j[0, i] + 1) * (high_k[0, i] - low_k[0, i] + 1)
                if high_j[0, i] >= 0 else 0)
        base[i + 1] = base[i] + area
    size = base[n_rho]
    weight = np.zeros((n_chunks, size))
    first = np.full((n_chunks, size), np.inf)
    last_ray = np.full((n_chunks, size), -1, dtype=np.int64)
    for chunk in prange(n_chunks):
        for ray in range(starts[chunk], starts[chunk + 1]):
            begin = firsts[chunk] if ray == starts[chunk] else offsets[ray]
            for seg in range(begin, offsets[ray + 1]):
                i = cells[seg, 0]
                j = _shifted(cells[seg, 1], j_shift, n_theta)
                span_k = high_k[0, i] - low_k[0, i] + 1
                box = base[i] + (j - low_j[0, i]) * span_k + (cells[seg, 2] - low_k[0, i])
                # Branch-free: a ray re-entering a cell counts once; first reach is a min.
                previous = last_ray[chunk, box]
                value = weights[seg] if per_segment else weights[ray]
                weight[chunk, box] += value * (previous != ray)
                last_ray[chunk, box] = ray
                first[chunk, box] = min(first[chunk, box], t_enter[seg])
    n_unique = 0
    for box in range(size):
        for chunk in range(1, n_chunks):
            weight[0, box] += weight[chunk, box]
            first[0, box] = min(first[0, box], first[chunk, box])
            last_ray[0, box] = max(last_ray[0, box], last_ray[chunk, box])
        n_unique += last_ray[0, box] != -1
    out_cells = np.empty((n_unique, 3), dtype=np.int32)
    out_weight = np.empty(n_unique)
    out_first = np.empty(n_unique)
    found = 0
    for i in range(n_rho):
        span_k = high_k[0, i] - low_k[0, i] + 1
        for box in range(base[i], base[i + 1]):
            if last_ray[0, box] == -1:
                continue
            offset = box - base[i]
            out_cells[found, 0] = i
            out_cells[found, 1] = _shifted(offset // span_k + low_j[0, i], n_theta - j_shift,
                                           n_theta)
            out_cells[found, 2] = offset % span_k + low_k[0, i]
            out_weight[found] = weight[0, box]
            out_first[found] = first[0, box]
            found += 1
    return out_cells, out_weight, out_first
