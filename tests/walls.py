"""Sources on the grid's vertices and faces, rays along, across and all but along
the faces, at every scale: the cases radiative-transfer codes test their
spherical grids with (sources on every vertex, rays along walls, edge-on
viewing angles whose ``cos(pi / 2)`` is 6e-17, radii from 1e-20 to 1e20).

Every number is drawn at random or built from the grid's own edges, so no
case is round. A case is a source, a direction, and ``kind``: ``"along"``
for a direction that lies in a face through the source to within ~1e-12 rad
(the ray lies in the face, so the cells on both sides are right and the
closure rule decides), anything else for one held to the oracle cell by cell.
"""

import sys

import numpy as np
from oracle import UNRESOLVED_TANGENT, compare, oracle_trace, within_faces

import logsph_trace as lt

# Scales the same cases are traced at: every one is multiplied into the
# grid's radii and the sources, so the cells crossed are the same.
SCALES = (1e-20, 1e-10, 1.0, 1e10, 1e20)
# Tilts off a face, in radians: below, at and above float64's resolution.
TILTS = (1e-17, 6.123233995736766e-17, 1e-15, 1e-12)


def unit_at(phi, theta):
    """The unit vector of elevation ``phi`` and azimuth ``theta``."""
    return np.array([np.cos(phi) * np.sin(theta), np.sin(phi), np.cos(phi) * np.cos(theta)])


def _wide_bins():
    """Few, wide azimuth bins whose edges are round angles stored rounded
    (-pi/2 is 6.1e-17 rad off the true plane) and Hyperion's 16 elevation bands."""
    return lt.Grid.from_edges([0.0, 1.0], [-np.pi, -np.pi / 2, np.pi / 4, np.pi],
                              np.linspace(-np.pi / 2, np.pi / 2, 17))


def _polar_caps():
    """Narrow caps at both poles and a cone 3e-4 rad from the plane."""
    return lt.Grid.from_edges(np.geomspace(0.41, 7.3, 4), np.linspace(0.0, 2 * np.pi, 6),
                              [-np.pi / 2, -1.49, -0.37, 3.1e-4, 0.83, 1.53, np.pi / 2])


WALL_GRIDS = {
    "log": lambda: lt.Grid(0.37, 9.3, 4, 7, 5),
    "uniform_from_centre": lambda: lt.Grid(0.0, 4.1, 3, 6, 4, spacing="uniform"),
    "wide_azimuth_bins": _wide_bins,
    "polar_caps": _polar_caps,
    "partial_wedge": lambda: lt.Grid(0.52, 3.7, 3, 5, 3, theta_range=(-2.3, 1.9),
                                     phi_range=(-0.7, 1.1)),
}


def scaled(grid, scale):
    """The same grid with its radii multiplied by ``scale``."""
    return lt.Grid.from_edges(grid.rho_edges * scale, grid.theta_edges, grid.phi_edges)


def _radii(grid, rng):
    """Every radial edge (the centre once) and a random radius inside each shell."""
    edges = grid.rho_edges
    inner = edges[:-1] + rng.uniform(0.2, 0.8, edges.size - 1) * np.diff(edges)
    return np.concatenate([edges, inner])


def _between(rng, edges):
    """A random angle inside each cell of an angular axis."""
    return edges[:-1] + rng.uniform(0.2, 0.8, edges.size - 1) * np.diff(edges)


def sources(grid, rng):
    """(points, faces): every vertex of the grid, the centre and points on the
    y axis, and a random point on every face. ``faces[n]`` lists, for point n,
    the faces through it as ``(family, edge)`` with family ``"theta"`` or
    ``"phi"`` (spheres are smooth: a ray along one is a tangent, held to the
    oracle)."""
    points, faces = [np.zeros(3)], [[]]
    radii = _radii(grid, rng)
    for rho in radii[radii > 0.0]:
        for theta in np.concatenate([grid.theta_edges, _between(rng, grid.theta_edges)]):
            on_theta = theta in grid.theta_edges
            for phi in np.concatenate([grid.phi_edges, _between(rng, grid.phi_edges)]):
                if abs(phi) == np.pi / 2:
                    continue  # the y axis, below
                on = [("theta", theta)] if on_theta else []
                if phi in grid.phi_edges:
                    on.append(("phi", phi))
                points.append(rho * unit_at(phi, theta))
                faces.append(on)
        for sign in (1.0, -1.0):
            points.append(np.array([0.0, sign * rho, 0.0]))
            faces.append([])
    return np.array(points), faces


def _tilted(rng, along, normal, tilt):
    """``along`` turned by ``tilt`` rad towards ``normal`` (one side or the other)."""
    sign = rng.choice([-1.0, 1.0])
    return np.cos(tilt) * along + sign * np.sin(tilt) * normal


def _face_frame(point, family, edge):
    """(two unit vectors spanning the face's tangent plane at ``point``, its normal)."""
    if family == "theta":
        in_plane = np.array([np.sin(edge), 0.0, np.cos(edge)])
        up = np.array([0.0, 1.0, 0.0])
        normal = np.array([np.cos(edge), 0.0, -np.sin(edge)])
        return in_plane, up, normal
    theta = np.arctan2(point[0], point[2])
    generatrix = unit_at(edge, theta)
    around = np.array([np.cos(theta), 0.0, -np.sin(theta)])
    normal = unit_at(edge + np.pi / 2, theta)
    return generatrix, around, normal


