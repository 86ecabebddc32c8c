"""The paper's Algorithm 1 (bisect) and the Thibaudeau-style baseline."""

import numpy as np
import pytest
from conftest import GRIDS, assert_matches_oracle, random_rays

import logsph_trace as lt


def test_thibaudeau_matches_the_oracle(grid):
    rng = np.random.default_rng(31)
    origins, directions = random_rays(rng, grid, 300)
    traces = lt.trace_many(grid, origins, directions, method="thibaudeau")
    serial = lt.trace_many(grid, origins, directions, method="thibaudeau", parallel=False)
    np.testing.assert_array_equal(traces.cells, serial.cells)
    for row in range(300):
        assert_matches_oracle(grid, origins[row], directions[row], traces[row])


def _subsequence_positions(bisect, exact):
    """Index into ``exact`` of each bisect cell, matched in order; None if impossible."""
    positions = []
    cursor = 0
    for cell, t_sample in zip(bisect.cells, bisect.t_enter):
        while cursor < len(exact) and not (
            np.array_equal(exact.cells[cursor], cell)
            and exact.t_enter[cursor] - 1e-9 <= t_sample <= exact.t_exit[cursor] + 1e-9
        ):
            cursor += 1
        if cursor == len(exact):
            return None
        positions.append(cursor)
    return positions


@pytest.mark.parametrize("default_t", [0.05, 0.4, 1.5531])
def test_bisect_is_a_subsequence_of_exact(grid, default_t):
    rng = np.random.default_rng(32)
    origins, directions = random_rays(rng, grid, 300)
    bisect = lt.trace_many(grid, origins, directions, method="bisect", default_t=default_t)
    exact = lt.trace_many(grid, origins, directions)
    n_theta = grid.n_theta
    for row in range(300):
        approx, truth = bisect[row], exact[row]
        positions = _subsequence_positions(approx, truth)
        assert positions is not None, f"ray {row}: a reported cell is not crossed there"
        if len(approx):
            # It starts where the ray enters and never reports a cell twice in a row.
            np.testing.assert_array_equal(approx.cells[0], truth.cells[0])
            assert not np.any(np.all(approx.cells[1:] == approx.cells[:-1], axis=1))
            # Accepted steps move every index by at most one (the azimuth cyclically).
            steps = np.abs(np.diff(approx.cells.astype(np.int64), axis=0))
            if grid.theta_full:
                steps[:, 1] = np.minimum(steps[:, 1], n_theta - steps[:, 1])
            assert np.all(steps <= 1)


def test_bisect_stops_at_the_first_exit():
    grid = GRIDS["log_full"]()
    origin, direction = [0.2, 0.1, -5.0], [0.0, 0.0, 1.0]  # crosses the egocentric gap
    exact = lt.trace(grid, origin, direction)
    bisect = lt.trace(grid, origin, direction, method="bisect", default_t=0.05)
    gap_start = exact.t_exit[np.flatnonzero(exact.t_enter[1:] > exact.t_exit[:-1])[0]]
    assert bisect.t_enter[-1] < gap_start
    assert len(bisect) < len(exact)


def test_bisect_iteration_cap_bounds_every_ray():
    grid = GRIDS["log_full"]()
    rng = np.random.default_rng(33)
    origins, directions = random_rays(rng, grid, 200)
    capped = lt.trace_many(grid, origins, directions, method="bisect", default_t=1e-4, max_iter=7)
    assert capped.counts.max() <= 8


def test_bisect_skips_cells_where_two_indices_change():
    # A ray through a corner-ish region: bisect may accept a diagonal step.
    grid = GRIDS["log_full"]()
    rng = np.random.default_rng(34)
    origins, directions = random_rays(rng, grid, 500)
    exact = lt.trace_many(grid, origins, directions)
    bisect = lt.trace_many(grid, origins, directions, method="bisect")
    assert bisect.cells.shape[0] < exact.cells.shape[0]


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(default_t=0.0), "default_t must be a positive finite number"),
        (dict(default_t=np.nan), "default_t must be a positive finite number"),
        (dict(default_t="x"), "default_t must be a positive number"),
        (dict(max_iter=0), "max_iter must be a positive integer"),
        (dict(max_iter=2.5), "max_iter must be a positive integer"),
    ],
)
def test_bisect_options_are_checked(kwargs, match):
    grid = GRIDS["log_full"]()
    with pytest.raises(ValueError, match=match):
        lt.trace(grid, [1.0, 0.0, 0.0], [0.0, 0.0, 1.0], method="bisect", **kwargs)


def test_the_paper_example_exact_thibaudeau_and_bisect():
    grid = lt.Grid.from_increments(10.0, 80.0, 10, d_theta=10.0, d_phi=10.0)
    origin, direction = [0, 20, 20], [-0.3, -0.01, 0]
    exact = lt.trace(grid, origin, direction)
    thibaudeau = lt.trace(grid, origin, direction, method="thibaudeau")
    np.testing.assert_array_equal(thibaudeau.cells, exact.cells)
    np.testing.assert_allclose(thibaudeau.t_exit, exact.t_exit, rtol=1e-12)
    # With the paper's own step (1.5531, here in decimetres) Algorithm 1 misses
    # cells on the paper's own example: two indices change in one accepted step.
    bisect = lt.trace(grid, origin, direction, method="bisect")
    assert _subsequence_positions(bisect, exact) is not None
    assert len(bisect) < len(exact)
