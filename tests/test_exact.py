"""The exact method against the slow oracle, on thousands of random rays."""

import numpy as np
import pytest
from conftest import GRIDS, TANGENT_SLIVER, assert_matches_oracle, random_rays
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st
from oracle import UNRESOLVED_TANGENT, compare, cut_at, oracle_trace

import logsph_trace as lt
from logsph_trace import _validate

RAYS_PER_GRID = 700  # 9 grids -> 6,300 random rays


def test_random_rays_match_oracle(grid):
    rng = np.random.default_rng(20261122)
    origins, directions = random_rays(rng, grid, RAYS_PER_GRID)
    traces = lt.trace_many(grid, origins, directions)
    assert len(traces) == RAYS_PER_GRID
    for row in range(RAYS_PER_GRID):
        assert_matches_oracle(grid, origins[row], directions[row], traces[row])


def test_rays_from_inside_the_region_match_oracle(grid):
    # Origins drawn as in the paper's use: the person stands inside the map.
    rng = np.random.default_rng(5)
    points = rng.uniform(-grid.rho_max, grid.rho_max, (4000, 3))
    origins = points[grid.contains(points)][:150]
    directions = rng.normal(size=origins.shape)
    traces = lt.trace_many(grid, origins, directions)
    for row in range(len(origins)):
        assert traces[row].t_enter[0] == 0.0 if len(traces[row]) else True
        assert_matches_oracle(grid, origins[row], directions[row], traces[row])


# The kernel absorbs slivers shorter than this share of the scene,
# rho_max + |o|, into the next segment (docs/geometry.md, "Default"). From
# an origin beyond about 1,000 rho_max that is more than the default 1e-9
# rho_max, so far rays are compared with the slivers below it dropped: a
# quarter more, for the two sides' rounding of a sliver's length.
ABSORBED = 1e-12


def test_far_origins_match_oracle(grid):
    # exact, thibaudeau and a t_max cut, from |o| of 10 to 1e8 rho_max (24
    # rays a decade), aimed at random points of the ball and at points near
    # the centre, from 3 rho_min (or 1% of rho_max) down to 1,000 absorbed
    # slivers: closer, the cells about the centre are crossed for about a
    # sliver, which one side absorbs into its neighbour (making it longer
    # than the cut) and the other drops (lines through the centre:
    # test_singular.py). The oracle is given the package's unit vector; so
    # given, it agreed with a 60-digit reference on 1,800 rays up to 1e10
    # rho_max (bench/results/far_origins.md).
    rng = np.random.default_rng(20261125)
    per_decade = 24
    near = grid.rho_min if grid.rho_min > 0.0 else 0.01 * grid.rho_max
    for decade in range(1, 8):
        distance = grid.rho_max * 10.0 ** (decade + rng.random(per_decade))
        origins = rng.normal(size=(per_decade, 3))
        origins *= (distance / np.linalg.norm(origins, axis=1))[:, None]
        aims = rng.normal(size=(per_decade, 3))
        aims /= np.linalg.norm(aims, axis=1)[:, None]
        closest = np.log10(1e3 * ABSORBED * (grid.rho_max + distance))
        reach = np.where(np.arange(per_decade) % 2 == 0,
                         grid.rho_max * rng.random(per_decade) ** (1 / 3),
                         10.0 ** rng.uniform(closest, np.maximum(closest, np.log10(3.0 * near))))
        directions = aims * reach[:, None] - origins
        _, units = _validate.rays(origins, directions)  # the line traced, for the oracle too
        # A cut within rho_max of the closest approach, mostly inside the region.
        t_max = -np.sum(origins * units, axis=1) + grid.rho_max * rng.uniform(-1.3, 1.3, per_decade)
        runs = {
            "exact": lt.trace_many(grid, origins, directions),
            "thibaudeau": lt.trace_many(grid, origins, directions, method="thibaudeau"),
            "t_max": lt.trace_many(grid, origins, directions, t_max=t_max),
        }
        for row in range(per_decade):
            want = oracle_trace(origins[row], units[row], grid.rho_edges, grid.theta_edges,
                                grid.phi_edges, normalise=False)
            scale = max(grid.rho_max, 1.25 * ABSORBED * (grid.rho_max + distance[row]) / 1e-9)
            for label, traces in runs.items():
                reference = cut_at(want, t_max[row]) if label == "t_max" else want
                got = (traces[row].cells, traces[row].t_enter, traces[row].t_exit)
                message = compare(got, reference, scale)
                assert message is None, (f"{label} origin={origins[row]} "
                                         f"direction={directions[row]}: {message}")


