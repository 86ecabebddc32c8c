"""A/B of a workload: this working tree against another commit.

    python -m bench.ab 5c4c438             # 100,000 rays, 128^3 cells, 10 rounds
    python -m bench.ab HEAD --rounds 6     # A/A: how far from 1 the probe itself reads
    python -m bench.ab main~3 --rays 20000 --cells 64 --threads 1
    python -m bench.ab main~3 --threads 2 --parallel   # trace_many on both threads
    python -m bench.ab main~3 --workload occupancy --threads 2
    python -m bench.ab main~3 --workload cone --threads 2

``--workload``: ``trace`` (the default: ``bench.run``'s serial ``trace_many``),
``occupancy`` (``bench.occupancy``'s table scan integrated at the centre and
10 cm off, the two times summed) or ``cone`` (``bench.cone``'s 1,000-ray cone
and ``fixation_probability`` on the same gaze, summed) or ``gaze`` (the
README's gaze on the real Motorcycle map, from a person facing the robot:
``fixation_probability`` with the default rays).

For kernel changes, whose effect is a few per cent on a machine whose speed
drifts by more than that. Each round starts one fresh Python for each tree,
in alternating order (this tree first in even rounds), so drift falls on
both. A process imports its tree's package, builds the ``bench.run``
workload, traces it once untimed, then times ``--repeats`` serial
``trace_many`` calls and reports the best. The other commit is checked out
in a temporary git worktree, removed afterwards; its Numba cache is its own.

Unlike a probe that imports two copies of the package into one process
(such a probe favours the tree it runs from by 1-2% on identical code),
the two trees never share a process. Run
it with REV = HEAD on a clean tree to see what "no change" reads as.
Prints the per-round ratios and the ratio of the medians (below 1: this
tree is faster); nothing is written. Needs git.
"""

import argparse
import os
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent

# Run in a fresh Python with one tree's package first on the path. Builds the
# bench.run workload by itself (numpy only), so that an older tree's bench
# module cannot change what is timed.
CHILD = """
import sys, time
import numpy as np
import numba
numba.set_num_threads({threads})
import logsph_trace as lt
rng = np.random.default_rng(0)
directions = rng.normal(size=({rays}, 3))
directions /= np.linalg.norm(directions, axis=1)[:, None]
radial = rng.normal(size=({rays}, 3))
radial /= np.linalg.norm(radial, axis=1)[:, None]
origins = radial * 10.0 * rng.random({rays})[:, None] ** (1 / 3)
grid = lt.Grid(0.1, 10.0, {cells}, {cells}, {cells}, spacing="log")
segments = len(lt.trace_many(grid, origins, directions, parallel={parallel}).cells)
best = float("inf")
for _ in range({repeats}):
    start = time.perf_counter()
    lt.trace_many(grid, origins, directions, parallel={parallel})
    best = min(best, time.perf_counter() - start)
print(best, segments)
"""

# bench.occupancy's table scan (the scene builds it with numpy alone), at the
# centre and 10 cm off; the segments slot counts the occupied cells.
OCCUPANCY_CHILD = """
import sys, time
import numpy as np
import numba
numba.set_num_threads({threads})
import logsph_trace as lt
from logsph_trace.scene import table_scene
grid = lt.Grid(0.3, 10.0, 64, 360, 180)
scene, _, _ = table_scene()
scans = [(s, scene.depth_points(sensor=s)[0]) for s in ((0.0, 0.0, 0.0), (0.06, 0.08, 0.0))]
occupied = sum(int((lt.OccupancyGrid(grid).integrate(p, s).log_odds > 0).sum()) for s, p in scans)
best = [float("inf")] * len(scans)
for _ in range({repeats}):
    for n, (sensor, points) in enumerate(scans):
        bvm = lt.OccupancyGrid(grid)
        start = time.perf_counter()
        bvm.integrate(points, sensor)
        best[n] = min(best[n], time.perf_counter() - start)
print(sum(best), occupied)
"""

# bench.cone's gaze: a 1,000-ray cone and fixation_probability over the table
# scene's map; the segments slot counts the cone's cells.
CONE_CHILD = """
import sys, time
import numpy as np
import numba
numba.set_num_threads({threads})
import logsph_trace as lt
from logsph_trace.scene import table_scene
grid = lt.Grid(0.3, 10.0, 64, 360, 180)
scene, _, _ = table_scene()
bvm = lt.OccupancyGrid(grid).integrate(scene.depth_points(sensor=(0.0, 0.0, 0.0))[0],
                                       (0.0, 0.0, 0.0))
origin, gaze, half_angle = (0.4, 1.5, 1.2), (-0.1, -0.4, 1.0), np.radians(5.0)
calls = [lambda: lt.trace_cone(grid, origin, gaze, half_angle, n_rays=1000),
         lambda: lt.fixation_probability(bvm, origin, gaze, half_angle=half_angle, n_rays=1000)]
cells = len(calls[0]().cells)
best = [float("inf")] * len(calls)
for _ in range(10 * {repeats}):
    for n, call in enumerate(calls):
        start = time.perf_counter()
        call()
        best[n] = min(best[n], time.perf_counter() - start)
print(sum(best), cells)
"""

