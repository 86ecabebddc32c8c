"""Aggregate the traces of a cone's rays into weighted cells (``@jit`` only).

A cone's rays stay close to each other, so at each radius the cells they
cross fill a small box of (theta, phi) index space; the boxes are addressed
densely (no hashing, no sort of all segments). The azimuth is shifted by ``j_shift`` first, so a cone straddling
the theta seam still makes a compact box.
"""

import numpy as np

from .._jit import jit


@jit
def _shifted(j, j_shift, n_theta):
    """(j + j_shift) mod n_theta for 0 <= j, j_shift < n_theta, without a division."""
    shifted = np.int64(j) + j_shift
    return shifted - n_theta if shifted >= n_theta else shifted


@jit
def aggregate(offsets, cells, t_enter, weights, per_segment, n_rho, n_theta, j_shift):
    """Per cell: summed weight over the rays crossing it (each ray once), first t.

    Parameters: CSR ``offsets`` (m + 1,) and ``cells`` (K, 3), ``t_enter`` (K,)
    of the cone's rays; ``weights``: what a segment adds to its cell -- per
    segment (K,) if ``per_segment`` (a weighted probability), else per ray
    (m,) (the ray's weight); only a ray's first segment in a cell counts. Returns (cells (u, 3) int32, weights (u,)
    float64 unnormalised, t_first (u,) float64), unsorted.

    Each radial shell gets its own dense (theta, phi) box: at one radius the
    cone's footprint is a compact patch, so the boxes together stay small.
    """
    n_segments = cells.shape[0]
    big = np.iinfo(np.int64).max
    low_j = np.full(n_rho, big, dtype=np.int64)
    high_j = np.full(n_rho, -1, dtype=np.int64)
    low_k = np.full(n_rho, big, dtype=np.int64)
    high_k = np.full(n_rho, -1, dtype=np.int64)
    for seg in range(n_segments):
        i = cells[seg, 0]
        j = _shifted(cells[seg, 1], j_shift, n_theta)
        k = np.int64(cells[seg, 2])
        low_j[i] = min(low_j[i], j)
        high_j[i] = max(high_j[i], j)
        low_k[i] = min(low_k[i], k)
        high_k[i] = max(high_k[i], k)
    base = np.zeros(n_rho + 1, dtype=np.int64)
    for i in range(n_rho):
        area = (high_j[i] - low_j[i] + 1) * (high_k[i] - low_k[i] + 1) if high_j[i] >= 0 else 0
        base[i + 1] = base[i] + area
    size = base[n_rho]
    weight = np.zeros(size)
    first = np.full(size, np.inf)
    last_ray = np.full(size, -1, dtype=np.int64)
    n_unique = 0
    for ray in range(offsets.shape[0] - 1):
        for seg in range(offsets[ray], offsets[ray + 1]):
            i = cells[seg, 0]
            j = _shifted(cells[seg, 1], j_shift, n_theta)
            span_k = high_k[i] - low_k[i] + 1
            box = base[i] + (j - low_j[i]) * span_k + (cells[seg, 2] - low_k[i])
            # Branch-free: a ray re-entering a cell counts once; first reach is a min.
            previous = last_ray[box]
            n_unique += previous == -1
            value = weights[seg] if per_segment else weights[ray]
            weight[box] += value * (previous != ray)
            last_ray[box] = ray
            first[box] = min(first[box], t_enter[seg])
    out_cells = np.empty((n_unique, 3), dtype=np.int32)
    out_weight = np.empty(n_unique)
    out_first = np.empty(n_unique)
    found = 0
    for i in range(n_rho):
        span_k = high_k[i] - low_k[i] + 1
        for box in range(base[i], base[i + 1]):
            if last_ray[box] == -1:
                continue
            offset = box - base[i]
            out_cells[found, 0] = i
            out_cells[found, 1] = _shifted(offset // span_k + low_j[i], n_theta - j_shift, n_theta)
            out_cells[found, 2] = offset % span_k + low_k[i]
            out_weight[found] = weight[box]
            out_first[found] = first[box]
            found += 1
    return out_cells, out_weight, out_first