def test_segments_are_ordered_contiguous_and_inside(grid):
    rng = np.random.default_rng(11)
    origins, directions = random_rays(rng, grid, 400)
    traces = lt.trace_many(grid, origins, directions)
    assert np.all(traces.t_exit > traces.t_enter)
    assert np.all(traces.t_enter >= 0.0)
    shape = np.array(grid.shape)
    assert np.all((traces.cells >= 0) & (traces.cells < shape))
    unit = directions / np.linalg.norm(directions, axis=1, keepdims=True)
    for row, one in enumerate(traces):
        if len(one) == 0:
            continue
        assert np.all(one.t_enter[1:] >= one.t_exit[:-1])
        touching = one.t_enter[1:] == one.t_exit[:-1]
        same = np.all(one.cells[1:] == one.cells[:-1], axis=1)
        assert not np.any(touching & same), "a cell is repeated across a shared boundary"
        # Each segment's midpoint lies in the cell reported for it.
        mids = origins[row] + 0.5 * (one.t_enter + one.t_exit)[:, None] * unit[row]
        long_enough = one.lengths > 1e-9 * grid.rho_max
        np.testing.assert_array_equal(grid.cell_of(mids)[long_enough], one.cells[long_enough])


def test_parallel_and_serial_are_identical(grid):
    rng = np.random.default_rng(3)
    origins, directions = random_rays(rng, grid, 2000)
    serial = lt.trace_many(grid, origins, directions, parallel=False)
    parallel = lt.trace_many(grid, origins, directions, parallel=True)
    for name in ("offsets", "cells", "t_enter", "t_exit"):
        np.testing.assert_array_equal(getattr(serial, name), getattr(parallel, name))


def test_trace_equals_row_of_trace_many():
    grid = GRIDS["log_full"]()
    rng = np.random.default_rng(4)
    origins, directions = random_rays(rng, grid, 20)
    many = lt.trace_many(grid, origins, directions)
    for row in range(20):
        one = lt.trace(grid, origins[row], directions[row])
        np.testing.assert_array_equal(one.cells, many[row].cells)
        np.testing.assert_array_equal(one.t_enter, many[row].t_enter)


def test_open3d_style_rays_array():
    grid = GRIDS["paper_dm"]()
    rng = np.random.default_rng(6)
    origins, directions = random_rays(rng, grid, 50)
    split = lt.trace_many(grid, origins, directions)
    joined = lt.trace_many(grid, np.hstack([origins, directions]))
    np.testing.assert_array_equal(split.offsets, joined.offsets)
    np.testing.assert_array_equal(split.cells, joined.cells)


def test_direction_length_does_not_matter():
    grid = GRIDS["log_full"]()
    rng = np.random.default_rng(8)
    origins, directions = random_rays(rng, grid, 100)
    unit = lt.trace_many(grid, origins, directions / np.linalg.norm(directions, axis=1)[:, None])
    scaled = lt.trace_many(grid, origins, 37.5 * directions)
    np.testing.assert_array_equal(unit.cells, scaled.cells)
    np.testing.assert_allclose(unit.t_exit, scaled.t_exit, rtol=1e-12)


def test_csr_views():
    grid = GRIDS["log_full"]()
    rng = np.random.default_rng(9)
    origins, directions = random_rays(rng, grid, 30)
    traces = lt.trace_many(grid, origins, directions)
    assert traces.offsets.dtype == np.int64 and traces.offsets[0] == 0
    assert traces.cells.dtype == np.int32 and traces.cells.flags.c_contiguous
    assert traces.counts.sum() == traces.cells.shape[0]
    assert traces[-1].cells.shape == traces[len(traces) - 1].cells.shape
    assert sum(len(one) for one in traces) == traces.cells.shape[0]
    np.testing.assert_array_equal(np.bincount(traces.ray_index, minlength=30), traces.counts)
    with pytest.raises(IndexError):
        traces[30]


