"""Sources on vertices and faces, rays along and across walls, at every scale
the library supports (``walls.py``), against the oracle cell by cell.

A ray agrees when it matches the oracle (``compare``), or, where it may lie
in a face, satisfies the closure rule (``within_faces``: every segment in
its closed cell, the same stretch covered); a tangent ray may also show or
omit an unresolved sliver. Every segment's midpoint is looked up with
``Grid.cell_of`` too: where it names another cell, the closure rule must hold.
"""

import numpy as np
import pytest
from walls import SCALES, WALL_GRIDS, cases, scaled, wrong_rays

import logsph_trace as lt
from logsph_trace import _validate

# Cases drawn per grid and scale, of 21,000 to 52,000 (``python tests/walls.py``
# runs every one, at every scale).
PER_SCALE = 600


def _edge_scales(grid):
    """The factors that put the grid's smallest positive radius at the smallest
    supported length, and its rho_max at the largest."""
    radii = grid.rho_edges[grid.rho_edges > 0.0]
    return (_validate.SMALLEST_LENGTH / radii[0], _validate.LARGEST_LENGTH / radii[-1])


@pytest.mark.parametrize("name", sorted(WALL_GRIDS))
def test_sources_on_vertices_and_faces_at_every_scale(name):
    base = WALL_GRIDS[name]()
    origins, directions, kinds = cases(base, seed=sorted(WALL_GRIDS).index(name))
    kinds = np.array(kinds)
    rng = np.random.default_rng(51)
    failures = []
    for factor in SCALES + _edge_scales(base):
        pick = rng.choice(len(origins), PER_SCALE, replace=False)
        grid = scaled(base, factor)
        found = wrong_rays(grid, origins[pick] * factor, directions[pick], kinds[pick])
        failures += [f"scale {factor:g}: {message}" for message in found]
    assert not failures, f"{len(failures)} rays wrong; first:\n{failures[0]}"


def _check_one(grid, origin, direction, kind="along"):
    failures = wrong_rays(grid, np.array([origin], dtype=float), np.array([direction], dtype=float),
                         [kind])
    assert not failures, failures[0]


def test_a_ray_from_a_cone_along_its_tangent_goes_down_band_by_band():
    """A source on the 67.5-degree cone looking horizontally along it, where phi
    turns. The cone's double root must not come from ``c / q``, whose c cancels there."""
    grid = lt.Grid.from_edges([0.0, 10.0], [0.0, 2 * np.pi], np.linspace(-np.pi / 2, np.pi / 2, 17))
    origin = [0.02760996481435132, 0.9238795325112867, 0.38168612661410234]
    for d_y in (0.0, 6.123233995736766e-17, -3e-17, 1e-16):
        direction = [0.997393914482203, d_y, -0.07214831497594258]
        assert lt.trace(grid, origin, direction).cells[:, 2].tolist() == [13, 12, 11, 10, 9, 8]
        _check_one(grid, origin, direction, "tangent")


@pytest.mark.parametrize("d_z", [-2.4e-17, -4e-17, -6e-17, -6.123233995736766e-17])
def test_a_ray_on_a_rounded_half_plane_across_the_y_axis_turns_there(d_z):
    """The stored -pi/2 is 6.1e-17 rad off the true plane. A source on it, looking
    across the y axis within rounding of it, meets the plane on its other half."""
    grid = lt.Grid.from_edges([0.0, 1.0], [-np.pi, -np.pi / 2, np.pi / 4, np.pi],
                              [-np.pi / 2, np.pi / 2])
    for factor in (1e-20, 1.0, 1e20):
        trace = lt.trace(scaled(grid, factor), [-0.5 * factor, 0.3 * factor, 0.0],
                         [1.0, 0.0, d_z])
        assert trace.cells[-1].tolist() == [0, 2, 0]
        assert trace.t_enter[-1] == pytest.approx(0.5 * factor, rel=1e-12)
        _check_one(scaled(grid, factor), [-0.5 * factor, 0.3 * factor, 0.0], [1.0, 0.0, d_z])


