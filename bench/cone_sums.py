"""How a cone's cells are summed: boxes or cell by cell, and where the boxes' seam goes.

    python -m bench.cone_sums [--rounds 20]

Two same-run A/Bs, alternated in one process (each side is the package's
own code; only the choice is forced):

* **Boxes or cell by cell** (``cone._towards_the_centre``): a gaze away
  from the robot (``bench.cone``'s, on the table scene's map) and the
  README's gaze from a person facing the robot (on the real Motorcycle
  frame's map), each summed both ways: ``trace_cone`` and
  ``fixation_probability`` with the default rays.
* **The boxes' seam** (``cone.theta_shifts``): ``trace_cones`` of 16 gazes
  from people facing the robot, which keep the boxes, with the seam
  opposite the middle of the azimuths each gaze sweeps (the package's) or
  opposite its axis (the plain rule, kept here as the baseline).

Writes bench/results/cone_sums.json and .md.
"""

import argparse
import time

import numpy as np

import logsph_trace as lt
from bench.workload import write_results
from logsph_trace import cone as cone_module
from logsph_trace import datasets
from logsph_trace.scene import table_scene


def axis_seam(grid, origins, axes):
    """The plain rule: the seam opposite each cone's axis, whatever its apex."""
    axes = np.asarray(axes, dtype=np.float64).reshape(-1, 3)
    theta = np.arctan2(axes[:, 0], axes[:, 2])
    low = grid.theta_edges[0]
    theta = low + np.mod(theta - low, 2.0 * np.pi)
    j = np.clip(np.searchsorted(grid.theta_edges, theta, side="right") - 1, 0, grid.n_theta - 1)
    return ((grid.n_theta // 2 - j) % grid.n_theta).astype(np.int64)


def best_of(rounds, variants):
    """Alternate the ``variants`` ({name: (set-up, call)}) for ``rounds``; best ms of each."""
    best = dict.fromkeys(variants, float("inf"))
    names = list(variants)
    for number in range(rounds):
        for name in names if number % 2 else names[::-1]:
            prepare, call = variants[name]
            prepare()
            start = time.perf_counter()
            call()
            best[name] = min(best[name], time.perf_counter() - start)
    return {name: 1e3 * seconds for name, seconds in best.items()}


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rounds", type=int, default=20)
    args = parser.parse_args(argv)
    towards = cone_module._towards_the_centre
    shifts = cone_module.theta_shifts

    def forced(sparse):
        return lambda: setattr(cone_module, "_towards_the_centre",
                               towards if sparse is None else (lambda o, a: sparse))

    table = lt.Grid(0.3, 10.0, 64, 360, 180)
    scene, _, _ = table_scene()
    table_map = lt.OccupancyGrid(table).integrate(scene.depth_points()[0], (0.0, 0.0, 0.0))
    frame = datasets.motorcycle()
    real = lt.Grid(0.3, 8.0, 64, 360, 180)
    real_map = lt.OccupancyGrid(real).integrate_depth(frame.depth, frame.intrinsics)
    facing = lt.gaze_from_pitch_yaw(np.radians(-52.0), np.radians(5.0), (0.2, -0.75, 3.0))
    gazes = {"away from the robot (table scene)": (table, table_map, (0.4, 1.5, 1.2),
                                                   (-0.1, -0.4, 1.0)),
             "facing the robot (Motorcycle)": (real, real_map, facing.origin, facing.direction)}
    half_angle = np.radians(5.0)
    lines = [f"best of {args.rounds} alternated calls per variant, ms, default rays, "
             "5-degree cones", "", "| gaze | call | boxes | cell by cell | package's choice |",
             "|---|---|---:|---:|---|"]
    rows = []
    for label, (grid, bvm, origin, axis) in gazes.items():
        calls = {"trace_cone": lambda g=grid, o=origin, a=axis: lt.trace_cone(g, o, a, half_angle),
                 "fixation_probability": lambda m=bvm, o=origin, a=axis: lt.fixation_probability(
                     m, o, a, half_angle=half_angle)}
        for name, call in calls.items():
            call()
            times = best_of(args.rounds, {"boxes": (forced(False), call),
                                          "cells": (forced(True), call)})
            choice = "cell by cell" if towards(np.asarray(origin), np.asarray(axis)) else "boxes"
            rows.append({"gaze": label, "call": name, **times, "choice": choice})
            lines.append(f"| {label} | {name} | {times['boxes']:.2f} | {times['cells']:.2f} | "
                         f"{choice} |")
    forced(None)()
    rng = np.random.default_rng(3)
    pitches, yaws = np.radians(-52.0 + 8 * rng.standard_normal(16)), np.radians(
        5.0 + 8 * rng.standard_normal(16))
    batch = [lt.gaze_from_pitch_yaw(p, y, (0.2, -0.75, 3.0)) for p, y in zip(pitches, yaws)]
    origins = np.array([g.origin for g in batch])
    axes = np.array([g.direction for g in batch])

    def seam(rule):
        return lambda: setattr(cone_module, "theta_shifts", rule)

    def cones():
        return lt.trace_cones(real, origins, axes, half_angle)

    cones()
    seams = best_of(args.rounds, {"sweep": (seam(shifts), cones),
                                  "axis": (seam(axis_seam), cones)})
    cone_module.theta_shifts = shifts
    lines += ["", "trace_cones of 16 gazes from people facing the robot (boxes), ms: seam "
              f"opposite the sweep's middle {seams['sweep']:.2f}, opposite the axis "
              f"{seams['axis']:.2f} ({seams['axis'] / seams['sweep']:.2f}x)"]
    write_results("cone_sums", argv, "\n".join(lines), {"rows": rows, "seams": seams})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