def test_unique_keeps_first_entry_order():
    trace = lt.Trace(
        np.array([[1, 2, 3], [1, 2, 4], [1, 2, 3], [0, 0, 0]], dtype=np.int32),
        np.array([0.0, 1.0, 2.0, 3.0]),
        np.array([1.0, 2.0, 3.0, 4.0]),
    )
    np.testing.assert_array_equal(trace.unique(), [[1, 2, 3], [1, 2, 4], [0, 0, 0]])
    assert lt.Trace(np.empty((0, 3), np.int32), np.empty(0), np.empty(0)).unique().shape == (0, 3)


# Values on a 1e-6 lattice: hypothesis still finds zeros, axes and round numbers,
# but not 1e-226, whose square underflows (a documented limit: components are
# 0 or larger than about 1e-150 in magnitude).
coordinate = st.floats(-15.0, 15.0, allow_nan=False, allow_infinity=False).map(
    lambda v: round(v, 6))
component = st.floats(-1.0, 1.0, allow_nan=False, allow_infinity=False).map(lambda v: round(v, 6))


def _along_a_cone(grid, direction):
    """How much a tangency's rounding of the distances grows when ``direction`` is
    nearly along a generatrix of one of the grid's cones: sqrt(1 / min |a|), at
    least 1 (median 3.7 for random directions on the 8-band grid).

    ``a = d_y^2 - tan^2(phi) (d_x^2 + d_z^2)`` (unit d) is the cone quadratic's
    leading coefficient. At a tangency the two crossings are u = -b' / a +-
    sqrt(b'^2 - a c) / a; the discriminant's rounding is about eps |a| times
    terms of order R^2 (b' and c are a u and a u^2 there), so the crossings
    move by about sqrt(eps / |a|) R: the tangent-sliver tolerance's sqrt(eps) R
    times this factor.
    """
    d = np.asarray(direction, dtype=np.float64)
    d = d / np.linalg.norm(d)
    phi = grid.phi_edges[np.abs(grid.phi_edges) < np.pi / 2]
    a = np.abs(d[1] ** 2 - np.tan(phi) ** 2 * (d[0] ** 2 + d[2] ** 2))
    return max(1.0, float(np.sqrt(1.0 / max(a.min(), 1e-12)))) if phi.size else 1.0


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    name=st.sampled_from(sorted(GRIDS)),
    origin=st.tuples(coordinate, coordinate, coordinate),
    direction=st.tuples(component, component, component).filter(
        lambda v: v[0] ** 2 + v[1] ** 2 + v[2] ** 2 > 1e-6
    ),
)
# Tangent in exact arithmetic to the 45-degree cone, at a point on a theta
# half-plane (y = x all along, z = 0 there), with the direction 0.06 degrees
# off the cone (|a| = 0.0019): a 2e-6 detour through the cell above that the
# oracle finds. The trace found it or not by numpy's tan(pi/4) (numpy 1.24 gave
# 1.0) before the edges' tangents came from math.tan. Its ends are 3.7e-7 from
# the oracle's, more than the plain tangent tolerance (3.1e-7 here): hence the
# distances' own tolerance.
@example(name="log_full", origin=(0.25, 0.25, 0.25), direction=(0.25, 0.25, -0.015625))
# The same kind of tangency: the trace dips 2.5 sqrt(eps) L into the cell
# above, the oracle 1.9 sqrt(eps) L, on either side of a threshold of 2. Such
# a sliver may show or not up to 4 sqrt(eps) L (``UNRESOLVED_TANGENT``, the
# contract in docs/geometry.md): slivers are dropped at that.
@example(name="thin_shell", origin=(0.625, 0.625, 1.0), direction=(0.625, 0.625, -0.1875))
# Tangent to the 45-degree cone at (6, 6, 0), on the theta = 90 degree
# half-plane, 0.8 degrees off the cone's generatrix (|a| = 0.014): the trace
# dips into the band above for two slivers of 7.6e-7 (a corner on the way),
# the oracle not at all. That is 4.6 sqrt(eps) L, under the contract's
# 4 sqrt(eps / |a|) L for a ray this near a generatrix: so the slivers'
# tolerance grows by ``_along_a_cone`` as the distances' does.
@example(name="log_full", origin=(0.0, 0.0, -1.0), direction=(0.75, 0.75, 0.125))
def test_property_any_ray_matches_oracle(name, origin, direction):
    # Hypothesis favours round numbers and zeros: axis-aligned rays, rays
    # through the origin and along the y axis come up far more than at random,
    # and so do exact tangencies, hence the tangent-sliver tolerance -- relative to
    # the whole scene: a far origin makes the quadratics' coefficients larger and
    # their rounding with them -- and the distances more along a cone
    # (``_along_a_cone``).
    grid = GRIDS[name]()
    result = lt.trace(grid, origin, direction)
    scene = grid.rho_max + float(np.linalg.norm(origin))
    along = _along_a_cone(grid, direction)
    assert_matches_oracle(grid, origin, direction, result, rel=UNRESOLVED_TANGENT * along,
                          scale=scene, rel_distances=TANGENT_SLIVER * along)


