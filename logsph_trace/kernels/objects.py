"""Objects in the map (``@jit`` only): connected components of occupied cells."""

import numpy as np

from .._jit import jit


@jit(runtime=True)
def components(occupied, wrap_theta, cells, labels):
    """Label the 26-connected components of ``occupied`` (n_rho, n_theta, n_phi) bool.

    Cells are neighbours when each index differs by at most 1; with
    ``wrap_theta`` the first and last theta columns are neighbours too (a
    full circle has no seam). ``cells``: the flat indices of the occupied
    cells, in C order (``numpy.flatnonzero(occupied)``): a map holds a few
    thousand among millions, and looking only at them took the Motorcycle
    frame's 64 x 360 x 180 map from 31 ms to under 1 (``python -m
    bench.replay``). ``labels`` (same shape, int32, zero) gets 1, 2, ... per
    component, numbered in order of each component's first cell in C order;
    returns how many there are. A flood fill with an explicit stack: every
    occupied cell is pushed once.
    """
    n_rho, n_theta, n_phi = occupied.shape
    stack = np.empty(cells.shape[0], dtype=np.int64)
    count = 0
    for start in cells:
        i0 = start // (n_theta * n_phi)
        j0 = (start // n_phi) % n_theta
        k0 = start % n_phi
        if not occupied[i0, j0, k0] or labels[i0, j0, k0] != 0:
            continue
        count += 1
        labels[i0, j0, k0] = count
        stack[0] = start
        top = 1
        while top > 0:
            top -= 1
            cell = stack[top]
            i = cell // (n_theta * n_phi)
            j = (cell // n_phi) % n_theta
            k = cell % n_phi
            for di in range(-1, 2):
                ni = i + di
                if ni < 0 or ni >= n_rho:
                    continue
                for dj in range(-1, 2):
                    nj = j + dj
                    if nj < 0 or nj >= n_theta:
                        if not wrap_theta:
                            continue
                        nj = (nj + n_theta) % n_theta
                    for dk in range(-1, 2):
                        nk = k + dk
                        if nk < 0 or nk >= n_phi:
                            continue
                        if occupied[ni, nj, nk] and labels[ni, nj, nk] == 0:
                            labels[ni, nj, nk] = count
                            stack[top] = (ni * n_theta + nj) * n_phi + nk
                            top += 1
    return count


@jit
def label_sums(labels, ids, radii, directions, sums):
    """Per shell, count and sum the centres of the cells whose label is in ``ids``.

    ``labels``: flat, shell-major (``grid.shape``); ``ids`` sorted; a cell's
    centre is ``radii[i] * directions[column]`` (mid-radius times the
    column's centre direction). ``sums`` (n_rho, len(ids), 4), zero, gets
    (count, x, y, z) per shell and label: one pass over the labels, which
    are mostly 0, instead of numpy's ``isin`` over every cell (4.7 ms a gaze
    on a 64 x 360 x 180 map, ``python -m bench.replay``'s profile). On one
    thread: in parallel it took 0.8 s more to compile in the main job
    (``python -m bench.first_call``).
    """
    plane = directions.shape[0]
    for i in range(radii.shape[0]):
        base = i * plane
        for column in range(plane):
            label = labels[base + column]
            if label == 0:
                continue
            slot = np.searchsorted(ids, label)
            if slot < ids.shape[0] and ids[slot] == label:
                sums[i, slot, 0] += 1.0
                sums[i, slot, 1] += radii[i] * directions[column, 0]
                sums[i, slot, 2] += radii[i] * directions[column, 1]
                sums[i, slot, 3] += radii[i] * directions[column, 2]


@jit
def hit_runs(hits, labels, n_rho, n_columns, cells, votes, counts):
    """Runs of one (cell, label) among consecutive rays that hit a cell; returns how many.

    ``hits``: each ray's cell, -1 for none; column-major (``column * n_rho
    + i``, as ``apply_scan`` takes them) when ``n_rho`` > 0, C order when
    0. ``cells`` (C order), ``votes`` and ``counts`` (each as long as
    ``hits``) get each run's cell, label and length. Neighbouring pixels
    mostly hit one cell with one label: a 640 x 480 frame's 307,200 votes
    become a few tens of thousands of runs before they are sorted.
    """
    runs = 0
    for ray in range(hits.shape[0]):
        hit = hits[ray]
        if hit < 0:
            continue
        if n_rho > 0:
            hit = (hit % n_rho) * n_columns + hit // n_rho
        label = labels[ray]
        if runs > 0 and cells[runs - 1] == hit and votes[runs - 1] == label:
            counts[runs - 1] += 1
        else:
            cells[runs] = hit
            votes[runs] = label
            counts[runs] = 1
            runs += 1
    return runs

