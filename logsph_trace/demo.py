"""The main job on real data, and the paper's worked example: ``logsph-trace demo``.

:func:`run` builds the occupancy map of the Middlebury Motorcycle frame
with its objects, has a person behind the motorcycle look at a few things
(gazes from pitch and yaw, as an appearance-based estimator gives them),
names what each gaze lands on, and writes a figure and an interactive
3-D view. :func:`run_synthetic` traces the paper's Fig. 3 example and a
gaze into a synthetic room, with no data to install.
"""

import sys
import time
from pathlib import Path

import numpy as np

from ._files import save_figure
from .sensor import DEFAULT_ROTATION

# A person standing 3 m in front of the camera, behind the motorcycle and
# facing the camera, eyes 0.75 m above it: the camera's OpenCV frame
# (x right, y down, z forward), metres.
EYES = (0.2, -0.75, 3.0)
# What they look at: (what, pitch, yaw), degrees, in L2CS-Net's convention
# (zero looks into the camera; positive pitch up, positive yaw to the image's left).
GAZES = (
    ("down at the motorcycle", -52.0, 5.0),
    ("round at the bench", -18.0, 126.0),
    ("round at the shelves", -8.0, -135.0),
    ("down at the floor", -70.0, 90.0),
)
HALF_ANGLE_DEG = 5.0
# The map: 0.3 to 8 m, 64 log-spaced shells, 1-degree cells.
GRID = (0.3, 8.0, 64, 360, 180)
# pose=None: the camera's (x, y, z) is the map's (-x, -y, z), and back.
CAMERA_FROM_MAP = DEFAULT_ROTATION.T
# The map's axes as the camera sees them, for figures of a map built with pose=None.
MAP_AXES = ("x (m, to the camera's left)", "y (m, up)", "z (m, forward)")


def run(out, html=True):
    """Run the main job on the Motorcycle frame; write ``out``/motorcycle_gaze.png and view.html.

    Returns the list of (what, GazeObjects) in ``GAZES`` order.
    """
    from . import Grid, OccupancyGrid, datasets, gaze_from_pitch_yaw, gaze_objects

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    start = time.perf_counter()
    frame = datasets.motorcycle()
    grid = Grid(*GRID)
    bvm = OccupancyGrid(grid).integrate_depth(frame.depth, frame.intrinsics, labels=frame.labels)
    stats = bvm.last_scan
    print(f"{frame.name}: {stats.rays:,} pixels with depth, {stats.invalid:,} without "
          f"(skipped); objects: {', '.join(frame.names.values())}")
    print(f"A person behind the motorcycle, eyes at {EYES} m in the camera's frame, looks "
          f"through a {HALF_ANGLE_DEG:g}-degree cone:")
    print(f"  {'looking':<24} {'pitch':>6} {'yaw':>6}  {'lands on':<11} {'probability':>11} "
          f"{'distance (m)':>12}")
    results = []
    for what, pitch, yaw in GAZES:
        gaze = gaze_from_pitch_yaw(np.radians(pitch), np.radians(yaw), EYES)
        objects = gaze_objects(bvm, gaze, half_angle=np.radians(HALF_ANGLE_DEG),
                               names=frame.names)
        top = objects.top
        landing = (f"{top.name:<11} {top.probability:11.3f} {top.distance:12.2f}" if top
                   else f"{'no object':<11} {'-':>11} {'-':>12}")
        print(f"  {what:<24} {pitch:6.0f} {yaw:6.0f}  {landing}")
        results.append((what, gaze, objects))
    _figure(frame, grid, bvm, results, out / "motorcycle_gaze.png")
    written = ["motorcycle_gaze.png"]
    if html:
        from .view import write_view

        what, gaze, objects = results[0]
        write_view(out / "view.html", bvm, gaze, objects, np.radians(HALF_ANGLE_DEG),
                   names=frame.names, axis_titles=MAP_AXES,
                   title=f"{frame.name}: the gaze {what}")
        written.append("view.html")
    print(f"wrote {', '.join(written)} to {out}/ in {time.perf_counter() - start:.1f} s")
    return [(what, objects) for what, _, objects in results]


