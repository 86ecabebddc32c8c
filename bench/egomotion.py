"""A map that follows a moving robot: the time of ``OccupancyGrid.move`` and what it keeps.

    python -m bench.egomotion [--repeats 10] [--threads 2]

A synthetic sequence (``logsph_trace.scene.robot_walk`` in ``room_scene``):
the robot turns 80 degrees about the vertical axis and walks 0.4 m in 40
steps, integrating a 640 x 480 scan after each, into a 64 x 360 x 180 map.
Recorded:

- the time per frame of move plus integrate (with the scan's labels),
  against integrate alone (the same frames into a map that never moves: the
  sensor at its centre);
- how far the final map is from one built from scratch from the same frames
  in the final frame: the F-score of occupied cells (p > 0.5; a cell is
  matched when the other map has an occupied cell within one cell of it),
  and how often 200 random gazes at the scene's boxes name the same object;
  the same for a map resampled after every move (``recentre`` each frame);
- the time of a general move followed by reading ``log_odds``, on a map
  observed over about 140 degrees of azimuth and on one observed in one
  view, and of a rotation by whole azimuth cells (an index roll), each
  against one integrate of a 640 x 480 frame in the same run; and, as
  same-run A/Bs of ``resample``'s two shortcuts, the same moves with every
  column traced and with the roll done as a gather of columns.

Writes bench/results/egomotion.json, egomotion.md and egomotion.png (also
docs/images/egomotion.png: the final maps seen from above).
"""

import contextlib
import time
from pathlib import Path

import numba
import numpy as np

import logsph_trace as lt
from bench.workload import thread_arguments, write_results
from logsph_trace import motion
from logsph_trace.scene import robot_walk, room_scene, yaw_pose

GRID = (0.3, 10.0, 64, 360, 180)
STEPS = 40
TURN = np.radians(80.0)
WALK = (0.4, 0.0, 0.0)


def neighbourhood(occupied, theta_full):
    """Cells within one index of an occupied cell on each axis (around the seam when full)."""
    near = occupied.copy()
    for axis in range(3):
        grown = near.copy()
        for shift in (-1, 1):
            moved = np.roll(near, shift, axis=axis)
            if not (axis == 1 and theta_full):
                moved[(slice(None),) * axis + (0 if shift == 1 else -1,)] = False
            grown |= moved
        near = grown
    return near


def f_score(first, second, theta_full=True):
    """F-score of two occupancy masks, a cell matched when the other has one within one cell.

    Returns (f, precision, recall), ``first`` read as the estimate.
    """
    precision = np.count_nonzero(first & neighbourhood(second, theta_full)) / max(
        np.count_nonzero(first), 1)
    recall = np.count_nonzero(second & neighbourhood(first, theta_full)) / max(
        np.count_nonzero(second), 1)
    total = precision + recall
    return (2.0 * precision * recall / total if total else 0.0), precision, recall


def in_frame(pose, points):
    """World ``points`` in the frame of ``pose`` (4 x 4)."""
    return (points - pose[:3, 3]) @ pose[:3, :3]


def walk_maps(grid, steps, recentre=False):
    """Run the sequence: (moving map, from-scratch map in the final frame, seconds per frame).

    ``steps``: ``robot_walk``'s; ``recentre``: resample after every move.
    The seconds are each frame's move plus integrate.
    """
    moving = lt.OccupancyGrid(grid)
    seconds = []
    for step in steps:
        start = time.perf_counter()
        moving.move(step.motion)
        if recentre:
            moving.recentre()
        moving.integrate(step.points, (0.0, 0.0, 0.0), labels=step.labels)
        seconds.append(time.perf_counter() - start)
    final = steps[-1].pose
    scratch = lt.OccupancyGrid(grid)
    for step in steps:
        world = step.points @ step.pose[:3, :3].T + step.pose[:3, 3]
        scratch.integrate(in_frame(final, world), in_frame(final, step.pose[:3, 3]),
                          labels=step.labels)
    return moving, scratch, seconds


def random_gazes(scene, pose, n_gazes, seed=0):
    """``n_gazes`` gazes from eyes near the robot at random points of the scene's boxes.

    Returns (eyes, directions, box + 1), in the frame of ``pose``.
    """
    rng = np.random.default_rng(seed)
    boxes = rng.integers(0, len(scene.boxes), n_gazes)
    targets = rng.uniform(scene.low[boxes], scene.high[boxes])
    eyes = pose[:3, 3] + rng.uniform((-0.6, 0.1, -0.6), (0.6, 0.5, 0.6), (n_gazes, 3))
    return in_frame(pose, eyes), in_frame(pose, targets) - in_frame(pose, eyes), boxes + 1


