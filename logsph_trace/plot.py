"""Plots of grids and traces (matplotlib, imported only when a plot is made).

The four panels of the paper's Fig. 3 are :func:`plot_scene`,
:func:`plot_rho_phi`, :func:`plot_index_boxes` and :func:`plot_cells`;
:func:`trace_figure` puts them together.
"""

import numpy as np

from .grid import spherical_to_cartesian


def _pyplot():
    try:
        import matplotlib.pyplot as plt
    except ImportError:  # pragma: no cover - depends on the environment
        raise ImportError(
            "logsph_trace.plot needs matplotlib: pip install 'logsph_trace[plot]'"
        ) from None
    return plt


def _axes(ax, three_d=False):
    if ax is not None:
        return ax
    plt = _pyplot()
    fig = plt.figure()
    return fig.add_subplot(projection="3d") if three_d else fig.add_subplot()


def _ray(origin, direction):
    origin = np.asarray(origin, dtype=np.float64)
    direction = np.asarray(direction, dtype=np.float64)
    return origin, direction / np.linalg.norm(direction)


def _ray_extent(grid, origin, direction, trace):
    if trace is not None and len(trace):
        return float(trace.t_exit[-1]) * 1.05
    return 2.0 * grid.rho_max + float(np.linalg.norm(origin))


def plot_scene(grid, origin, direction, t_max=None, trace=None, ax=None, unit="m"):
    """Panel (a): the Cartesian scene -- the robot at the origin, the person, the gaze ray.

    Parameters
    ----------
    grid : Grid
    origin, direction : array_like, shape (3,)
    t_max : float, optional
        Length of the ray drawn; by default up to the trace's last exit.
    trace : Trace, optional
    ax : mpl_toolkits.mplot3d.Axes3D, optional
    unit : str
        The grid's length unit, for the axis labels.
    """
    ax = _axes(ax, three_d=True)
    origin, direction = _ray(origin, direction)
    t_max = _ray_extent(grid, origin, direction, trace) if t_max is None else t_max
    line = origin + np.linspace(0.0, t_max, 2)[:, None] * direction
    ax.plot(line[:, 0], line[:, 2], line[:, 1], "k--", label="gaze ray")
    ax.scatter([0], [0], [0], color="tab:orange", s=60, label="robot")
    ax.scatter([origin[0]], [origin[2]], [origin[1]], color="tab:green", s=60, label="person")
    # The outer sphere as a wireframe, to show the bounded region.
    u, v = np.meshgrid(np.linspace(-np.pi, np.pi, 25), np.linspace(-np.pi / 2, np.pi / 2, 13))
    outer = np.stack([np.full(u.size, grid.rho_max), u.ravel(), v.ravel()], 1)
    shell = spherical_to_cartesian(outer)
    ax.plot_wireframe(shell[:, 0].reshape(u.shape), shell[:, 2].reshape(u.shape),
                      shell[:, 1].reshape(u.shape), color="0.8", linewidth=0.4)
    ax.set_xlabel(f"x ({unit})")
    ax.set_ylabel(f"z ({unit})")
    ax.set_zlabel(f"y ({unit}, up)")
    ax.legend(fontsize=7, loc="upper left")
    return ax


def plot_rho_phi(grid, origin, direction, t_max=None, trace=None, ax=None, unit="m"):
    """Panel (b): the ray in the rho-phi plane over the grid's boundaries (log-spaced rho)."""
    return _plot_rho_angle(grid, origin, direction, t_max, trace, ax, "phi", unit)


def plot_rho_theta(grid, origin, direction, t_max=None, trace=None, ax=None, unit="m"):
    """Draw the ray in the rho-theta plane over the grid's boundaries."""
    return _plot_rho_angle(grid, origin, direction, t_max, trace, ax, "theta", unit)


def _plot_rho_angle(grid, origin, direction, t_max, trace, ax, axis, unit="m"):
    ax = _axes(ax)
    origin, direction = _ray(origin, direction)
    t_max = _ray_extent(grid, origin, direction, trace) if t_max is None else t_max
    points = origin + np.linspace(0.0, t_max, 2000)[:, None] * direction
    rho = np.linalg.norm(points, axis=1)
    if axis == "phi":
        angle = np.arctan2(points[:, 1], np.hypot(points[:, 0], points[:, 2]))
        edges = grid.phi_edges
    else:
        angle = np.arctan2(points[:, 0] + 0.0, points[:, 2] + 0.0)
        angle = grid.theta_edges[0] + np.mod(angle - grid.theta_edges[0], 2 * np.pi)
        edges = grid.theta_edges
    for value in grid.rho_edges:
        ax.axvline(value, color="0.6", linestyle="--", linewidth=0.6)
    for value in edges:
        ax.axhline(np.degrees(value), color="0.8", linestyle=":", linewidth=0.6)
    ax.plot(rho, np.degrees(angle), color="k", label="gaze ray")
    if trace is not None and len(trace):
        hits = origin + trace.t_enter[:, None] * direction
        hit_rho = np.linalg.norm(hits, axis=1)
        if axis == "phi":
            hit_angle = np.arctan2(hits[:, 1], np.hypot(hits[:, 0], hits[:, 2]))
        else:
            hit_angle = np.arctan2(hits[:, 0] + 0.0, hits[:, 2] + 0.0)
            hit_angle = grid.theta_edges[0] + np.mod(hit_angle - grid.theta_edges[0], 2 * np.pi)
        ax.plot(hit_rho, np.degrees(hit_angle), "r.", label="cell entries")
    ax.set_xlabel(f"rho ({unit})")
    ax.set_ylabel(f"{axis} (deg)")
    ax.set_xlim(0.0, grid.rho_max * 1.05)
    low, high = np.degrees(angle.min()), np.degrees(angle.max())
    margin = max(5.0, 0.15 * (high - low))
    ax.set_ylim(low - margin, high + margin)
    ax.legend(fontsize=7)
    return ax


