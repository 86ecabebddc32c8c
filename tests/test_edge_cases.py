"""Hand-made rays for every special case of the geometry contract.

Each is checked against the oracle *and* against what the geometry says must
happen (a gap, a seam crossing, a fixed index...), so a wrong oracle cannot
hide a wrong kernel.
"""

import numpy as np
import pytest
from conftest import GRIDS, TANGENT_SLIVER, assert_matches_oracle
from singular import CLASSES, singular_rays

import logsph_trace as lt
from logsph_trace import _batching, _validate
from logsph_trace.kernels import geometry, locate


@pytest.fixture(scope="module")
def grid():
    return GRIDS["log_full"]()  # rho 0.3..10 in 12 log shells, 16 x 8 angular cells


def run(grid, origin, direction, rel=1e-9):
    result = lt.trace(grid, origin, direction)
    assert_matches_oracle(grid, origin, direction, result, rel=rel)
    assert np.all(result.t_exit > result.t_enter), "zero-length segment"
    touching = result.t_enter[1:] == result.t_exit[:-1]
    repeated = np.all(result.cells[1:] == result.cells[:-1], axis=1)
    assert not np.any(touching & repeated), "a cell repeated across a shared boundary"
    return result


def gaps(result):
    """(t_from, t_to) of every stretch between segments that do not touch."""
    return [(a, b) for a, b in zip(result.t_exit[:-1], result.t_enter[1:]) if b > a]


def test_origin_outside_enters_at_rho_max(grid):
    result = run(grid, [0.0, 0.0, -20.0], [0.1, 0.05, 1.0])
    unit = np.array([0.1, 0.05, 1.0]) / np.linalg.norm([0.1, 0.05, 1.0])
    entry = np.array([0.0, 0.0, -20.0]) + result.t_enter[0] * unit
    assert np.linalg.norm(entry) == pytest.approx(grid.rho_max, rel=1e-12)
    assert result.cells[0, 0] == grid.n_rho - 1


def test_origin_outside_pointing_away_or_missing_is_empty(grid):
    assert len(run(grid, [0.0, 0.0, -20.0], [0.0, 0.0, -1.0])) == 0
    assert len(run(grid, [0.0, 15.0, -20.0], [0.0, 0.0, 1.0])) == 0


def test_egocentric_gap_is_crossed_and_left_out(grid):
    result = run(grid, [0.2, 0.1, -5.0], [0.0, 0.0, 1.0])
    (gap,) = gaps(result)
    chord = 2 * np.sqrt(grid.rho_min**2 - 0.2**2 - 0.1**2)
    assert gap[1] - gap[0] == pytest.approx(chord, rel=1e-12)
    assert result.cells[0, 0] == grid.cell_of([0.2, 0.1, -5.0])[0]
    assert result.cells[-1, 0] == grid.n_rho - 1


def test_reentry_through_a_theta_range_wider_than_half_a_turn():
    grid = GRIDS["uniform_partial_wide"]()  # theta in (-2.5, 2.0): 4.5 rad
    result = run(grid, [-3.0, 0.0, -2.0], [1.0, 0.0, 0.0])
    (gap,) = gaps(result)
    # The ray leaves at theta_min = -2.5 (sweeping down) and comes back at theta_max = 2.0.
    before = result.cells[result.t_exit <= gap[0]]
    after = result.cells[result.t_enter >= gap[1]]
    assert before[-1, 1] == 0 and after[0, 1] == grid.n_theta - 1


def test_reentry_through_a_partial_phi_range():
    grid = GRIDS["uniform_partial_wide"]()  # phi in (-0.6, 1.0)
    result = run(grid, [-4.0, 2.0, 0.3], [1.0, 0.0, 0.0])
    (gap,) = gaps(result)
    # phi rises above phi_max near the y axis and falls back: both sides are in the top row.
    assert result.cells[result.t_exit <= gap[0]][-1, 2] == grid.n_phi - 1
    assert result.cells[result.t_enter >= gap[1]][0, 2] == grid.n_phi - 1


def test_theta_seam_of_a_full_circle(grid):
    result = run(grid, [-1.0, 0.2, -3.0], [1.0, 0.0, 0.0])
    # Crossing x = 0 behind the robot (z < 0) passes theta = -pi == pi: j wraps 0 -> 15.
    j = result.cells[:, 1]
    wraps = np.flatnonzero((j[:-1] == 0) & (j[1:] == grid.n_theta - 1))
    assert wraps.size == 1 and gaps(result) == []


