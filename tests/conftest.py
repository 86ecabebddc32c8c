"""Shared grids and helpers: the grid zoo every traversal method is checked on."""

import numpy as np
import pytest
from oracle import TANGENT_SLIVER, compare, oracle_trace  # noqa: F401

import logsph_trace as lt


def _explicit_grid():
    rng = np.random.default_rng(7)
    return lt.Grid.from_edges(
        np.sort(rng.uniform(0.5, 4.0, 7)),
        np.sort(rng.uniform(0.3, 1.2, 5)),
        np.sort(rng.uniform(-1.2, -0.1, 4)),
    )


# Spacings log / paper / uniform / explicit; full and partial theta and phi
# ranges (a theta range wider than half a turn, one that starts anywhere, a
# narrow one); rho_min small, large and zero; single-cell angular axes.
GRIDS = {
    "log_full": lambda: lt.Grid(0.3, 10.0, 12, 16, 8),
    "paper_dm": lambda: lt.Grid(10.0, 80.0, 10, 36, 18, spacing="paper"),
    "uniform_partial_wide": lambda: lt.Grid(
        1.0, 5.0, 7, 9, 5, theta_range=(-2.5, 2.0), phi_range=(-0.6, 1.0), spacing="uniform"
    ),
    "explicit_narrow": _explicit_grid,
    "thin_shell": lambda: lt.Grid(4.0, 6.0, 5, 24, 12),
    "seam_at_one_radian": lambda: lt.Grid(0.5, 3.0, 6, 7, 5, theta_range=(1.0, 1.0 + 2 * np.pi)),
    "uniform_rho_min_zero": lambda: lt.Grid(0.0, 3.0, 6, 8, 6, spacing="uniform"),
    "one_sector": lambda: lt.Grid(0.5, 3.0, 4, 1, 1),
    "small_window": lambda: lt.Grid(
        0.5, 3.0, 4, 3, 3, theta_range=(0.2, 0.9), phi_range=(0.1, 0.5)
    ),
}


@pytest.fixture(params=sorted(GRIDS), scope="module")
def grid(request):
    return GRIDS[request.param]()


def assert_matches_oracle(grid, origin, direction, result, rel=1e-9, scale=None,
                          rel_distances=None):
    """``scale`` (default rho_max): the size tolerances are relative to;
    ``rel_distances``: the distances' own tolerance (default ``rel``, see ``compare``)."""
    want = oracle_trace(origin, direction, grid.rho_edges, grid.theta_edges, grid.phi_edges)
    scale = grid.rho_max if scale is None else scale
    message = compare((result.cells, result.t_enter, result.t_exit), want, scale, rel,
                      rel_distances)
    assert message is None, f"origin={list(origin)} direction={list(direction)}: {message}"


def random_rays(rng, grid, n_rays):
    """Origins in a box 1.3x the region (inside, in the gap and outside), random directions."""
    reach = 1.3 * grid.rho_max
    origins = rng.uniform(-reach, reach, (n_rays, 3))
    directions = rng.normal(size=(n_rays, 3))
    return origins, directions


def pytest_addoption(parser):
    parser.addoption("--fuzz-rays", type=int, default=200_000,
                     help="rays of tests/test_fuzz.py over all grid kinds together "
                          "(default 200,000; more for a longer fuzz)")


@pytest.fixture(scope="session")
def fuzz_rays(request):
    return request.config.getoption("--fuzz-rays")
