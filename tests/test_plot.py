"""The plots draw without error and put the right things on the axes (Agg backend)."""

import numpy as np
import pytest

import logsph_trace as lt

matplotlib = pytest.importorskip("matplotlib")
matplotlib.use("Agg")


def test_trace_figure_has_four_panels_and_one_volume_per_cell():
    from logsph_trace.plot import trace_figure

    grid = lt.Grid.from_increments(10.0, 80.0, 10, d_theta=10.0, d_phi=10.0)
    result = lt.trace(grid, [0, 20, 20], [-0.3, -0.01, 0])
    fig = trace_figure(grid, [0, 20, 20], [-0.3, -0.01, 0], result)
    assert len(fig.axes) == 4
    fig.canvas.draw()  # 3-D collections get their 2-D paths when drawn
    volumes = fig.axes[3].collections[-1]
    assert len(volumes.get_paths()) == 6 * len(result.unique())  # six faces per cell
    matplotlib.pyplot.close(fig)


def test_cell_corners_lie_on_the_cell_bounds():
    from logsph_trace.plot import cell_corners

    grid = lt.Grid(0.3, 10.0, 4, 8, 4)
    corners = cell_corners(grid, [2, 3, 1])
    rho = np.linalg.norm(corners, axis=1)
    bounds = grid.cell_bounds([2, 3, 1])
    assert np.allclose(np.sort(np.unique(np.round(rho, 9))), bounds[:2])


def test_rho_theta_panel():
    from logsph_trace.plot import plot_rho_theta

    grid = lt.Grid(0.3, 10.0, 4, 8, 4)
    ax = plot_rho_theta(grid, [1.0, 0.5, -2.0], [0.3, 0.0, 1.0])
    assert ax.get_xlabel() == "rho (m)" and "theta" in ax.get_ylabel()
    matplotlib.pyplot.close(ax.figure)


def test_heatmap_over_theta_and_phi():
    from logsph_trace.plot import plot_heatmap

    grid = lt.Grid(0.3, 10.0, 4, 8, 4)
    values = np.zeros(grid.shape)
    values[2, 5, 1] = 0.9
    ax = plot_heatmap(grid, values)
    mesh = ax.collections[0]
    assert mesh.get_array().reshape(4, 8)[1, 5] == 0.9  # (phi, theta) after the transpose
    assert ax.get_xlabel() == "theta (deg)"
    with pytest.raises(ValueError, match="values must have the grid's shape"):
        plot_heatmap(grid, np.zeros((2, 2, 2)))
    matplotlib.pyplot.close(ax.figure)