def test_seam_where_the_theta_range_starts_anywhere():
    grid = GRIDS["seam_at_one_radian"]()
    seam = 1.0
    start = seam + 0.3
    origin = 2.0 * np.array([np.sin(start), 0.0, np.cos(start)])
    result = run(grid, origin, [-np.cos(start), 0.0, np.sin(start)])  # sweeps theta downward
    j = result.cells[:, 1]
    assert np.any((j[:-1] == 0) & (j[1:] == grid.n_theta - 1))


def test_one_sector_circle_seam_does_not_repeat_the_cell():
    grid = GRIDS["one_sector"]()
    result = run(grid, [-1.0, 0.2, -1.5], [1.0, 0.0, 0.0])
    assert np.all(result.cells[:, 1:] == 0)


def test_ray_through_the_origin(grid):
    result = run(grid, [-2.0, -1.0, -3.0], [2.0, 1.0, 3.0])
    (gap,) = gaps(result)
    assert gap[1] - gap[0] == pytest.approx(2 * grid.rho_min, rel=1e-12)
    first, last = result.cells[0], result.cells[-1]
    assert first[1] != last[1] and first[2] + last[2] == grid.n_phi - 1  # opposite directions


def test_ray_through_the_origin_without_a_gap():
    grid = GRIDS["uniform_rho_min_zero"]()
    result = run(grid, [-2.0, -1.0, -3.0], [2.0, 1.0, 3.0])
    assert gaps(result) == []
    inner = result.cells[result.cells[:, 0] == 0]
    assert len(inner) == 2 and inner[0, 2] + inner[1, 2] == grid.n_phi - 1