def _figure(frame, grid, bvm, results, path):
    """Draw the photo with its objects and gazes, and the map from above and the side."""
    import matplotlib.pyplot as plt

    colours = {1: "tab:red", 2: "tab:green", 3: "tab:blue"}
    fig, axes = plt.subplots(1, 3, figsize=(17, 5.6), width_ratios=(1.45, 1, 1),
                             layout="constrained")
    image, top, side = axes
    image.imshow(frame.image)
    overlay = np.zeros(frame.labels.shape + (4,))
    for label, colour in colours.items():
        overlay[frame.labels == label] = plt.matplotlib.colors.to_rgba(colour, 0.35)
    image.imshow(overlay)
    fx, fy = frame.intrinsics[0, 0], frame.intrinsics[1, 1]
    cx, cy = frame.intrinsics[0, 2], frame.intrinsics[1, 2]

    def pixel(point_in_camera):
        x, y, z = point_in_camera
        return fx * x / z + cx, fy * y / z + cy

    eyes_pixel = pixel(EYES)
    image.plot(*eyes_pixel, "*", color="gold", markeredgecolor="k", markersize=16)
    for what, gaze, objects in results:
        if objects.top is None:
            continue
        landing = pixel(CAMERA_FROM_MAP @ objects.top.point)
        image.annotate("", xy=landing, xytext=eyes_pixel,
                       arrowprops=dict(arrowstyle="->", color="gold", linewidth=2))
        image.text(landing[0], landing[1] + 18, objects.top.name, color="white", fontsize=9,
                   ha="center", bbox=dict(facecolor="black", alpha=0.5, pad=1, linewidth=0))
    image.set_title("the photo, its objects (tinted) and where each gaze lands;\n"
                    "the star is the person's eyes", fontsize=10)
    image.set_xlabel("column (pixels)")
    image.set_ylabel("row (pixels)")
    occupied = bvm.occupied(0.6)
    centres = grid.cell_centers(occupied) @ CAMERA_FROM_MAP.T  # in the camera's frame
    labels = bvm.labels[tuple(occupied.T)]
    eyes = np.asarray(EYES)
    # From above: x to the right as in the photo, z away from the camera.
    # From the side: z away from the camera, up as up.
    for ax, (a, b), (a_name, b_name), sign in (
            (top, (0, 2), ("x (m, to the camera's right)", "z (m, forward)"), (1, 1)),
            (side, (2, 1), ("z (m, forward)", "height above the camera (m)"), (1, -1))):
        ax.scatter(sign[0] * centres[:, a], sign[1] * centres[:, b], s=0.3, color="0.75")
        for label, colour in colours.items():
            mine = centres[labels == label]
            ax.scatter(sign[0] * mine[:, a], sign[1] * mine[:, b], s=0.6, color=colour,
                       label=frame.names[label])
        for what, gaze, objects in results:
            if objects.top is None:
                continue
            end = CAMERA_FROM_MAP @ objects.top.point
            ax.plot([sign[0] * eyes[a], sign[0] * end[a]], [sign[1] * eyes[b], sign[1] * end[b]],
                    color="goldenrod", linewidth=1.5)
        ax.plot(sign[0] * eyes[a], sign[1] * eyes[b], "*", color="gold", markeredgecolor="k",
                markersize=14)
        ax.plot(0, 0, "k^", markersize=9)
        ax.set_xlabel(a_name)
        ax.set_ylabel(b_name)
        ax.set_aspect("equal")
        ax.grid(alpha=0.3)
    top.legend(loc="upper left", fontsize=8, markerscale=8)
    top.set_title("the map from above (occupied cells; the triangle is the camera)",
                  fontsize=10)
    side.set_title("the map from the side", fontsize=10)
    save_figure(fig, path, dpi=80)
    plt.close(fig)


