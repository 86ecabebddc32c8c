"""Cartesian -> discrete log-spherical conversion (the paper's appendix, corrected).

A *zone* extends a cell index past the region so the traversal can follow a ray
outside it: ``-1`` is below the first edge (the egocentric gap for rho),
``n`` is above the last edge.  For theta the zones are cyclic and ``n_theta``
is the sector outside a partial range.

Tie rule (docs/geometry.md, "Ties"): a value on an interior edge belongs to
the cell above it (``edges[i] <= v < edges[i+1]``); a value equal to the last
edge belongs to the last cell, so the region is closed as in Eq. 1 and a ray
running along the +y axis (phi == pi/2 everywhere) is inside when
``phi_max == pi/2``.
"""

import math
from typing import NamedTuple

import numpy as np
from numba import prange

from .._jit import jit, jit_twins

EXPLICIT = 0
UNIFORM = 1
LOG = 2
PAPER = 3

TWO_PI = 2.0 * np.pi
HALF_PI = 0.5 * np.pi

# Rays per block in the batch kernels: each block allocates its scratch once.
BLOCK = 256
# Elevation cones timed at a time by the exact kernel's phi crossings
# (``crossings._branch_times``). On the CPU a grid's cone arrays carry
# ``CONE_BLOCK - 1`` zeros past the last cone (``GridArrays``), so that every
# block computes all of its lanes in one vector pass from any first cone.
CONE_BLOCK = 8


class GridArrays(NamedTuple):
    """A grid as the kernels take it: one argument, not twelve (``Grid.kernel_args()``).

    A plain named tuple of arrays and scalars, so Numba passes it by value on
    the CPU and numba-cuda can pass it to a device kernel the same way.
    """

    rho_edges: np.ndarray
    rho_sq: np.ndarray  # rho_edges ** 2
    rho_kind: int
    theta_edges: np.ndarray
    theta_sin: np.ndarray
    theta_cos: np.ndarray
    theta_kind: int
    theta_full: bool
    phi_edges: np.ndarray
    phi_tan2: np.ndarray  # tan(phi_edges) ** 2, then CONE_BLOCK - 1 zeros on the CPU
    phi_nappe: np.ndarray  # sign(phi_edges): the cone's half; padded the same
    phi_kind: int
    phi_sin: np.ndarray
    phi_cos: np.ndarray
    # The cones from phi_flat_from up to (not including) phi_flat_to lie within
    # ``crossings.FLAT_TAN2`` of the plane y = 0 (``crossings._flat_cone_times``).
    phi_flat_from: int = 0
    phi_flat_to: int = 0


@jit(inline="always")
def _last_at_or_below(value, edges):
    """Index of the last edge <= ``value`` (-1 if none): ``searchsorted(..., "right") - 1``,
    written out because numba-cuda has no ``np.searchsorted`` in device code."""
    low = 0
    high = edges.shape[0]
    while low < high:  # edges[:low] <= value < edges[high:]
        middle = (low + high) // 2
        if edges[middle] <= value:
            low = middle + 1
        else:
            high = middle
    return low - 1


@jit
def locate(value, edges, kind):
    """Zone of ``value`` among strictly increasing ``edges`` (see module doc)."""
    return locate_in(value, edges, kind, per_log_of(edges, kind))


@jit(inline="always")
def per_log_of(edges, kind):
    """``locate_in``'s ``per_log`` for ``edges`` of spacing ``kind``."""
    return log_cells(edges) if kind == LOG else 0.0


@jit(inline="always")
def log_cells(edges):
    """Cells per unit of ``log(value / edges[0])`` on log-spaced ``edges``."""
    n = edges.shape[0] - 1
    return n / math.log(edges[n] / edges[0])


@jit
def locate_in(value, edges, kind, per_log):
    """``locate`` with log spacing's constant ``per_log = log_cells(edges)`` given
    (unused for other kinds), so a loop over many values takes its logarithm once."""
    n = edges.shape[0] - 1
    lo = edges[0]
    hi = edges[n]
    if value < lo:
        return -1
    if value > hi:
        return n
    # Closed-form guess for the regular spacings, binary search otherwise; the
    # guess is then corrected against the stored edges, so rounding in log()
    # can never disagree with the edges themselves.
    if kind == UNIFORM:
        guess = int((value - lo) / (hi - lo) * n)
    elif kind == LOG:
        guess = int(math.log(value / lo) * per_log)
    elif kind == PAPER:
        offset = value - lo
        base = edges[1] - lo
        guess = int(math.log(offset) / math.log(base)) if offset > 1.0 else 0
    else:
        guess = _last_at_or_below(value, edges)
    if guess < 0:
        guess = 0
    if guess > n - 1:
        guess = n - 1
    # Each correction loop moves monotonically inside [0, n-1]: at most n steps.
    while guess > 0 and value < edges[guess]:
        guess -= 1
    while guess < n - 1 and value >= edges[guess + 1]:
        guess += 1
    return guess


