"""Fig. 5 of the paper, reproduced: from a depth image to what the person looks at.

    python -m bench.fig5

The synthetic scene of ``logsph_trace.scene.table_scene``: a table with an
object on it and a wall, seen by the robot's 640 x 480 depth sensor at the
origin; a person about 1.5 m away looks at the object. The scan builds the
occupancy map (3 scans, OctoMap updates); the gaze ray and a 4-degree gaze
cone are traced into it. Writes bench/results/fig5.png (the four panels of
Fig. 5) and fig5.md, and exits non-zero unless the object is the top target
both by the paper's rule (first cell above p = 0.6 on the ray) and by
fixation probability.
"""

import sys
import time
from pathlib import Path

import numpy as np

import logsph_trace as lt
from bench.workload import write_results
from logsph_trace._files import save_figure
from logsph_trace.scene import table_scene

RESULTS = Path(__file__).resolve().parent / "results"
# Coarse enough that the map's cells can be drawn as volumes.
GRID_ARGS = dict(rho_min=0.3, rho_max=5.0, n_rho=32, n_theta=120, n_phi=60)


def run(grid, scans=3, width=640, height=480):
    """The pipeline; returns everything the figure and the check need."""
    scene, eyes, target = table_scene()
    points, labels, depth = scene.depth_points(width=width, height=height)
    lt.OccupancyGrid(grid).integrate(points[:1000], [0.0, 0.0, 0.0])  # compile or load first
    occupancy = lt.OccupancyGrid(grid)
    start = time.perf_counter()
    for _ in range(scans):
        occupancy.integrate(points, [0.0, 0.0, 0.0])
    integrate_ms = (time.perf_counter() - start) / scans * 1e3
    gaze = target - eyes
    ray = lt.trace(grid, eyes, gaze)
    targets = lt.gaze_targets(occupancy, eyes, gaze, threshold=0.6)
    fixation = lt.fixation_probability(occupancy, eyes, gaze, half_angle=np.radians(4))
    on_object = points[labels == scene.index("object")]
    object_cells = {tuple(c) for c in grid.cell_of(on_object).tolist()}
    return {
        "scene": scene, "eyes": eyes, "target": target, "points": points, "labels": labels,
        "depth": depth, "occupancy": occupancy, "ray": ray, "targets": targets,
        "fixation": fixation, "object_cells": object_cells, "integrate_ms": integrate_ms,
        "top_is_object": bool(len(targets)) and tuple(targets.cells[0]) in object_cells,
        "fixation_top_is_object": bool(len(fixation)) and tuple(fixation.cells[0]) in object_cells,
    }


def figure(grid, result, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from logsph_trace.plot import plot_cells

    eyes, target = result["eyes"], result["target"]
    points = result["points"][::97]  # a light point cloud overlay
    line = np.stack([eyes, eyes + 1.6 * (target - eyes)])
    fig = plt.figure(figsize=(13, 10))
    ax = fig.add_subplot(2, 2, 1)
    depth = np.where(np.isfinite(result["depth"]), result["depth"], np.nan)
    shown = ax.imshow(depth, cmap="viridis")
    fig.colorbar(shown, ax=ax, label="depth (m)")
    ax.set_title("(a) the robot's depth camera")
    ax.set_axis_off()
    panels = [
        ("(b) occupied cells nearer than 3 m (red) and the gaze (yellow)",
         result["occupancy"].occupied(0.6),
         "tab:red"),
        ("(c) cells the gaze traverses (yellow)", result["ray"].unique(), "gold"),
        ("(d) gaze targets: traversed and occupied (green)", result["targets"].cells, "tab:green"),
    ]
    for number, (title, cells, color) in enumerate(panels, start=2):
        ax = fig.add_subplot(2, 2, number, projection="3d")
        ax.scatter(points[:, 0], points[:, 2], points[:, 1], s=0.5, color="tab:blue", alpha=0.3)
        if len(cells):  # the wall behind would hide the rest, and 3-D axes clip nothing
            cells = cells[np.linalg.norm(grid.cell_centers(cells), axis=1) < 3.0]
        plot_cells(grid, cells, ax=ax, color=color, alpha=0.35)
        ax.plot(line[:, 0], line[:, 2], line[:, 1], color="gold", linewidth=2)
        ax.scatter([eyes[0]], [eyes[2]], [eyes[1]], marker="*", color="gold", edgecolor="k",
                   s=160, depthshade=False, label="the person's eyes")
        ax.set_xlim(-1.5, 1.5)
        ax.set_ylim(0.0, 3.6)
        ax.set_zlim(-1.0, 1.0)
        ax.set_xlabel("x (m)")
        ax.set_ylabel("z (m)")
        ax.set_zlabel("y (m, up)")
        ax.view_init(elev=25, azim=-60)
        ax.set_title(title)
    fig.suptitle("Gaze tracing with the occupancy map (cf. paper Fig. 5)")
    fig.tight_layout()
    save_figure(fig, path, dpi=100)
    plt.close(fig)


def main(argv=None):
    grid = lt.Grid(**GRID_ARGS)
    result = run(grid)
    targets, fixation = result["targets"], result["fixation"]
    object_cells = result["object_cells"]
    lines = [
        f"{grid}; {result['points'].shape[0]:,} points from a 640 x 480 "
        f"depth image, integrated 3 times ({result['integrate_ms']:.1f} ms a scan, all threads); "
        f"eyes at {result['eyes'].tolist()} m looking at {result['target'].tolist()} m.",
        "",
        "Gaze targets (paper's rule: cells on the ray above p = 0.6, by distance):",
        "",
        "| # | cell | p | enters at (m) | on the object |",
        "|---:|---|---:|---:|---|",
    ]
    for n, (cell, p, t) in enumerate(zip(targets.cells.tolist(), targets.values, targets.t_enter)):
        lines.append(f"| {n} | {tuple(cell)} | {p:.3f} | {t:.3f} | {tuple(cell) in object_cells} |")
    lines += ["", "Fixation probability (4-degree cone; first occupied cell), top 5:", "",
              "| cell | probability | on the object |", "|---|---:|---|"]
    for cell, p in zip(fixation.cells[:5].tolist(), fixation.values[:5]):
        lines.append(f"| {tuple(cell)} | {p:.3f} | {tuple(cell) in object_cells} |")
    share = sum(p for c, p in zip(fixation.cells.tolist(), fixation.values)
                if tuple(c) in object_cells)
    lines += ["", f"object is the top target: {result['top_is_object']}; "
                  "top fixation cell is on the "
                  f"object: {result['fixation_top_is_object']} "
                  f"(object cells hold {share:.2f} of the "
                  "fixation probability)."]
    text = "\n".join(lines)
    write_results("fig5", argv, text, {
        "top_is_object": bool(result["top_is_object"]),
        "fixation_top_is_object": bool(result["fixation_top_is_object"])})
    figure(grid, result, RESULTS / "fig5.png")
    print(f"wrote {RESULTS / 'fig5.png'}")
    return 0 if result["top_is_object"] and result["fixation_top_is_object"] else 1


if __name__ == "__main__":
    sys.exit(main())
