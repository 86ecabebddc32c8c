"""bench.integrate_kernels' timers: they see every kernel, change no result, and undo themselves."""

import numpy as np
import pytest

import logsph_trace as lt
from bench.integrate_kernels import MODULES, kernel_timers
from logsph_trace import occupancy as occupancy_module

GRID = dict(rho_min=0.3, rho_max=6.0, n_rho=24, n_theta=72, n_phi=36)


def _points(rng, n):
    """End points of rays in every direction, 0.5 to 5 from the centre."""
    directions = rng.normal(size=(n, 3))
    directions /= np.linalg.norm(directions, axis=1)[:, None]
    return directions * rng.uniform(0.5, 5.0, size=(n, 1))


@pytest.mark.parametrize("sensor, parts", [
    ((0.0, 0.0, 0.0), {"mark_radial", "apply_radial"}),
    # Off the centre with enough rays: the coherent scan, each walk by name.
    ((0.061, 0.079, -0.013), {"ray_extent", "bin_rays", "mark_scan (samples)", "mark_scan (others)",
                              "ray_cone", "columns_in_view", "near_masks",
                              "mark_candidates", "apply_scan"}),
])
def test_timed_scan_is_the_scan_with_every_kernel_named(sensor, parts):
    rng = np.random.default_rng(7)
    points = _points(rng, occupancy_module.COHERENT_MIN_RAYS + 1_000)
    grid = lt.Grid(**GRID)
    plain, timed = lt.OccupancyGrid(grid), lt.OccupancyGrid(grid)
    plain.integrate(points, sensor)
    times = {}
    with kernel_timers(times):
        timed.integrate(points, sensor)
    assert parts | {"check: vectors", "check: point", "check: choice"} == set(times)
    assert all(ms > 0.0 for ms in times.values())
    np.testing.assert_array_equal(plain.log_odds, timed.log_odds)


def test_a_few_rays_off_the_centre_are_walked_whole():
    grid = lt.Grid(**GRID)
    times = {}
    with kernel_timers(times):
        lt.OccupancyGrid(grid).integrate(_points(np.random.default_rng(8), 500), (0.05, 0, 0))
    assert "mark_scan (all)" in times and "bin_rays" not in times


def test_the_timers_are_taken_off_after_an_error():
    before = [getattr(occupancy_module, name) for name in MODULES]
    with pytest.raises(ValueError, match="finite"):
        with kernel_timers({}):
            lt.OccupancyGrid(lt.Grid(**GRID)).integrate([[np.nan, 1.0, 1.0]], (0, 0, 0))
    assert [getattr(occupancy_module, name) for name in MODULES] == before