def directions(point, faces, rng, n_random=2):
    """(directions, kinds) for one source: along each face through it (the
    face's own lines and random ones in its tangent plane), tilted off it by
    ``TILTS``, across it, edge-on ones whose zero components are 6e-17, and
    random ones."""
    out, kinds = [], []
    for family, edge in faces:
        first, second, normal = _face_frame(point, family, edge)
        mixed = np.cos(a := rng.uniform(0, 2 * np.pi)) * first + np.sin(a) * second
        for n, along in enumerate((first, -first, second, -second, mixed)):
            # A half-plane holds every line of its plane; a cone only its generatrix,
            # and the rest of its tangent plane touches it at the source.
            lies_in = family == "theta" or n < 2
            for tilt in (0.0,) + TILTS:
                out.append(_tilted(rng, along, normal, tilt))
                kinds.append("along" if lies_in else "tangent")
        out += [normal, -normal]
        kinds += ["across", "across"]
    # Edge-on: an observer at inclination pi/2 sees along x or z with a
    # cos(pi/2) = 6.1e-17 part, not a zero.
    edge_on = np.cos(np.pi / 2)
    for view in rng.uniform(0, 2 * np.pi, 2):
        out.append(np.array([np.sin(view), edge_on, np.cos(view)]))
        kinds.append("edge_on")
    # Along a Cartesian axis with the other parts 0 or a random 1e-17 to 1e-16:
    # a source built on an axis looking along another lies within rounding of
    # the half-planes at multiples of pi/2, whose stored edges are not.
    for axis in range(3):
        for sign in (1.0, -1.0):
            direction = rng.choice([-1.0, 1.0], 3) * 10.0 ** rng.uniform(-17, -16, 3)
            direction[rng.integers(0, 3)] = 0.0
            direction[axis] = sign
            out.append(direction)
            kinds.append("axis")
    out += list(rng.normal(size=(n_random, 3)))
    kinds += ["random"] * n_random
    return np.array(out), kinds


def cases(grid, seed):
    """(origins, directions, kinds) of every source of ``grid`` and its directions."""
    rng = np.random.default_rng(seed)
    points, faces = sources(grid, rng)
    # The same sources with their parts below 1e-15 of their size set to 0, as
    # a source built in Cartesian coordinates has them: (-0.5, 0.3, 0.0), not
    # ``cos(-pi / 2)``'s 6e-17 for z.
    snapped = np.where(np.abs(points) < 1e-15 * np.abs(points).max(axis=1)[:, None], 0.0, points)
    moved = np.any(snapped != points, axis=1)
    points = np.concatenate([points, snapped[moved]])
    faces = faces + [f for f, m in zip(faces, moved) if m]
    origins, dirs, kinds = [], [], []
    for point, on in zip(points, faces):
        d, k = directions(point, on, rng)
        origins += [point] * len(d)
        dirs.append(d)
        kinds += k
    return np.array(origins), np.concatenate(dirs), kinds


def wrong_rays(grid, origins, directions, kinds):
    """A message for each ray ``lt.trace_many`` gets wrong (see ``test_walls.py``)."""
    traces = lt.trace_many(grid, origins, directions)
    units = directions / np.linalg.norm(directions, axis=1)[:, None]
    mids = np.concatenate([origins[r] + 0.5 * (t.t_enter + t.t_exit)[:, None] * units[r]
                           for r, t in enumerate(traces)])
    looked_up = grid.cell_of(mids)
    rows = np.repeat(np.arange(len(traces)), [len(t.cells) for t in traces])
    elsewhere = set(rows[np.any(looked_up != np.concatenate([t.cells for t in traces]), axis=1)])
    failures = []
    for row, trace in enumerate(traces):
        got = (trace.cells, trace.t_enter, trace.t_exit)
        scale = grid.rho_max + float(np.linalg.norm(origins[row]))
        want = oracle_trace(origins[row], directions[row], grid.rho_edges, grid.theta_edges,
                            grid.phi_edges)
        agrees = compare(got, want, scale) is None or (
            kinds[row] == "tangent" and compare(got, want, scale, UNRESOLVED_TANGENT) is None)
        if agrees and row not in elsewhere:
            continue
        message = within_faces(got, origins[row], units[row], grid.rho_edges, grid.theta_edges,
                               grid.phi_edges, scale)
        if message is not None:
            failures.append(f"{kinds[row]} origin={origins[row].tolist()} "
                            f"direction={directions[row].tolist()}: {message}")
    return failures


if __name__ == "__main__":
    # Every case of every grid at every scale (a few minutes): the rays wrong, per scale.
    for name, make in WALL_GRIDS.items():
        points, towards, labels = cases(make(), seed=sorted(WALL_GRIDS).index(name))
        for factor in SCALES:
            wrong = wrong_rays(scaled(make(), factor), points * factor, towards, labels)
            print(f"{name}, scale {factor:g}: {len(wrong)} of {len(points)} rays wrong")
            if wrong:
                print("  first:", wrong[0])
                sys.exit(1)