@pytest.mark.parametrize("chunk_segments, margin", [(1 << 18, 1.25), (600, 1.25), (600, 0.02)])
def test_every_parallel_path_equals_the_serial_one(monkeypatch, chunk_segments, margin):
    # Ordered chunks placed by the threads that traced them: with 600 segments
    # a chunk is a single ray, so thousands of chunks pass their starts on;
    # with a reservation of 2% of the bounds the output runs out of room many
    # times, keeps the rows placed and grows. The first 256 rays miss the grid.
    from logsph_trace import _batching, _validate

    monkeypatch.setattr(_batching, "ORDERED_SEGMENTS", chunk_segments)
    monkeypatch.setattr(_batching, "RESERVE_MARGIN", margin)
    grid = GRIDS["log_full"]()
    rng = np.random.default_rng(41)
    origins, directions = random_rays(rng, grid, 6000)
    origins[:256] = [0.0, 0.0, 100.0]
    directions[:256] = [0.0, 0.0, 1.0]
    serial = lt.trace_many(grid, origins, directions, parallel=False)
    o, d = _validate.rays(origins, directions)
    far = np.full(len(o), np.inf)
    results = [
        lt.trace_many(grid, origins, directions, parallel=True),
        _batching.run_exact_ordered(grid, o[::-1].copy(), d[::-1].copy(), far, workers=3),
        _batching.run_exact_ordered(grid, o, d, far, workers=5),
        _batching.run_exact_ordered(grid, o, d, far, workers=1),
    ]
    reversed_serial = lt.trace_many(grid, origins[::-1], directions[::-1], parallel=False)
    for result, want in zip(results, [serial, reversed_serial, serial, serial]):
        for name in ("offsets", "cells", "t_enter", "t_exit"):
            np.testing.assert_array_equal(getattr(result, name), getattr(want, name))
            # The ordered path's arrays own exactly their data: no spare room kept
            # alive.
            assert result is results[0] or getattr(result, name).base is None


@pytest.mark.parametrize("kind", ["centre", "y_axis", "sphere_tangent", "phi_turn", "corner"])
def test_ordered_chunks_equal_the_serial_pass_on_near_singular_rays(monkeypatch, kind):
    # Rays through or a hair (1e-15 .. 1e-3 of the scene) beside the centre,
    # the y axis, tangents and corners, from random eyes, in ordered chunks of
    # a few rays each on 3 workers.
    from singular import CLASSES, singular_rays

    from logsph_trace import _batching, _validate

    monkeypatch.setattr(_batching, "ORDERED_SEGMENTS", 2000)
    grid = GRIDS["log_full"]()
    rng = np.random.default_rng(CLASSES.index(kind) + 313)
    origins, directions, _ = singular_rays(rng, grid, kind, 100)
    serial = lt.trace_many(grid, origins, directions, parallel=False)
    o, d = _validate.rays(origins, directions)
    ordered = _batching.run_exact_ordered(grid, o, d, np.full(len(o), np.inf), workers=3)
    for name in ("offsets", "cells", "t_enter", "t_exit"):
        np.testing.assert_array_equal(getattr(ordered, name), getattr(serial, name))