def plot_index_boxes(trace, ax=None, color="tab:red"):
    """Panel (c): the traversed cells as unit boxes at their (i, j, k) indices."""
    ax = _axes(ax, three_d=True)
    cells = np.asarray(trace.unique())
    if cells.size == 0:
        return ax
    low = cells.min(axis=0)
    shape = cells.max(axis=0) - low + 1
    filled = np.zeros(shape, dtype=bool)
    filled[tuple((cells - low).T)] = True
    x, y, z = np.indices(shape + 1)
    ax.voxels(x + low[0], y + low[1], z + low[2], filled, facecolors=color, edgecolors="k",
              alpha=0.6, linewidth=0.4)
    ax.set_xlabel("i (rho)")
    ax.set_ylabel("j (theta)")
    ax.set_zlabel("k (phi)")
    return ax


def cell_corners(grid, cell):
    """Return the 8 corners (Cartesian) of a cell: every (rho, theta, phi) bound combination."""
    bounds = grid.cell_bounds(np.asarray(cell))
    combos = np.array([[r, t, p] for r in bounds[0:2] for t in bounds[2:4] for p in bounds[4:6]])
    return spherical_to_cartesian(combos)


def plot_cells(grid, cells, ax=None, color="tab:red", alpha=0.25):
    """Panel (d): cells as trapezoid volumes in Cartesian space (faces flattened to quads)."""
    from mpl_toolkits.mplot3d.art3d import Poly3DCollection

    ax = _axes(ax, three_d=True)
    cells = np.atleast_2d(np.asarray(cells))
    # Corner index = 4 * rho_bit + 2 * theta_bit + phi_bit; the six faces of a cell.
    faces = [(0, 1, 3, 2), (4, 5, 7, 6), (0, 1, 5, 4), (2, 3, 7, 6), (0, 2, 6, 4), (1, 3, 7, 5)]
    polygons = []
    for cell in cells:
        corners = cell_corners(grid, cell)[:, [0, 2, 1]]  # draw with y (up) vertical
        polygons.extend([corners[list(face)] for face in faces])
    if polygons:
        ax.add_collection3d(Poly3DCollection(polygons, facecolors=color, edgecolors="k",
                                             linewidths=0.2, alpha=alpha))
        every = np.concatenate(polygons)
        ax.auto_scale_xyz(every[:, 0], every[:, 1], every[:, 2])
    return ax


def trace_figure(grid, origin, direction, trace, title=None, unit="m"):
    """Draw the four panels of the paper's Fig. 3 for one traced ray; return the Figure.

    ``unit`` is the grid's length unit, for the axis labels (the paper's
    worked example is in decimetres).
    """
    plt = _pyplot()
    fig = plt.figure(figsize=(12, 10))
    ax_a = fig.add_subplot(2, 2, 1, projection="3d")
    plot_scene(grid, origin, direction, trace=trace, ax=ax_a, unit=unit)
    ax_a.set_title("(a) scene: robot, person, gaze ray")
    ax_b = fig.add_subplot(2, 2, 2)
    plot_rho_phi(grid, origin, direction, trace=trace, ax=ax_b, unit=unit)
    ax_b.set_title("(b) the ray in the rho-phi plane")
    ax_c = fig.add_subplot(2, 2, 3, projection="3d")
    plot_index_boxes(trace, ax=ax_c)
    ax_c.set_title("(c) traversed cells by index (i, j, k)")
    ax_d = fig.add_subplot(2, 2, 4, projection="3d")
    plot_scene(grid, origin, direction, trace=trace, ax=ax_d, unit=unit)
    plot_cells(grid, trace.unique(), ax=ax_d)
    ax_d.set_title("(d) the cells as volumes over the scene")
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    return fig


def plot_heatmap(grid, values, ax=None, reduce="max", cmap="magma", label=None):
    """Draw a map over the grid (occupancy, fixation) as a heat map over theta and phi.

    Parameters
    ----------
    grid : Grid
    values : array_like, shape ``grid.shape``
        E.g. ``OccupancyGrid.probability`` or ``fixation_probability(..., dense=True)``.
    reduce : {"max", "sum", "mean"}
        How the radial cells of each direction are combined.
    ax : matplotlib.axes.Axes, optional
    label : str, optional
        Colour-bar label.

    Returns
    -------
    matplotlib.axes.Axes
    """
    values = np.asarray(values, dtype=np.float64)
    if values.shape != grid.shape:
        raise ValueError(f"values must have the grid's shape {grid.shape}, got {values.shape}")
    reducers = {"max": np.max, "sum": np.sum, "mean": np.mean}
    if reduce not in reducers:
        raise ValueError(f"reduce must be one of {tuple(reducers)}, got {reduce!r}")
    ax = _axes(ax)
    image = reducers[reduce](values, axis=0)  # (n_theta, n_phi)
    mesh = ax.pcolormesh(np.degrees(grid.theta_edges), np.degrees(grid.phi_edges), image.T,
                         cmap=cmap, shading="flat")
    ax.figure.colorbar(mesh, ax=ax, label=label or f"{reduce} over rho")
    ax.set_xlabel("theta (deg)")
    ax.set_ylabel("phi (deg)")
    return ax