# A squared length in this range is summed as it is; beyond it a component of
# ~1e154 overflows (a direction of 1e200 became (0, 0, 0)) or one of ~1e-154
# underflows and loses its digits, so the row is scaled by its largest
# component first.
SQUARES_LOW = 1e-300
SQUARES_HIGH = 1e300


@jit(inline="always")
def norm3(x, y, z):
    """Euclidean length of (x, y, z) without overflow or underflow: the one
    definition of a ray's length, shared by every path (``_validate.row_norms``,
    the sensor kernels), so that all of them normalise a ray identically."""
    squares = x * x + y * y + z * z
    if SQUARES_LOW <= squares <= SQUARES_HIGH:
        return math.sqrt(squares)
    scale = max(abs(x), max(abs(y), abs(z)))
    if scale == 0.0:
        return 0.0
    x /= scale
    y /= scale
    z /= scale
    return scale * math.sqrt(x * x + y * y + z * z)


@jit_twins(runtime=False)
def row_norms(vectors, out):
    """``out[r] = norm3(vectors[r])`` for an (m, 3) float64 array.

    Twins: a few rows (a single trace) take the serial build, which compiles
    in a fraction of the parallel one's time.
    """
    for row in prange(vectors.shape[0]):
        out[row] = norm3(vectors[row, 0], vectors[row, 1], vectors[row, 2])