@pytest.mark.parametrize("offset", [1e-170, 1e-120, 1e-40, 1e-25])
def test_an_origin_all_but_at_the_centre_traces_as_the_centre(offset):
    """Below ``AT_CENTRE`` rho_max the origin is the centre. The squares of 1e-170
    underflow, so the line cannot be told from one through the centre."""
    grid = lt.Grid(0.2, 12.0, 64, 90, 45)
    direction = np.array([0.3456, 0.8216, 0.3304])
    from_centre = lt.trace(grid, [0.0, 0.0, 0.0], direction)
    for origin in ([offset, 0.0, 0.0], [0.0, -offset, 0.3 * offset]):
        near = lt.trace(grid, origin, direction)
        np.testing.assert_array_equal(near.cells, from_centre.cells)
        np.testing.assert_allclose(near.t_exit, from_centre.t_exit, rtol=1e-15)
        cone = lt.trace_cone(grid, origin, direction, 0.05)
        np.testing.assert_array_equal(cone.cells,
                                      lt.trace_cone(grid, [0.0, 0.0, 0.0], direction, 0.05).cells)
    # Just above it the line is traced as it is, and still agrees with the oracle.
    _check_one(grid, [1e-19, 0.0, 0.0], direction, "random")


def test_a_sensor_all_but_at_the_centre_integrates_as_at_the_centre():
    grid = lt.Grid(0.2, 12.0, 16, 24, 12)
    points = np.random.default_rng(3).normal(size=(500, 3)) * 4.0
    at = lt.OccupancyGrid(grid)
    at.integrate(points, [0.0, 0.0, 0.0])
    near = lt.OccupancyGrid(grid)
    near.integrate(points, [1e-170, 0.0, -1e-171])
    np.testing.assert_array_equal(near.log_odds, at.log_odds)


@pytest.mark.parametrize("make, match", [
    (lambda: lt.Grid(2e-161, 1.2e-159, 8, 8, 8), r"rho_min must lie within \[1e-100, 1e\+100\]"),
    (lambda: lt.Grid(0.0, 1e-120, 8, 8, 8, spacing="uniform"), r"rho_max must lie within"),
    (lambda: lt.Grid(0.2, 1e120, 8, 8, 8), r"rho_max must lie within"),
    (lambda: lt.Grid.from_edges([1e-300, 1.0], [0, 1], [0, 1]), r"rho_edges must lie within"),
    (lambda: lt.Grid.from_edges([0.0, 1e-110, 1.0], [0, 1], [0, 1]), r"rho_edges must lie"),
])
def test_grids_outside_the_supported_lengths_are_refused(make, match):
    with pytest.raises(ValueError, match=match):
        make()


def test_grids_at_the_edges_of_the_supported_lengths_are_taken():
    assert lt.Grid(1e99, 1e100, 8, 8, 8).rho_max == 1e100
    assert lt.Grid(1e-100, 2e-100, 8, 8, 8).rho_min == 1e-100
    assert lt.Grid(0.0, 1e-99, 8, 8, 8, spacing="uniform").rho_edges[1] >= 1e-100


@pytest.mark.parametrize("call, name, row", [
    (lambda g, o: lt.trace(g, o, [-1.0, 0.0, 0.0]), "origins", 0),
    # a batch long enough to be checked on all threads, its far row last
    (lambda g, o: lt.trace_many(g, np.array([[0.5, 0.0, 0.0]] * 40_000 + [o]),
                                [-1.0, 0.0, 0.0]), "origins", 40_000),
    (lambda g, o: lt.trace_cone(g, o, [-1.0, 0.0, 0.0], 0.1), "origin", 0),
    (lambda g, o: lt.trace_cones(g, [o], [[-1.0, 0.0, 0.0]], 0.1), "origins", 0),
    (lambda g, o: lt.OccupancyGrid(g).integrate([[1.0, 0.0, 0.0]], o), "sensor_origin", 0),
    (lambda g, o: lt.fixation_probability(lt.OccupancyGrid(g), o, [-1.0, 0.0, 0.0]), "origin",
     0),
])
def test_origins_beyond_the_supported_reach_are_refused(call, name, row):
    """From 1e13 rho_max a ray through the centre would cross nothing."""
    grid = lt.Grid(0.2, 12.0, 16, 24, 12)
    match = (rf"^{name} must lie within 1e9 rho_max \(1.2e\+10\) .* "
             rf"row {row} is \[10000000000000.0, 0.0, 0.0\], 1e\+13 away")
    with pytest.raises(ValueError, match=match):
        call(grid, [1e13, 0.0, 0.0])
    call(grid, [0.99e9 * 12.0, 0.0, 0.0])  # inside the reach: traced
