"""An interactive 3-D view of a map, a gaze and the objects it reaches.

:func:`write_view` writes one self-contained HTML file (plotly, with its
JavaScript inlined: about 5 MB, and it opens offline in any browser). It
needs plotly: ``pip install "logsph_trace[view]"``.
"""

import math
from pathlib import Path

import numpy as np

from . import _validate as validate
from ._files import atomic_write
from .gaze import GazeObjects
from .occupancy import _check_occupancy
from .sensor import Gaze

# Distinct colours for objects, in label order (matplotlib's "tab" colours:
# red, green, blue first, as the demo's figure draws labels 1, 2, 3).
COLOURS = ("#d62728", "#2ca02c", "#1f77b4", "#ff7f0e", "#9467bd", "#8c564b", "#e377c2",
           "#bcbd22", "#17becf")
# At most this many cells are drawn, evenly subsampled: the file stays small.
MAX_CELLS = 60_000


def write_view(path, occupancy, gaze=None, objects=None, half_angle=None, names=None,
               threshold=0.6, axis_titles=("x (m)", "y (m)", "z (m)"), title=None,
               view_from=None):
    """Write an interactive 3-D view of a map's occupied cells, a gaze and its objects.

    Parameters
    ----------
    path : str or path-like
        The HTML file to write (atomically).
    occupancy : OccupancyGrid
        Its cells above ``threshold`` are drawn at their centres, coloured by
        object label (grey: no label).
    gaze : Gaze, optional
        Drawn from the eyes (a star) to the point where it lands on its most
        probable object, or 1 m long if it reaches none.
    objects : GazeObjects, optional
        The objects the gaze reached (:func:`~logsph_trace.gaze_objects`):
        each is named at its centroid with its probability.
    half_angle : float, optional
        The gaze cone's half-angle (radians): its outline is drawn.
    names : mapping of int to str, optional
        Names of the labels, for the legend.
    threshold : float
        Probability above which a cell is drawn.
    axis_titles : tuple of 3 str
        The axes' titles, with their units and directions.
    title : str, optional
    view_from : array_like, shape (3,), optional
        Where the initial view looks from, relative to the scene's middle
        (plotly's camera ``eye``); default behind the map's origin along -z,
        a little above, with +y up: as a camera at the origin looking along
        +z sees it.

    Returns
    -------
    pathlib.Path
        The file written.
    """
    try:
        import plotly.graph_objects as go
    except ImportError:
        raise ImportError("the 3-D view needs plotly: pip install 'logsph_trace[view]'") from None
    _check_occupancy(occupancy)
    if gaze is not None and not isinstance(gaze, Gaze):
        raise validate.WrongTypeError(f"gaze must be a Gaze, got {type(gaze).__name__}")
    if objects is not None and not isinstance(objects, GazeObjects):
        raise validate.WrongTypeError(f"objects must be GazeObjects, got "
                                      f"{type(objects).__name__}")
    names = dict(names or {})
    figure = go.Figure()
    _draw_cells(go, figure, occupancy, threshold, names)
    if gaze is not None:
        _draw_gaze(go, figure, gaze, objects, half_angle)
    if objects is not None:
        for hit in objects:
            name = hit.name or names.get(hit.id, f"object {hit.id}")
            figure.add_trace(go.Scatter3d(
                x=[hit.centroid[0]], y=[hit.centroid[1]], z=[hit.centroid[2]],
                mode="markers+text", text=[f"{name}: {hit.probability:.2f}"],
                textposition="top center", marker=dict(size=4, color="black"),
                name=f"{name} (centroid)", showlegend=False))
    eye = dict(x=0.35, y=0.5, z=-2.1) if view_from is None else dict(
        zip("xyz", validate.vector("view_from", view_from).tolist()))
    scene = dict(aspectmode="data", camera=dict(up=dict(x=0, y=1, z=0), eye=eye))
    for axis, text in zip(("xaxis", "yaxis", "zaxis"), axis_titles):
        scene[axis] = dict(title=dict(text=text))
    figure.update_layout(scene=scene, title=title, legend=dict(itemsizing="constant"),
                         margin=dict(l=0, r=0, t=40 if title else 0, b=0))
    html = figure.to_html(include_plotlyjs=True, full_html=True)
    with atomic_write(path) as stream:
        stream.write(html.encode("utf-8"))
    return Path(path)


def _draw_cells(go, figure, occupancy, threshold, names):
    """Add the map's occupied cells to ``figure``, a trace per object label.

    At most ``MAX_CELLS`` cells, evenly thinned.
    """
    cells = occupancy.occupied(threshold)
    if cells.shape[0] > MAX_CELLS:
        cells = cells[:: -(-cells.shape[0] // MAX_CELLS)]
    centres = occupancy.grid.cell_centers(cells) if cells.shape[0] else np.empty((0, 3))
    labels = occupancy._frame_labels()[tuple(cells.T)] if cells.shape[0] else np.empty(0, np.int32)
    for label in np.unique(labels).tolist():
        mine = centres[labels == label]
        name = "no object" if label == 0 else names.get(label, f"object {label}")
        colour = "#9a9a9a" if label == 0 else COLOURS[(label - 1) % len(COLOURS)]
        figure.add_trace(go.Scatter3d(
            x=mine[:, 0], y=mine[:, 1], z=mine[:, 2], mode="markers", name=name,
            marker=dict(size=1.6, color=colour, opacity=0.35 if label == 0 else 0.8),
            hovertemplate=f"{name}<br>(%{{x:.2f}}, %{{y:.2f}}, %{{z:.2f}}) m<extra></extra>"))


def _draw_gaze(go, figure, gaze, objects, half_angle):
    """Draw the eyes, the gaze to where it lands, and the cone's outline as far."""
    eyes, axis = np.asarray(gaze.origin, float), np.asarray(gaze.direction, float)
    top = objects.top if objects is not None else None
    reach = top.distance if top is not None else 1.0
    end = eyes + reach * axis
    figure.add_trace(go.Scatter3d(x=[eyes[0]], y=[eyes[1]], z=[eyes[2]], mode="markers",
                                  name="eyes", marker=dict(size=6, color="gold",
                                                           symbol="diamond",
                                                           line=dict(color="black", width=1))))
    figure.add_trace(go.Scatter3d(x=[eyes[0], end[0]], y=[eyes[1], end[1]], z=[eyes[2], end[2]],
                                  mode="lines", name="gaze", line=dict(color="gold", width=6)))
    if half_angle:
        # Eight lines on the cone's surface, from the eyes to the same distance.
        helper = np.eye(3)[int(np.argmin(np.abs(axis)))]
        u = np.cross(axis, helper)
        u /= np.linalg.norm(u)
        v = np.cross(axis, u)
        xs, ys, zs = [], [], []
        for angle in np.linspace(0.0, 2 * math.pi, 8, endpoint=False):
            side = math.cos(half_angle) * axis + math.sin(half_angle) * (
                math.cos(angle) * u + math.sin(angle) * v)
            tip = eyes + reach / math.cos(half_angle) * side
            xs += [eyes[0], tip[0], None]
            ys += [eyes[1], tip[1], None]
            zs += [eyes[2], tip[2], None]
        figure.add_trace(go.Scatter3d(x=xs, y=ys, z=zs, mode="lines", name="gaze cone",
                                      line=dict(color="orange", width=2)))
