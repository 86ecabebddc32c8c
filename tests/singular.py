"""Rays aimed at the singular sets of a log-spherical grid, from random (not round) eyes.

Along a line, rho, theta and phi are smooth except on a few sets; a ray that
passes through or near one of them is where rounding decides the answer:

* ``centre``: the line meets (or nearly meets) the grid's centre; phi jumps to
  the opposite elevation and theta by half a turn there.
* ``y_axis``: the line meets the y axis; theta jumps by half a turn.
* ``sphere_tangent``: the line grazes a radial sphere.
* ``phi_turn``: phi turns back exactly on an elevation cone (the line is
  tangent to the cone, away from its generatrix).
* ``corner``: the line passes through a point where a sphere, a half-plane
  and a cone meet.

Each ray is built exactly on its set and then moved off it by ``offset``
times the scene's size, perpendicular to the line (for tangents, along the
surface's normal), so both the singular case and its near misses are drawn.
The eye is drawn at random in a box 1.3x the region, so no input is round.
"""

import numpy as np

CLASSES = ("centre", "y_axis", "sphere_tangent", "phi_turn", "corner")
OFFSETS = (0.0, 1e-15, 1e-12, 1e-9, 1e-6, 1e-3)


def _unit(vector):
    return vector / np.linalg.norm(vector)


def _perpendicular(rng, direction):
    """A random unit vector perpendicular to ``direction``."""
    other = np.cross(direction, rng.normal(size=3))
    return _unit(other)


def _random_eye(rng, grid):
    reach = 1.3 * grid.rho_max
    return rng.uniform(-reach, reach, 3)


def unit_at(phi, theta):
    """The unit vector of elevation ``phi`` and azimuth ``theta`` (docs/geometry.md's frame)."""
    return np.array([np.cos(phi) * np.sin(theta), np.sin(phi), np.cos(phi) * np.cos(theta)])


def _interior(rng, edges):
    """An edge of the grid chosen at random, interior ones preferred."""
    if len(edges) > 2 and rng.random() < 0.8:
        return edges[rng.integers(1, len(edges) - 1)]
    return edges[rng.integers(0, len(edges))]


def _on_sphere_of_edges(rng, grid):
    """A point on a cell corner: rho edge, theta edge and phi edge all at once."""
    rho = _interior(rng, grid.rho_edges)
    if rho == 0.0:
        rho = grid.rho_edges[1]
    theta = _interior(rng, grid.theta_edges)
    phi = _interior(rng, grid.phi_edges)
    return rho * unit_at(phi, theta)


def aim(rng, grid, kind, offset, eye):
    """A point of set ``kind`` (``centre``, ``y_axis`` or ``corner``) seen from ``eye``,
    moved ``offset`` x rho_max off it, perpendicular to the line of sight."""
    if kind == "centre":
        target = np.zeros(3)
    elif kind == "y_axis":
        target = np.array([0.0, rng.uniform(-grid.rho_max, grid.rho_max), 0.0])
    elif kind == "corner":
        target = _on_sphere_of_edges(rng, grid)
    else:
        raise ValueError(f"{kind!r} is not a point set")
    sight = target - eye
    if not np.any(sight):
        sight = rng.normal(size=3)
    return target + offset * grid.rho_max * _perpendicular(rng, sight)


def singular_ray(rng, grid, kind, offset):
    """One ray (origin, direction) of class ``kind``, moved ``offset`` x rho_max off its set."""
    scale = grid.rho_max
    shift = offset * scale
    if kind in ("centre", "y_axis", "corner"):
        eye = _random_eye(rng, grid)
        return eye, aim(rng, grid, kind, offset, eye) - eye
    if kind == "sphere_tangent":
        radius = _interior(rng, grid.rho_edges)
        if radius == 0.0:
            radius = grid.rho_edges[1]
        normal = _unit(rng.normal(size=3))
        direction = _perpendicular(rng, normal)
        touch = (radius + shift * rng.choice([-1.0, 1.0])) * normal
        return touch - rng.uniform(0.2, 1.5) * scale * direction, direction
    if kind == "phi_turn":
        phi = _interior(rng, grid.phi_edges)
        phi = float(np.clip(phi, -1.5, 1.5))  # the cone, not the y axis itself
        theta = rng.uniform(-np.pi, np.pi)
        if grid.rho_min > 0:
            rho = rng.uniform(grid.rho_min, grid.rho_max)
        else:
            rho = rng.uniform(0.1, 1.0) * grid.rho_max
        generatrix = unit_at(phi, theta)
        across = np.array([np.cos(theta), 0.0, -np.sin(theta)])  # horizontal tangent
        normal = np.cross(generatrix, across)
        # Tangent to the cone at the touch point, within 1 rad of the horizontal.
        beta = rng.uniform(-1.0, 1.0)
        direction = np.cos(beta) * across + np.sin(beta) * generatrix
        touch = rho * generatrix + shift * rng.choice([-1.0, 1.0]) * normal
        return touch - rng.uniform(0.2, 1.5) * scale * direction, direction
    raise ValueError(f"unknown singular class {kind!r}")