def gaze_agreement(first, second, eyes, directions):
    """The share of gazes whose named object (``gaze_objects(...).top``, 0 for none) agrees."""
    same = 0
    for eye, direction in zip(eyes, directions):
        names = []
        for occupancy in (first, second):
            top = lt.gaze_objects(occupancy, eye, direction).top
            names.append(0 if top is None else top.id)
        same += names[0] == names[1]
    return same / eyes.shape[0]


def observed_map(grid, scene, yaws):
    """A map of the scene's scans from the centre, one per yaw (degrees), and one scan's points."""
    occupancy = lt.OccupancyGrid(grid)
    for yaw in yaws:
        pose = yaw_pose(np.radians(yaw), (0.0, 0.0, 0.0))
        points, boxes, _ = scene.depth_points(forward=pose[:3, 2], up=pose[:3, 1])
        occupancy.integrate(points, (0.0, 0.0, 0.0), labels=boxes + 1)
    return occupancy, points


def time_moves(occupancy, motions, repeats):
    """Best seconds of ``move`` then reading ``log_odds``, cycling through ``motions``."""
    best = np.inf
    for run in range(repeats):
        start = time.perf_counter()
        occupancy.move(motions[run % len(motions)])
        occupancy.log_odds  # noqa: B018 -- reading it is what is timed
        best = min(best, time.perf_counter() - start)
    return best


