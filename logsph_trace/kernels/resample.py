"""Resampling a map into a moved frame (``OccupancyGrid.move``), column by column.

A new cell's value comes from the old cells its column's centre ray crosses
within its shell. From the old centre that ray is radial, so a rotation
maps whole columns (``gather_columns``); from elsewhere it is traced exactly
through the old grid, and each new shell takes the value and label of the
old cell that covers the most of the ray within it (``copy_along_columns``,
then ``place_columns``). A turn by whole azimuth cells is ``roll_columns``.
"""

from numba import prange

from .._jit import jit
from .locate import phi_zone, theta_zone


@jit(parallel=True)
def aim_columns(directions, rotation, grid, aimed, source):
    """Turn each column's centre direction by ``rotation`` into ``aimed``, and
    give ``source`` the flat old column it points into, or -1 outside the
    grid's angles."""
    n_theta = grid.theta_edges.shape[0] - 1
    n_phi = grid.phi_edges.shape[0] - 1
    for column in prange(directions.shape[0]):
        u = directions[column, 0]
        v = directions[column, 1]
        w = directions[column, 2]
        x = rotation[0, 0] * u + rotation[0, 1] * v + rotation[0, 2] * w
        y = rotation[1, 0] * u + rotation[1, 1] * v + rotation[1, 2] * w
        z = rotation[2, 0] * u + rotation[2, 1] * v + rotation[2, 2] * w
        aimed[column, 0] = x
        aimed[column, 1] = y
        aimed[column, 2] = z
        j = theta_zone(x, z, grid.theta_edges, grid.theta_kind)
        k = phi_zone(x, y, z, grid.phi_edges, grid.phi_kind)
        if 0 <= j < n_theta and 0 <= k < n_phi:
            source[column] = j * n_phi + k
        else:
            source[column] = -1