def test_ray_along_the_y_axis(grid):
    result = run(grid, [0.0, -5.0, 0.0], [0.0, 1.0, 0.0])
    (gap,) = gaps(result)
    below = result.cells[result.t_exit <= gap[0]]
    above = result.cells[result.t_enter >= gap[1]]
    assert np.all(below[:, 2] == 0) and np.all(above[:, 2] == grid.n_phi - 1)
    # theta = atan2(0, 0) = 0 on the axis: the cell whose lower edge is 0.
    assert np.all(result.cells[:, 1] == grid.n_theta // 2)


def test_ray_starting_on_the_y_axis_and_parallel_to_it(grid):
    up = run(grid, [0.0, 0.5, 0.0], [0.0, 1.0, 0.0])
    assert np.all(up.cells[:, 2] == grid.n_phi - 1) and up.t_enter[0] == 0.0
    side = run(grid, [1.0, -5.0, 1.0], [0.0, 2.0, 0.0])
    assert np.all(side.cells[:, 1] == side.cells[0, 1])  # theta never changes
    assert np.all(np.diff(side.cells[:, 2]) >= 0)  # phi only rises


def test_ray_starting_at_the_origin(grid):
    result = run(grid, [0.0, 0.0, 0.0], [1.0, 1.0, 1.0])
    assert result.t_enter[0] == pytest.approx(grid.rho_min, rel=1e-12)
    assert np.all(result.cells[:, 1:] == result.cells[0, 1:])


def test_ray_in_the_plane_of_the_equator(grid):
    # phi == 0 exactly everywhere: on the phi = 0 edge, so the cell above it.
    result = run(grid, [-5.0, 0.0, 1.0], [1.0, 0.0, 0.0])
    assert np.all(result.cells[:, 2] == grid.n_phi // 2)


@pytest.mark.parametrize("shell", [0, 5, 11, 12])
def test_ray_tangent_to_a_sphere(grid, shell):
    radius = grid.rho_edges[shell]
    result = run(grid, [radius, 0.0, -5.0], [0.0, 0.0, 1.0], rel=TANGENT_SLIVER)
    long = result.lengths > TANGENT_SLIVER * grid.rho_max
    assert np.all(result.cells[long, 0] >= shell)  # touches, never enters the inner shell
    if shell == grid.n_rho:
        assert not np.any(long)  # grazes rho_max: nothing inside


def test_ray_tangent_to_a_cone(grid):
    edge = grid.phi_edges[5]  # pi/8
    height = 2.0 * np.tan(edge)
    result = run(grid, [-4.0, height, 2.0], [1.0, 0.0, 0.0], rel=TANGENT_SLIVER)
    long = result.lengths > TANGENT_SLIVER * grid.rho_max
    assert np.all(result.cells[long, 2] == 4)  # phi peaks exactly at the edge


def test_simultaneous_crossing_of_sphere_plane_and_cone(grid):
    rho, theta, phi = grid.rho_edges[6], grid.theta_edges[10], grid.phi_edges[5]
    corner = lt.spherical_to_cartesian([rho, theta, phi])
    direction = np.array([0.3, -0.7, 0.5])
    result = run(grid, corner - 2.0 * direction / np.linalg.norm(direction), direction)
    at_corner = np.flatnonzero(np.isclose(result.t_exit, 2.0, rtol=1e-12))
    assert at_corner.size == 1
    before, after = result.cells[at_corner[0]], result.cells[at_corner[0] + 1]
    assert np.all(before != after)  # all three indices change at once, in one step


@pytest.mark.parametrize("sign", [1.0, -1.0])
def test_ray_starting_on_a_boundary(grid, sign):
    on_sphere = grid.rho_edges[6] * np.array([0.0, 0.6, 0.8])
    run(grid, on_sphere, sign * on_sphere)
    on_plane = lt.spherical_to_cartesian([2.0, grid.theta_edges[3], 0.3])
    run(grid, on_plane, [sign, 0.2, 0.1])
    on_cone = lt.spherical_to_cartesian([2.0, 0.3, grid.phi_edges[6]])
    run(grid, on_cone, [0.1, sign, 0.2])


def test_segment_count_respects_the_loop_bound():
    for name, make in GRIDS.items():
        grid = make()
        n_rho, n_theta, n_phi = grid.shape
        bound = 2 * (n_rho + 1) + (n_theta + 2) + 2 * (n_phi + 1) + 2
        rng = np.random.default_rng(1)
        traces = lt.trace_many(grid, rng.uniform(-20, 20, (2000, 3)), rng.normal(size=(2000, 3)))
        assert traces.counts.max() <= bound, name


@pytest.mark.parametrize("name", sorted(GRIDS))
def test_the_bound_pass_is_never_below_a_rays_segments(name):
    # The parallel paths and the GPU size each ray's region by its bound
    # (_batching.bound_counts on the CPU, geometry.ray_bound on the GPU): one below
    # the segments would overwrite the next ray. Random rays, near-singular
    # ones, rays from the centre and the y axis along the edges' directions,
    # and rays stopped at a random t_max.
    grid = GRIDS[name]()
    rng = np.random.default_rng(sorted(GRIDS).index(name))
    sets = [(rng.uniform(-1.3, 1.3, (3000, 3)) * grid.rho_max, rng.normal(size=(3000, 3)))]
    sets += [singular_rays(rng, grid, kind, 20)[:2] for kind in CLASSES]
    theta = np.resize(grid.theta_edges, 200)
    phi = np.resize(grid.phi_edges, 200)
    along = np.stack([np.cos(phi) * np.sin(theta), np.sin(phi), np.cos(phi) * np.cos(theta)], 1)
    sets.append((np.zeros_like(along), along))
    sets.append((np.c_[np.zeros(200), rng.uniform(-1, 1, 200) * grid.rho_max, np.zeros(200)],
                 along))
    origins, directions = _validate.rays(np.concatenate([s[0] for s in sets]),
                                         np.concatenate([s[1] for s in sets]))
    bounds = np.empty(len(origins), dtype=np.int64)
    _batching.bound_counts(origins, directions, grid.kernel_args(), bounds)
    t_max = rng.uniform(0.0, 2.5, len(origins)) * grid.rho_max
    for stop in (None, t_max):
        counts = lt.trace_many(grid, origins, directions, t_max=stop, parallel=False).counts
        assert np.all(bounds >= counts), np.flatnonzero(bounds < counts)[:10]
    assert np.all(bounds <= geometry.max_segments(*grid.shape))
    # The GPU's per-ray function gives the same bounds.
    args = grid.kernel_args()
    per_log = locate.per_log_of(grid.rho_edges, grid.rho_kind)
    lookups = np.zeros(8, dtype=np.int64)
    assert [geometry.ray_bound(origins, directions, row, args, per_log, lookups)
            for row in range(len(origins))] == bounds.tolist()
