"""Grid construction, spacings (docs/geometry.md formulas) and conversions."""

import numpy as np
import pytest
from conftest import GRIDS
from oracle import classify

import logsph_trace as lt


def test_log_spacing_formula():
    grid = lt.Grid(0.3, 10.0, 12, 4, 4)
    i = np.arange(13)
    np.testing.assert_allclose(grid.rho_edges, 0.3 * (10.0 / 0.3) ** (i / 12), rtol=1e-14)
    assert grid.shape == (12, 4, 4) and grid.spacing == "log"


def test_paper_spacing_formula_and_cell_zero():
    grid = lt.Grid(10.0, 80.0, 10, 36, 18, spacing="paper")
    base = 70.0 ** (1 / 10)
    expected = 10.0 + base ** np.arange(11.0)
    expected[0] = 10.0
    np.testing.assert_allclose(grid.rho_edges, expected, rtol=1e-14)
    # [rho_min, rho_min + 1) is not lost (docs/geometry.md): it is folded into cell 0.
    assert grid.cell_of([0.0, 0.0, 10.5])[0] == 0
    assert grid.cell_of([0.0, 0.0, 10.0 + base * 1.01])[0] == 1


def test_uniform_spacing_and_zero_rho_min():
    grid = lt.Grid(0.0, 4.0, 8, 2, 2, spacing="uniform")
    np.testing.assert_allclose(grid.rho_edges, np.linspace(0, 4, 9))
    assert grid.cell_of([0.0, 0.0, 0.0])[0] == 0


def test_from_increments_matches_the_paper_example():
    grid = lt.Grid.from_increments(10.0, 80.0, 10, d_theta=10.0, d_phi=10.0)
    assert grid.shape == (10, 36, 18)
    np.testing.assert_allclose(grid.theta_edges, np.radians(np.arange(-180, 181, 10)))
    assert grid == lt.Grid(10.0, 80.0, 10, 36, 18, spacing="paper")


def test_from_edges_keeps_edges_and_uses_them():
    rho, theta, phi = [0.5, 0.7, 2.0, 9.0], [-1.0, 0.0, 0.5], [-0.2, 0.1, 0.4, 1.0]
    grid = lt.Grid.from_edges(rho, theta, phi)
    assert grid.shape == (3, 2, 3) and grid.spacing == "explicit"
    np.testing.assert_array_equal(grid.rho_edges, rho)
    assert not grid.theta_full


def test_theta_range_may_start_anywhere_and_wraps():
    grid = lt.Grid(1.0, 2.0, 1, 4, 1, theta_range=(3.0, 3.0 + 2 * np.pi))
    assert grid.theta_full
    # theta = -3 (i.e. 2*pi - 3 = 3.28) lies 0.28 past the start of the range: cell 0.
    point = lt.spherical_to_cartesian([1.5, -3.0, 0.0])
    assert grid.cell_of(point)[1] == 0


def test_edges_are_read_only():
    grid = lt.Grid(0.3, 10.0, 4, 4, 4)
    with pytest.raises(ValueError):
        grid.rho_edges[0] = 1.0


@pytest.mark.parametrize("name", sorted(GRIDS))
def test_cell_of_agrees_with_plain_numpy_classification(name):
    grid = GRIDS[name]()
    rng = np.random.default_rng(0)
    points = rng.uniform(-1.2 * grid.rho_max, 1.2 * grid.rho_max, (20000, 3))
    want = classify(points, grid.rho_edges, grid.theta_edges, grid.phi_edges)
    got = grid.cell_of(points)
    want[want[:, 0] < 0] = -1
    np.testing.assert_array_equal(got, want)
    np.testing.assert_array_equal(grid.contains(points), want[:, 0] >= 0)


def test_cell_of_on_edges_takes_the_cell_above_and_closes_the_region():
    grid = lt.Grid(1.0, 3.0, 2, 4, 2, spacing="uniform")
    assert grid.cell_of([0.0, 0.0, 2.0]).tolist() == [1, 2, 1]  # rho on an edge, theta = 0 edge
    assert grid.cell_of([0.0, 0.0, 3.0])[0] == 1  # rho == rho_max is inside (Eq. 1a)
    assert grid.cell_of([0.0, 2.0, 0.0]).tolist() == [1, 2, 1]  # +y axis: phi = pi/2, theta = 0
    assert grid.cell_of([0.0, 0.0, 0.5]).tolist() == [-1, -1, -1]  # in the egocentric gap


def test_cell_bounds_contain_the_cell_centres():
    grid = GRIDS["paper_dm"]()
    rng = np.random.default_rng(1)
    cells = np.stack([rng.integers(0, n, 200) for n in grid.shape], axis=1)
    bounds = grid.cell_bounds(cells)
    assert bounds.shape == (200, 6)
    np.testing.assert_array_equal(grid.cell_of(grid.cell_centers(cells)), cells)
    with pytest.raises(ValueError, match="cells must lie in the grid"):
        grid.cell_bounds([[0, 0, 18]])


def test_spherical_round_trip():
    rng = np.random.default_rng(2)
    points = rng.normal(size=(1000, 3)) * 5
    back = lt.spherical_to_cartesian(lt.cartesian_to_spherical(points))
    np.testing.assert_allclose(back, points, atol=1e-12)
    sph = lt.cartesian_to_spherical([0.0, 1.0, 0.0])
    np.testing.assert_allclose(sph, [1.0, 0.0, np.pi / 2])  # y axis is at 90 deg, not 45 (Eq. 7)
    np.testing.assert_allclose(lt.cartesian_to_spherical([1.0, 0.0, 0.0]), [1.0, np.pi / 2, 0.0])


def test_ros_frame_is_a_documented_rotation():
    forward, left, up = lt.from_ros(np.eye(3))
    np.testing.assert_array_equal(forward, [0, 0, 1])  # theta = 0
    np.testing.assert_array_equal(up, [0, 1, 0])  # phi = pi/2
    np.testing.assert_array_equal(left, [1, 0, 0])  # theta = +pi/2
    assert np.linalg.det(lt.grid.ROS_TO_GRID) == pytest.approx(1.0)


def test_repr_names_the_partition():
    assert "log" in repr(lt.Grid(0.3, 10.0, 4, 4, 4))


def test_an_elevation_edge_within_rounding_of_zero_is_the_plane():
    # np.linspace(-pi/2, pi/2, 101)[50] is 2.2e-16: the grids make it 0, and a
    # grid rebuilt from its edges keeps them and their closed-form lookups.
    for n_phi in (50, 100):
        grid = lt.Grid(0.5, 5.0, 4, 8, n_phi)
        assert grid.phi_edges[n_phi // 2] == 0.0
        again = lt.Grid.from_edges(grid.rho_edges, grid.theta_edges, grid.phi_edges,
                                   spacing="log")
        np.testing.assert_array_equal(again.phi_edges, grid.phi_edges)
        assert again.phi_kind == grid.phi_kind
    edges = np.array([-0.5, -2e-16, 3e-16, 0.5])  # two such edges are not increasing
    with pytest.raises(ValueError):
        lt.Grid.from_edges([0.5, 1.0], [-1.0, 1.0], edges)
    grid = lt.Grid.from_edges([0.5, 1.0], [-1.0, 1.0], [-0.5, 2.2e-16, 0.5])
    assert grid.phi_edges.tolist() == [-0.5, 0.0, 0.5]
    kept = lt.Grid.from_edges([0.5, 1.0], [-1.0, 1.0], [-0.5, 1e-15, 0.5])
    assert kept.phi_edges[1] == 1e-15  # farther than 4 ulps of 1 from 0: a cone