@jit(parallel=True)
def seen_columns(bits, n_rho, seen):
    """``seen[c] = 1`` where some shell of column ``c`` is known (log-odds not 0),
    else 0. ``bits``: the flat, shell-major float32 log-odds viewed as
    uint32 (OR-ing the words vectorises; -0.0 counts as 0); ``seen``: uint32."""
    plane = seen.shape[0]
    block = 4096
    for first in prange((plane + block - 1) // block):
        low = first * block
        high = min(low + block, plane)
        for column in range(low, high):
            seen[column] = 0
        for i in range(n_rho):
            base = i * plane
            for column in range(low, high):
                seen[column] |= bits[base + column]
        for column in range(low, high):
            seen[column] = 1 if seen[column] & 0x7FFFFFFF else 0


@jit(inline="always")
def _window_count(mask, row, low, high, wrap):
    """How many entries of ``mask[low..high, row]`` are set (indices wrapped, or
    those outside dropped)."""
    n = mask.shape[0]
    count = 0
    for index in range(low, high + 1):
        if wrap:
            count += mask[index % n, row]
        elif 0 <= index < n:
            count += mask[index, row]
    return count


@jit
def dilate(mask, reach, wrap, out):
    """``out[j, r] = 1`` where ``mask`` is set within ``reach[r]`` entries of ``j``
    along axis 0 (all of column ``r`` when ``reach[r] < 0``), wrapping around
    when ``wrap``: a count over a window slid along the axis."""
    n = mask.shape[0]
    for row in range(mask.shape[1]):
        spread = reach[row]
        if spread < 0 or 2 * spread + 1 >= n:
            spread = n  # the whole axis
        count = _window_count(mask, row, -spread, spread, wrap)
        for j in range(n):
            out[j, row] = 1 if count > 0 else 0
            if spread < n:
                leaving = j - spread
                entering = j + spread + 1
                if wrap:
                    count += mask[entering % n, row] - mask[leaving % n, row]
                else:
                    if leaving >= 0:
                        count -= mask[leaving, row]
                    if entering < n:
                        count += mask[entering, row]


@jit(parallel=True)
def gather_columns(log_odds, labels, source, n_rho, out_log_odds, out_labels):
    """New column ``c`` is old column ``source[c]`` shell by shell, or unknown
    where ``source[c]`` is -1 (a rotation: the shells are the same)."""
    plane = source.shape[0]
    for i in prange(n_rho):
        base = i * plane
        for column in range(plane):
            old = source[column]
            if old >= 0:
                out_log_odds[base + column] = log_odds[base + old]
                out_labels[base + column] = labels[base + old]
            else:
                out_log_odds[base + column] = 0
                out_labels[base + column] = 0


@jit(inline="always")
def _longest_in_shell(first, end, low, high, t_enter, t_exit):
    """The segment of first..end-1 that covers the most of ``[low, high)``, or -1
    where none covers any of it (the first of equals)."""
    longest = 0.0
    chosen = -1
    segment = first
    while segment < end and t_enter[segment] < high:
        overlap = min(t_exit[segment], high) - max(t_enter[segment], low)
        if overlap > longest:
            longest = overlap
            chosen = segment
        segment += 1
    return chosen


@jit(parallel=True)
def copy_along_columns(first_ray, offsets, cells, t_enter, t_exit, rho_edges, log_odds, labels,
                       n_phi, values, value_labels):
    """Ray ``r`` (``first_ray + r`` in ``values``' rows) is the centre ray of a new
    column, its segments ``offsets[r]:offsets[r+1]`` at distances from the
    new centre: row ``first_ray + r`` of ``values`` and ``value_labels``
    gets, per shell ``i``, the log-odds and label of the old cell that
    covers the most of the ray between ``rho_edges[i]`` and
    ``rho_edges[i+1]`` (``_longest_in_shell``), or 0 where the ray is never
    in the old region."""
    n_rho = rho_edges.shape[0] - 1
    plane = log_odds.shape[0] // n_rho
    for ray in prange(offsets.shape[0] - 1):
        row = first_ray + ray
        first = offsets[ray]
        end = offsets[ray + 1]
        for i in range(n_rho):
            low = rho_edges[i]
            while first < end and t_exit[first] <= low:
                first += 1
            chosen = _longest_in_shell(first, end, low, rho_edges[i + 1], t_enter, t_exit)
            if chosen >= 0:
                cell = cells[chosen, 0] * plane + cells[chosen, 1] * n_phi + cells[chosen, 2]
                values[row, i] = log_odds[cell]
                value_labels[row, i] = labels[cell]
            else:
                values[row, i] = 0
                value_labels[row, i] = 0


@jit(parallel=True)
def place_columns(slot, values, value_labels, out_log_odds, out_labels):
    """Write every cell once: column ``c`` takes row ``slot[c]`` of ``values`` and
    ``value_labels`` (one entry per shell), or is unknown where ``slot[c]`` is -1."""
    plane = slot.shape[0]
    for i in prange(values.shape[1]):
        base = i * plane
        for column in range(plane):
            row = slot[column]
            if row >= 0:
                out_log_odds[base + column] = values[row, i]
                out_labels[base + column] = value_labels[row, i]
            else:
                out_log_odds[base + column] = 0
                out_labels[base + column] = 0


@jit(parallel=True)
def roll_columns(log_odds, labels, shift, n_rho, out_log_odds, out_labels):
    """Shell by shell, new flat column ``c`` is old column ``c + shift`` (modulo the
    shell): a turn by whole azimuth cells, ``shift`` = cells * n_phi."""
    plane = log_odds.shape[0] // n_rho
    head = plane - shift
    for i in prange(n_rho):
        base = i * plane
        for column in range(head):
            out_log_odds[base + column] = log_odds[base + column + shift]
            out_labels[base + column] = labels[base + column + shift]
        for column in range(shift):
            out_log_odds[base + head + column] = log_odds[base + column]
            out_labels[base + head + column] = labels[base + column]