def figure(grid, maps, path):
    """Draw the final maps' occupied cells from above, unmatched ones in red; write ``path``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    scratch = maps["built from scratch in the final frame"] > 0
    panels = len(maps)
    fig, axes = plt.subplots(1, panels, figsize=(4.2 * panels, 5.0), sharey=True)
    for axis, (title, log_odds) in zip(axes, maps.items()):
        occupied = log_odds > 0
        near = occupied if occupied is scratch else scratch
        matched = occupied & neighbourhood(near, grid.theta_full)
        for mask, colour, label in ((matched, "0.35", "matched within one cell"),
                                    (occupied & ~matched, "tab:red", "not matched")):
            cells = np.argwhere(mask)
            centres = grid.cell_centers(cells) if cells.size else np.empty((0, 3))
            axis.scatter(centres[:, 0], centres[:, 2], s=2, c=colour, label=label)
        if occupied is not scratch:
            f, _, _ = f_score(occupied, scratch, grid.theta_full)
            title += f"\nF-score {f:.3f}"
        axis.set_title(title, fontsize=10)
        axis.set_xlabel("x, to the robot's left (m)")
        axis.set_aspect("equal")
        axis.set_xlim(4.0, -3.5)  # the robot's left on the left, as seen from above
        axis.set_ylim(-3.0, 4.0)
        axis.plot(0.0, 0.0, "k^", markersize=6)
    axes[0].set_ylabel("z, ahead of the robot (m)")
    axes[-1].legend(loc="lower right", fontsize=8, markerscale=4)
    fig.suptitle("Occupied cells (p > 0.5) after the robot turned 80 degrees and walked 0.4 m, "
                 "seen from above; the robot at the triangle", fontsize=10)
    fig.tight_layout(rect=(0.0, 0.02, 1.0, 0.95))
    fig.savefig(path, dpi=110)
    plt.close(fig)


def move_timings(grid, scene, repeats):
    """Rows of (map, move, best ms, integrate best ms) for the move targets."""
    general = yaw_pose(np.radians(2.0), (0.011, 0.0, 0.007))
    roll = yaw_pose(2.0 * np.pi / grid.n_theta * 2, (0.0, 0.0, 0.0))
    rows = []
    for name, yaws in (("about 140 degrees", (-40.0, 0.0, 40.0, 80.0)), ("one view", (0.0,))):
        occupancy, points = observed_map(grid, scene, yaws)
        integrate = lt.OccupancyGrid(grid)
        integrate_ms = min(_seconds(lambda: integrate.integrate(points, (0.0, 0.0, 0.0)))
                           for _ in range(repeats)) * 1e3
        for what, motions, switched_off in (
                ("general (2 degrees, 1.3 cm)", [general, np.linalg.inv(general)], None),
                ("general, every column traced (A/B)", [general, np.linalg.inv(general)],
                 "_near_seen"),
                ("index roll (2 cells)", [roll, np.linalg.inv(roll)], None),
                ("index roll as a column gather (A/B)", [roll, np.linalg.inv(roll)],
                 "whole_cell_turn")):
            with _without(switched_off):
                occupancy.log_odds  # noqa: B018 -- centred before each series
                rows.append((name, what, time_moves(occupancy, motions, repeats) * 1e3,
                             integrate_ms))
    return rows


@contextlib.contextmanager
def _without(mechanism):
    """Switch off one of ``resample``'s shortcuts inside the block (None: none).

    ``_near_seen``: every column's centre ray is traced, not only those
    near an observed column; ``whole_cell_turn``: a turn by whole azimuth
    cells is a gather of columns, not a block copy per shell.
    """
    if mechanism is None:
        yield
        return
    saved = getattr(motion, mechanism)
    stand_in = {"_near_seen": lambda grid, seen, delta: np.ones(seen.size, dtype=bool),
                "whole_cell_turn": lambda grid, rotation: None}[mechanism]
    setattr(motion, mechanism, stand_in)
    try:
        yield
    finally:
        setattr(motion, mechanism, saved)


def _seconds(call):
    start = time.perf_counter()
    call()
    return time.perf_counter() - start


def main(argv=None):
    args, counts = thread_arguments(__doc__, 10, argv)
    numba.set_num_threads(counts[-1])
    grid = lt.Grid(*GRID)
    scene = room_scene()
    steps = list(robot_walk(scene, STEPS, TURN, WALK))
    eyes, directions, _ = random_gazes(scene, steps[-1].pose, 200)
    walk_maps(grid, steps[:3])  # compiles what the timed runs use: integrate through a pose,
    walk_maps(grid, steps[:3], recentre=True)  # then from the centre and the resampling
    results, maps = {}, {}
    for name, recentre in (("lazy (move as it is)", False), ("resampled every move", True)):
        moving, scratch, seconds = walk_maps(grid, steps, recentre)
        maps["built from scratch in the final frame"] = scratch.log_odds
        maps[name] = moving.log_odds
        f, precision, recall = f_score(moving.log_odds > 0, scratch.log_odds > 0)
        results[name] = {"frame_ms_median": float(np.median(seconds)) * 1e3,
                         "frame_ms_max": float(np.max(seconds)) * 1e3,
                         "f_score": f, "precision": precision, "recall": recall,
                         "gazes_agree": gaze_agreement(moving, scratch, eyes, directions)}
    still = lt.OccupancyGrid(grid)
    alone = [_seconds(lambda step=step: still.integrate(step.points, (0.0, 0.0, 0.0),
                                                        labels=step.labels))
             for step in steps]
    rows = move_timings(grid, scene, args.repeats)
    lines = [f"{grid}, {counts[-1]} threads; {STEPS} steps turning 80 degrees and walking "
             "0.4 m, a 640 x 480 scan of the room scene after each", "",
             "| map | frame, median (ms) | frame, slowest (ms) | F-score | precision | recall "
             "| gazes naming the same object |", "|---|---:|---:|---:|---:|---:|---:|"]
    for name, r in results.items():
        lines.append(f"| {name} | {r['frame_ms_median']:.1f} | {r['frame_ms_max']:.1f} "
                     f"| {r['f_score']:.3f} | {r['precision']:.3f} | {r['recall']:.3f} "
                     f"| {r['gazes_agree']:.1%} |")
    lines.append(f"| integrate alone (a map that never moves) | {np.median(alone) * 1e3:.1f} "
                 f"| {np.max(alone) * 1e3:.1f} | | | | |")
    lines += ["", "frame: move plus integrate; F-score and gazes: the final map against one "
              "built from scratch from the same frames in the final frame (occupied: p > 0.5, "
              "matched within one cell; 200 random gazes at the scene's boxes)", "",
              f"Move, then read `log_odds` (best of {args.repeats}), against one integrate of "
              "a 640 x 480 scan from the centre into an empty map (best, same run):", "",
              "| map observed | move | move + read (ms) | integrate (ms) |",
              "|---|---|---:|---:|"]
    lines += [f"| {m} | {w} | {t:.2f} | {i:.2f} |" for m, w, t, i in rows]
    root = Path(__file__).resolve().parents[1]
    for path in (root / "bench" / "results" / "egomotion.png",
                 root / "docs" / "images" / "egomotion.png"):
        figure(grid, {k: maps[k] for k in ("built from scratch in the final frame",
                                           "lazy (move as it is)", "resampled every move")},
               path)
    write_results("egomotion", argv, "\n".join(lines),
                  {"threads": counts[-1], "sequence": results,
                   "integrate_alone_ms_median": float(np.median(alone)) * 1e3,
                   "moves": [{"map": m, "move": w, "ms": t, "integrate_ms": i}
                             for m, w, t, i in rows]})


if __name__ == "__main__":
    main()