# The main job's gaze: a person facing the robot's camera, behind the
# motorcycle of the real frame, looks down at it (the README's gaze, built
# by hand so that older trees take it); fixation_probability with the
# default rays. The segments slot counts the cells with a probability.
GAZE_CHILD = """
import sys, time
import numpy as np
import numba
numba.set_num_threads({threads})
import logsph_trace as lt
from logsph_trace import datasets
frame = datasets.motorcycle()
grid = lt.Grid(0.3, 8.0, 64, 360, 180)
bvm = lt.OccupancyGrid(grid).integrate_depth(frame.depth, frame.intrinsics)
pitch, yaw = np.radians(-52.0), np.radians(5.0)
eyes = np.array([-0.2, 0.75, 3.0])  # the camera's (0.2, -0.75, 3.0), in the map
direction = np.array([np.cos(pitch) * np.sin(yaw), np.sin(pitch), -np.cos(pitch) * np.cos(yaw)])
call = lambda: lt.fixation_probability(bvm, eyes, direction, half_angle=np.radians(5.0))
cells = len(call().cells)
best = float("inf")
for _ in range(10 * {repeats}):
    start = time.perf_counter()
    call()
    best = min(best, time.perf_counter() - start)
print(best, cells)
"""

CHILDREN = {"trace": CHILD, "occupancy": OCCUPANCY_CHILD, "cone": CONE_CHILD,
            "gaze": GAZE_CHILD}


def run_child(tree, code):
    """Run ``code`` with ``tree``'s package importable; return (seconds, segments)."""
    env = dict(os.environ, PYTHONPATH=str(tree))
    out = subprocess.run([sys.executable, "-c", code], cwd=tree, env=env, check=True,
                         capture_output=True, text=True).stdout.split()
    return float(out[-2]), int(out[-1])


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("rev", help="the commit to compare this working tree against")
    parser.add_argument("--rounds", type=int, default=10)
    parser.add_argument("--repeats", type=int, default=5, help="timed calls per process")
    parser.add_argument("--rays", type=int, default=100_000)
    parser.add_argument("--cells", type=int, default=128)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--workload", choices=sorted(CHILDREN), default="trace")
    parser.add_argument("--parallel", action="store_true",
                        help="trace: trace_many on all threads (default: one thread)")
    args = parser.parse_args(argv)
    if min(args.rounds, args.repeats, args.rays, args.cells, args.threads) < 1:
        parser.error("--rounds, --repeats, --rays, --cells and --threads must be at least 1")
    known = subprocess.run(["git", "rev-parse", "--verify", "--quiet", f"{args.rev}^{{commit}}"],
                           cwd=ROOT, capture_output=True)
    if known.returncode != 0:
        parser.error(f"{args.rev!r} is not a commit of this repository")
    code = CHILDREN[args.workload].format(threads=args.threads, rays=args.rays,
                                          cells=args.cells, repeats=args.repeats,
                                          parallel=args.parallel)
    with tempfile.TemporaryDirectory(prefix="bench-ab-") as scratch:
        other = Path(scratch) / "tree"
        subprocess.run(["git", "worktree", "add", "--detach", "--quiet", str(other), args.rev],
                       cwd=ROOT, check=True)
        try:
            trees = {"this tree": ROOT, args.rev: other}
            print("warming both trees' caches (compiles on a first run) ...", flush=True)
            segments = {name: run_child(tree, code)[1] for name, tree in trees.items()}
            if len(set(segments.values())) != 1:
                print(f"note: the trees write different numbers of segments: {segments}")
            times = {name: [] for name in trees}
            for round_ in range(args.rounds):
                order = list(trees) if round_ % 2 == 0 else list(trees)[::-1]
                for name in order:
                    times[name].append(run_child(trees[name], code)[0])
                ratio = times["this tree"][-1] / times[args.rev][-1]
                print(f"round {round_ + 1}: this tree {times['this tree'][-1] * 1e3:.1f} ms, "
                      f"{args.rev} {times[args.rev][-1] * 1e3:.1f} ms, ratio {ratio:.3f}",
                      flush=True)
        finally:
            subprocess.run(["git", "worktree", "remove", "--force", str(other)], cwd=ROOT,
                           check=False)
    medians = {name: statistics.median(values) for name, values in times.items()}
    ratios = sorted(a / b for a, b in zip(times["this tree"], times[args.rev]))
    what = (f"{args.rays:,} rays, {args.cells}^3 cells" if args.workload == "trace"
            else f"the {args.workload} workload")
    print(f"\n{what}, {args.threads} thread(s), {args.rounds} rounds, best of "
          f"{args.repeats} calls per process")
    print(f"median: this tree {medians['this tree'] * 1e3:.1f} ms, {args.rev} "
          f"{medians[args.rev] * 1e3:.1f} ms")
    print(f"this tree / {args.rev}: {medians['this tree'] / medians[args.rev]:.3f} "
          f"(per round {ratios[0]:.3f} to {ratios[-1]:.3f})")


if __name__ == "__main__":
    main()