def run_synthetic(out):
    """Trace the paper's Fig. 3 example and a gaze cone into a synthetic room; write figures."""
    from . import Grid, OccupancyGrid, fixation_probability, gaze_targets, trace
    from .cli import print_trace
    from .plot import trace_figure
    from .scene import table_scene

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    start = time.perf_counter()
    grid = Grid.from_increments(10.0, 80.0, 10, d_theta=10.0, d_phi=10.0)
    origin, direction = (0.0, 20.0, 20.0), (-0.3, -0.01, 0.0)
    exact = trace(grid, origin, direction)
    bisect = trace(grid, origin, direction, method="bisect")
    print("The paper's worked example (Fig. 3), decimetres:")
    print(f"  gaze from {origin} along {direction}: {len(exact)} cells (exact); "
          f"Algorithm 1 with the paper's default_t reports {len(bisect)}")
    print_trace(exact, "table", sys.stdout)
    figure = trace_figure(grid, origin, direction, exact, title="The paper's Fig. 3 example",
                          unit="dm")
    save_figure(figure, out / "fig3_worked_example.png", dpi=90)

    scene, eyes, target = table_scene()
    room = Grid(0.3, 5.0, 32, 120, 60)
    points, labels, _ = scene.depth_points()
    bvm = OccupancyGrid(room)
    for _ in range(3):
        bvm.integrate(points, [0.0, 0.0, 0.0])
    targets = gaze_targets(bvm, eyes, target - eyes)
    fixation = fixation_probability(bvm, eyes, target - eyes, half_angle=np.radians(4))
    on_object = points[labels == scene.index("object")]
    object_cells = {tuple(c) for c in room.cell_of(on_object).tolist()}
    print("\nA person 1.5 m from the robot looks at an object on a table (cf. Fig. 5):")
    print(f"  {points.shape[0]:,} depth points -> occupancy map {room.shape}")
    print(f"  {'cell':>16} {'fixation':>9} {'on the object':>14}")
    for cell, value in zip(fixation.cells[:5].tolist(), fixation.values[:5]):
        print(f"  {str(tuple(cell)):>16} {value:9.3f} {str(tuple(cell) in object_cells):>14}")
    top = bool(len(targets)) and tuple(targets.cells[0]) in object_cells
    print(f"  the first occupied cell on the gaze is on the object: {top}")
    _scene_figure(room, bvm, eyes, targets, points, out / "fig5_gaze_on_object.png")
    print(f"\nfigures written to {out}/ in {time.perf_counter() - start:.1f} s")


def _scene_figure(grid, bvm, eyes, targets, points, path):
    import matplotlib.pyplot as plt

    from .plot import plot_cells

    fig = plt.figure(figsize=(7.5, 6.5))
    ax = fig.add_subplot(projection="3d")
    ax.computed_zorder = False  # drawn in order: the gaze and the eyes over the cells
    cloud = points[::97]
    ax.scatter(cloud[:, 0], cloud[:, 2], cloud[:, 1], s=0.5, color="tab:blue", alpha=0.3)
    occupied = bvm.occupied(0.6)
    near = occupied[grid.rho_edges[occupied[:, 0]] < 3.0]  # the wall behind would hide the rest
    hit = {tuple(c) for c in targets.cells.tolist()}
    near = np.array([c for c in near.tolist() if tuple(c) not in hit], dtype=np.int32)
    plot_cells(grid, near, ax=ax, color="tab:red", alpha=0.06)
    plot_cells(grid, targets.cells, ax=ax, color="tab:green", alpha=0.9)
    eyes = np.asarray(eyes)
    landing = grid.cell_centers(targets.cells[0]) if len(targets) else eyes
    ax.plot([eyes[0], landing[0]], [eyes[2], landing[2]], [eyes[1], landing[1]], color="gold",
            linewidth=2.5)
    ax.scatter([eyes[0]], [eyes[2]], [eyes[1]], marker="*", s=200, color="gold",
               edgecolor="k", depthshade=False)
    ax.set_xlim(-0.8, 1.2)  # the table, the object and the person
    ax.set_ylim(1.0, 2.4)
    ax.set_zlim(-0.8, 0.3)
    ax.view_init(elev=22, azim=-125)
    ax.set_xlabel("x (m)")
    ax.set_ylabel("z (m)")
    ax.set_zlabel("y (m, up)")
    ax.set_title("occupied cells nearer than 3 m (red; the wall is left out), the person's\n"
                 "eyes (star), the gaze (yellow) to the first occupied cell on it, and all\n"
                 "the occupied cells on it (green: the object, then the table behind)",
                 fontsize=10)
    fig.subplots_adjust(left=0.02, right=0.92, bottom=0.04, top=0.9)
    save_figure(fig, path, dpi=90)
    plt.close(fig)
