"""A zone found from a guess (the ray before's) is the zone the lookup finds,
whatever the guess, on and beside every edge."""

import numba
import numpy as np
import pytest

import logsph_trace as lt
from logsph_trace.kernels.locate import (
    cell_of_point,
    phi_zone,
    phi_zone_near,
    rough_atan2,
    theta_zone,
    theta_zone_near,
)


@numba.njit
def _both(points, guesses, grid):
    """Per point and guess: (theta by lookup, theta from the guess, phi ..., phi ...)."""
    out = np.empty((points.shape[0], guesses.shape[0], 4), dtype=np.int64)
    for row in range(points.shape[0]):
        x, y, z = points[row, 0], points[row, 1], points[row, 2]
        for g in range(guesses.shape[0]):
            out[row, g, 0] = theta_zone(x, z, grid.theta_edges, grid.theta_kind)
            out[row, g, 1] = theta_zone_near(x, z, guesses[g], grid)
            out[row, g, 2] = phi_zone(x, y, z, grid.phi_edges, grid.phi_kind)
            out[row, g, 3] = phi_zone_near(x, y, z, guesses[g], grid)
    return out


def _points(rng, grid):
    """Random points, points on every edge (theta and phi) and 1e-16 ... 1e-6 rad beside it,
    points on the seam and on the y axis."""
    theta = np.r_[rng.uniform(-np.pi, np.pi, 500), np.repeat(grid.theta_edges, 4)]
    phi = np.r_[rng.uniform(-np.pi / 2, np.pi / 2, 500), np.repeat(grid.phi_edges, 4)]
    n = max(theta.size, phi.size)
    theta = np.resize(theta, n)
    phi = rng.permutation(np.resize(phi, n))
    offsets = rng.choice([0.0, 1e-16, -1e-16, 1e-14, -1e-13, 1e-12, -1e-12, 1e-9, -1e-6], (2, n))
    theta, phi = theta + offsets[0], np.clip(phi + offsets[1], -np.pi / 2, np.pi / 2)
    radius = rng.uniform(0.1, 10.0, n)
    points = np.stack([radius * np.cos(phi) * np.sin(theta), radius * np.sin(phi),
                       radius * np.cos(phi) * np.cos(theta)], axis=1)
    seam = [[0.0, 0.3, -1.0], [-0.0, 0.3, -1.0], [1e-17, 0.0, -2.0], [-1e-17, -0.5, -2.0],
            [0.0, 1.0, 0.0], [0.0, -2.0, 0.0], [1e-300, 1.0, 0.0]]
    return np.concatenate([points, seam])


@pytest.mark.parametrize("grid", [
    lt.Grid(0.3, 8.0, 64, 360, 180),
    lt.Grid(0.5, 6.0, 20, 24, 12, theta_range=(-1.0, 2.5), phi_range=(-0.6, 1.1),
            spacing="uniform"),
    lt.Grid(1.0, 30.0, 12, 36, 18, spacing="paper"),
    lt.Grid.from_edges([0.5, 1.0, 3.0], [0.0, 0.4, 1.1, 4.0], [-0.3, 0.2, 1.5]),
    lt.Grid(0.3, 8.0, 8, 3, 2),  # sectors of 120 degrees
])
def test_a_guessed_zone_is_the_looked_up_zone(grid):
    rng = np.random.default_rng(59)
    points = _points(rng, grid)
    guesses = np.array([-7, -1, 0, 1, grid.n_phi // 2, grid.n_theta // 2, grid.n_phi - 1,
                        grid.n_theta - 1, grid.n_phi, grid.n_theta, 10**6])
    both = _both(points, guesses, grid.kernel_args())
    np.testing.assert_array_equal(both[..., 1], both[..., 0])
    np.testing.assert_array_equal(both[..., 3], both[..., 2])
    # ... and with each point's own zone and its neighbours' as the guess.
    for shift in (-1, 0, 1):
        for column in (0, 2):
            own = both[:, 0, column] + shift
            for row in range(0, points.shape[0], 7):
                again = _both(points[row:row + 1], own[row:row + 1], grid.kernel_args())
                assert again[0, 0, column + 1] == again[0, 0, column]


@numba.njit
def _cells_by_lookup(points, grid):
    """``cell_of_point`` (atan2 lookups) of every point."""
    out = np.empty((points.shape[0], 3), dtype=np.int64)
    for row in range(points.shape[0]):
        out[row, 0], out[row, 1], out[row, 2] = cell_of_point(
            points[row, 0], points[row, 1], points[row, 2], grid.rho_edges, grid.rho_kind,
            grid.theta_edges, grid.theta_kind, grid.phi_edges, grid.phi_kind)
    return out


@pytest.mark.parametrize("grid", [
    lt.Grid(0.3, 8.0, 64, 360, 180),
    lt.Grid(0.5, 6.0, 20, 24, 12, theta_range=(-1.0, 2.5), phi_range=(-0.6, 1.1),
            spacing="uniform"),
    lt.Grid.from_edges([0.5, 1.0, 3.0], [0.0, 0.4, 1.1, 4.0], [-0.3, 0.2, 1.5]),
])
def test_cell_of_is_the_lookups_cell(grid):
    """``Grid.cell_of`` (angular zones from a rough guess) gives ``cell_of_point``'s
    cells on and beside every edge, on the seam and on the y axis."""
    points = _points(np.random.default_rng(67), grid)
    want = _cells_by_lookup(points, grid.kernel_args())
    np.testing.assert_array_equal(grid.cell_of(points), want)


@numba.njit
def _rough(points):
    out = np.empty(points.shape[0])
    for row in range(points.shape[0]):
        out[row] = rough_atan2(points[row, 0], points[row, 1])
    return out


def test_the_rough_azimuth_is_within_its_stated_error():
    """The second guess's angle (``rough_atan2``) is within 2e-6 rad of atan2 in
    every octant, on the axes and diagonals, and for tiny and huge components."""
    rng = np.random.default_rng(61)
    points = np.concatenate([
        rng.normal(size=(200_000, 2)),
        rng.normal(size=(1000, 2)) * np.array([[1e-300, 1e300]]),
        [[1.0, 0.0], [0.0, 1.0], [-1.0, 0.0], [0.0, -1.0], [1.0, 1.0], [-1.0, -1.0],
         [1.0, -1.0], [-1.0, 1.0], [0.0, -0.0], [1e-310, -2.0], [-3.0, 1e-320]],
    ])
    points = points[(points[:, 0] != 0.0) | (points[:, 1] != 0.0)]
    exact = np.arctan2(points[:, 0], points[:, 1])
    error = np.abs(_rough(points) - exact)
    error = np.minimum(error, 2 * np.pi - error)  # -pi and pi are the same direction
    assert error.max() < 2e-6