def singular_rays(rng, grid, kind, n_rays, offsets=OFFSETS):
    """``n_rays`` rays of class ``kind`` per offset: (origins, directions, offsets) arrays."""
    origins, directions, used = [], [], []
    for offset in offsets:
        for _ in range(n_rays):
            origin, direction = singular_ray(rng, grid, kind, offset)
            origins.append(origin)
            directions.append(direction)
            used.append(offset)
    return np.array(origins), np.array(directions), np.array(used)


# ---- Rays lying in faces ---------------------------------------------------
# A line through the centre lies on the cone of its elevation and in the
# vertical plane of its azimuth; when those are edges, the line runs along a
# face of the grid (past the centre, along the opposite face). A line through
# the y axis lies in the plane of its azimuth. Lines of these kinds are built
# exactly, as far as floats allow, from power-of-two multiples of unit vectors
# along the grid's edges, where the normalised direction is often collinear
# with the eye to the last bit (o x d == 0) and otherwise within a few ulps.

FACE_FAMILIES = ("own_ray", "near_own_ray", "across_the_axis", "edge_directions", "off_own_ray",
                 "beside_the_axis")


def edge_unit(rng, grid, on_edge=0.6):
    """A unit vector whose elevation and azimuth are each a grid edge with
    probability ``on_edge``, and otherwise random in the grid's ranges."""
    phi = rng.uniform(*grid.phi_range)
    if rng.random() < on_edge:
        phi = grid.phi_edges[rng.integers(0, grid.phi_edges.shape[0])]
    theta = rng.uniform(*grid.theta_range)
    if rng.random() < on_edge:
        theta = grid.theta_edges[rng.integers(0, grid.theta_edges.shape[0])]
    return unit_at(phi, theta)


def face_ray(rng, grid, family):
    """One ray (origin, direction) of ``family`` (``FACE_FAMILIES``).

    ``own_ray``: the eye at a power of two times an edge unit vector (in the
    egocentric gap or out to past rho_max), looking along that vector's line,
    away from the centre or through it. ``near_own_ray``: the same, through
    the centre, tilted by 1e-17 ... 1e-13 rad. ``across_the_axis``: the eye
    as in ``own_ray``, looking across the y axis in its own vertical plane.
    ``edge_directions``: an eye anywhere along an edge unit vector, looking
    along another one. ``off_own_ray``: the eye as in ``own_ray``, looking
    along its own line, through the centre or away from it, tilted by
    1e-13 ... 1e-8 rad: beyond rounding, but near enough that a crossing of
    the eye's own cone, at eps |o| / tilt, is rounded by more than the
    trace's slack. ``beside_the_axis``: the eye 1e-17 ... 1e-12 of its height
    from the y axis, on a half-plane, looking across the axis in that
    half-plane's vertical plane (half the time tilted off it by 1e-16 ...
    1e-9 rad): the line meets the axis, or passes it on a side its inputs
    tell, near the eye. The directions are left unnormalised.
    """
    unit = edge_unit(rng, grid)
    inner = grid.rho_min if grid.rho_min > 0.0 else grid.rho_edges[1]
    eye = 2.0 ** (np.floor(np.log2(inner)) + rng.integers(-3, 5)) * unit
    # Directions are differences of points, as a sensor's are: rounding
    # leaves them off the exact line by a few ulps as often as not.
    reach = rng.uniform(0.2, 1.3) * grid.rho_max * rng.choice([-1.0, 1.0])
    if family == "own_ray":
        return eye, (eye + reach * unit) - eye
    if family == "near_own_ray":
        tilt = rng.normal(size=3) * 10.0 ** -rng.integers(13, 18)
        return eye, (eye - abs(reach) * (unit + tilt)) - eye
    if family == "across_the_axis":
        target = np.array([-eye[0], rng.normal() * np.linalg.norm(eye), -eye[2]])
        return eye, (eye + abs(reach) * target) - eye
    if family == "edge_directions":
        eye = rng.uniform(0.05, 1.3) * grid.rho_max * edge_unit(rng, grid, 0.8)
        return eye, (eye + reach * edge_unit(rng, grid, 0.8)) - eye
    if family == "off_own_ray":
        across = np.cross(unit, rng.normal(size=3))
        tilt = 10.0 ** rng.uniform(-13.0, -8.0) * across / np.linalg.norm(across)
        return eye, (eye + reach * (unit + tilt)) - eye
    if family == "beside_the_axis":
        theta = grid.theta_edges[rng.integers(0, grid.theta_edges.shape[0])]
        side = np.array([np.sin(theta), 0.0, np.cos(theta)])
        height = rng.uniform(-1.3, 1.3) * grid.rho_max
        eye = np.array([0.0, height, 0.0]) + 10.0 ** rng.uniform(-17.0, -12.0) * abs(height) * side
        target = np.array([0.0, rng.uniform(-1.3, 1.3) * grid.rho_max, 0.0]) - abs(reach) * side
        direction = target - eye
        if rng.random() < 0.5:
            across = np.cross(direction, rng.normal(size=3))
            direction = direction + (10.0 ** rng.uniform(-16.0, -9.0) * np.linalg.norm(direction)
                                     / np.linalg.norm(across)) * across
        return eye, direction
    raise ValueError(f"unknown face family {family!r}")


def face_rays(rng, grid, family, n_rays):
    """``n_rays`` rays of ``family``: (origins, directions) arrays."""
    rays = [face_ray(rng, grid, family) for _ in range(n_rays)]
    return np.array([o for o, _ in rays]), np.array([d for _, d in rays])