@jit(parallel=True)
def unit_rays(origins, directions, units, reach2):
    """Check a batch of rays and scale its directions to unit length, on all threads.

    ``units[r] = directions[r] / norm3(directions[r])``, the same divisions
    as ``_validate.unit_directions``. Returns whether every row is valid:
    finite coordinates, an origin whose squared length is at most
    ``reach2`` (finite), a non-zero direction. When not, the caller checks
    again row by row to name the first fault (``x * 0.0`` is 0 only for a
    finite x).
    """
    n = origins.shape[0]
    bad = 0
    for block in prange((n + 4095) // 4096):
        flawed = False
        for row in range(block * 4096, min(n, (block + 1) * 4096)):
            x, y, z = origins[row, 0], origins[row, 1], origins[row, 2]
            a, b, c = directions[row, 0], directions[row, 1], directions[row, 2]
            length = norm3(a, b, c)
            flawed |= not (x * x + y * y + z * z <= reach2
                           and a * 0.0 + b * 0.0 + c * 0.0 == 0.0 and length > 0.0)
            units[row, 0] = a / length
            units[row, 1] = b / length
            units[row, 2] = c / length
        bad += flawed
    return bad == 0


@jit
def azimuth(x, z):
    """theta = atan2(x, z); ``+ 0.0`` turns -0.0 into +0.0 so the y axis has theta 0."""
    return math.atan2(x + 0.0, z + 0.0)


@jit
def elevation(x, y, z):
    """phi = atan2(y, sqrt(x^2 + z^2)), in [-pi/2, pi/2] (docs/geometry.md, not Eq. 7)."""
    return math.atan2(y + 0.0, math.sqrt(x * x + z * z))


@jit
def wrap_theta(theta, theta_min):
    """Wrap an azimuth into [theta_min, theta_min + 2*pi).

    An azimuth already in range is returned as it is: shifting it by
    ``theta_min`` and back would round a tiny angle (a point a hair off the
    plane x = 0) onto the edge at 0 when theta_min = -pi, and put it in the
    wrong zone. ``floor`` rather than ``%``: the float modulo is a slow libm
    call and this runs for every ray.
    """
    if theta_min <= theta < theta_min + TWO_PI:
        return theta
    offset = theta - theta_min
    offset -= TWO_PI * math.floor(offset / TWO_PI)
    if offset >= TWO_PI or offset < 0.0:
        offset = 0.0
    return theta_min + offset


@jit
def theta_zone(x, z, theta_edges, theta_kind):
    """Azimuthal zone of the point (x, ., z); ``n_theta`` outside a partial range."""
    wrapped = wrap_theta(azimuth(x, z), theta_edges[0])
    return locate(wrapped, theta_edges, theta_kind)


@jit
def phi_zone(x, y, z, phi_edges, phi_kind):
    """Elevation zone of the point (x, y, z)."""
    return locate(elevation(x, y, z), phi_edges, phi_kind)


# A point this far inside a sector (the sine of its angle to either edge, over
# its distance from the axis) is in that sector by atan2 and the edges too:
# their rounding is ~1e-16.
INSIDE_MARGIN = 1e-12


@jit
def rough_atan2(y, x):
    """atan2(y, x) to within 2e-6 rad, for a first guess only (x and y not both 0).

    An odd polynomial of degree 11 for atan on [0, 1] (a common minimax fit;
    its largest error on a million random points was 1.7e-6 rad, and
    ``tests/test_zones.py`` holds it under 2e-6) and the octants'
    symmetries: about a third of the libm call's time, with no call.
    """
    ay = abs(y)
    ax = abs(x)
    t = min(ax, ay) / max(ax, ay)
    s = t * t
    s2 = s * s
    # Estrin's scheme: the pairs are independent, so the chain from t to a is
    # five multiply-adds shorter than Horner's (each ray does four lookups).
    a = t * ((0.99997726 + s * -0.33262347)
             + s2 * ((0.19354346 + s * -0.11643287) + s2 * (0.05265332 + s * -0.01172120)))
    a = HALF_PI - a if ay > ax else a
    a = math.pi - a if x < 0.0 else a
    return -a if y < 0.0 else a


@jit
def _uniform_guess(angle, low, high, n):
    """The zone of ``angle`` among ``n`` uniform zones from ``low`` to ``high``, by
    arithmetic (may be off by one)."""
    return int((angle - low) * (n / (high - low)))


@jit
def _inside_by_margin(u, v, sin_low, cos_low, sin_high, cos_high):
    """Whether the direction (u, v) (u along the sines, v along the cosines) lies
    between the edges (sin, cos) low and high by more than ``INSIDE_MARGIN``:
    the sines of its angles to them, from the edges' own sines and cosines.
    Then its zone by atan2 is the one between them as well."""
    margin = INSIDE_MARGIN * (abs(u) + abs(v))
    return (u * cos_low - v * sin_low > margin
            and v * sin_high - u * cos_high > margin)


@jit(inline="always")
def _in_sector(x, z, zone, edges, sines, cosines):
    """Whether (x, ., z) is inside azimuthal ``zone`` by more than ``INSIDE_MARGIN``
    (``_inside_by_margin``): then it is in that zone by atan2 as well."""
    return (0 <= zone < edges.shape[0] - 1 and edges[zone + 1] - edges[zone] < 3.0
            and _inside_by_margin(x, z, sines[zone], cosines[zone], sines[zone + 1],
                                  cosines[zone + 1]))


@jit(inline="always")
def _in_band(y, flat, zone, edges, sines, cosines):
    """Whether a point at height ``y`` and distance ``flat`` (>= 0) from the y axis is
    inside elevation ``zone`` by more than ``INSIDE_MARGIN`` (see ``_in_sector``)."""
    return (0 <= zone < edges.shape[0] - 1
            and _inside_by_margin(y, flat, sines[zone], cosines[zone], sines[zone + 1],
                                  cosines[zone + 1]))


@jit(inline="always")
def theta_zone_rough(x, z, edges, sines, cosines, kind):
    """``theta_zone`` of (x, z), from a guess where it can: on uniform edges the zone
    of ``rough_atan2``'s angle, kept if the point is inside it by more than
    ``INSIDE_MARGIN`` (``_in_sector``), so that it is its zone by atan2 too.
    A third of the lookup's time. A point within the guess's error of an
    edge, outside a partial range, or on other edges is looked up."""
    n = edges.shape[0] - 1
    if kind == UNIFORM and (x != 0.0 or z != 0.0):
        theta = wrap_theta(rough_atan2(x, z), edges[0])
        guess = _uniform_guess(theta, edges[0], edges[n], n)
        if _in_sector(x, z, guess, edges, sines, cosines):
            return guess
    return theta_zone(x, z, edges, kind)


@jit(inline="always")
def phi_zone_rough(x, y, z, edges, sines, cosines, kind):
    """``phi_zone`` of (x, y, z), from a guess where it can (see ``theta_zone_rough``)."""
    n = edges.shape[0] - 1
    flat = math.sqrt(x * x + z * z)
    if kind == UNIFORM and (y != 0.0 or flat != 0.0):
        guess = _uniform_guess(rough_atan2(y, flat), edges[0], edges[n], n)
        if _in_band(y, flat, guess, edges, sines, cosines):
            return guess
    return phi_zone(x, y, z, edges, kind)


@jit(inline="always")
def theta_zone_near(x, z, guess, grid):
    """``theta_zone`` of (x, z), trying zone ``guess`` (a neighbour's) first.

    A zone the point is inside by more than ``INSIDE_MARGIN`` (``_in_sector``)
    is its zone by atan2 too; any other point gets ``theta_zone_rough``.
    """
    if _in_sector(x, z, guess, grid.theta_edges, grid.theta_sin, grid.theta_cos):
        return guess
    return theta_zone_rough(x, z, grid.theta_edges, grid.theta_sin, grid.theta_cos,
                            grid.theta_kind)


@jit(inline="always")
def phi_zone_near(x, y, z, guess, grid):
    """``phi_zone`` of (x, y, z), trying zone ``guess`` first (see ``theta_zone_near``)."""
    if _in_band(y, math.sqrt(x * x + z * z), guess, grid.phi_edges, grid.phi_sin, grid.phi_cos):
        return guess
    return phi_zone_rough(x, y, z, grid.phi_edges, grid.phi_sin, grid.phi_cos, grid.phi_kind)


@jit
def rho_zone(x, y, z, rho_edges, rho_kind):
    """Radial zone of the point (x, y, z); -1 in the egocentric gap, n_rho beyond rho_max."""
    return locate(math.sqrt(x * x + y * y + z * z), rho_edges, rho_kind)


@jit
def cell_of_point(x, y, z, rho_edges, rho_kind, theta_edges, theta_kind, phi_edges, phi_kind):
    """Cartesian2DiscreteLogSpherical (the appendix, corrected): (i, j, k), or
    (-1, -1, -1) outside the region.

    Takes the grid's arrays, not its ``GridArrays``: callers that look up many
    points per ray unpack the bundle once. Reading an array out of the bundle
    inside a loop costs a reference count each time (a tenth of bisect's time).
    """
    return _cell_of_zones(rho_zone(x, y, z, rho_edges, rho_kind),
                          theta_zone(x, z, theta_edges, theta_kind),
                          phi_zone(x, y, z, phi_edges, phi_kind),
                          rho_edges, theta_edges, phi_edges)


@jit(inline="always")
def _cell_of_zones(i, j, k, rho_edges, theta_edges, phi_edges):
    """The cell of zones (i, j, k), or (-1, -1, -1) when they lie outside the region."""
    inside = (0 <= i < rho_edges.shape[0] - 1 and j < theta_edges.shape[0] - 1
              and 0 <= k < phi_edges.shape[0] - 1)
    if not inside:
        return -1, -1, -1
    return i, j, k


@jit(runtime=True)
def cells_of_points(points, grid):
    """(M, 3) float64 points -> (M, 3) int32 cells, rows of -1 outside the region.

    ``cell_of_point``'s cells, with the angular zones from a rough guess
    confirmed against the edges (``theta_zone_rough``, ``phi_zone_rough``).
    """
    rho_edges, rho_kind = grid.rho_edges, grid.rho_kind
    theta_edges, theta_sin, theta_cos = grid.theta_edges, grid.theta_sin, grid.theta_cos
    phi_edges, phi_sin, phi_cos = grid.phi_edges, grid.phi_sin, grid.phi_cos
    theta_kind, phi_kind = grid.theta_kind, grid.phi_kind
    out = np.empty((points.shape[0], 3), dtype=np.int32)
    for row in range(points.shape[0]):
        x, y, z = points[row, 0], points[row, 1], points[row, 2]
        out[row, 0], out[row, 1], out[row, 2] = _cell_of_zones(
            rho_zone(x, y, z, rho_edges, rho_kind),
            theta_zone_rough(x, z, theta_edges, theta_sin, theta_cos, theta_kind),
            phi_zone_rough(x, y, z, phi_edges, phi_sin, phi_cos, phi_kind),
            rho_edges, theta_edges, phi_edges,
        )
    return out
