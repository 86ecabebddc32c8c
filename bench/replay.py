"""Replaying a ROS 2 bag: frames per second, against the same frames without the bag.

    python -m bench.replay [--frames 300] [--rounds 3]

Writes a bag (MCAP) of a robot turning and walking past the room scene
(``logsph_trace.ros_scene.walking_robot``): ``--frames`` 640 x 480 depth
frames (16UC1) at 30 Hz with their label images, camera info, odometry and
two people's gaze frames (one sample each per frame). Then times, on all
threads, into a 64 x 360 x 180 map, in ``--rounds`` alternated rounds
(the median and the range are reported):

- ``BagReplay`` with the label topic;
- ``BagReplay`` without it (``label_objects`` before each frame's gazes);
- the baseline: the same frames, already decoded, integrated with the same
  moves and camera poses, and the same gazes ranked as the replay ranks
  them (``gaze_objects`` without the objects' centroids, which events do
  not carry), without reading the bag;
- three A/Bs: the replay with the label topic with every ray's label vote
  sorted (``vote_every_ray``, as before votes were counted in runs), and
  with each transform looked up afresh (no memo in ``TransformTree``); the
  replay without it with ``label_objects``' labels in numpy's zeros.

Also, when scikit-image is installed, the time of ``label_objects`` on the
Motorcycle frame's map, and the first and second calls of
``integrate_depth``, ``label_objects`` and ``gaze_objects`` in a fresh
process whose kernels are all cached (what a first call costs beyond its
work: loading the cached kernels). Writes bench/results/replay.json and replay.md.
"""

import argparse
import contextlib
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numba
import numpy as np

import logsph_trace as lt
from bench.workload import write_results
from logsph_trace import objects
from logsph_trace.gaze import DEFAULT_HALF_ANGLE, _fixation_options, _ranked
from logsph_trace.ros import MAP_FROM_BASE, BagReplay, TransformTree
from logsph_trace.ros_scene import (
    PEOPLE,
    base_pose,
    box_centre,
    camera_pose,
    look_at,
    walking_robot,
)

GRID = (0.3, 10.0, 64, 360, 180)
BASELINE = "the same frames without the bag (decoded, same moves and gazes)"
TOPICS = ("/camera/depth", "/camera/camera_info", "base_link")


def baseline(frames, intrinsics, scene, steps):
    """The replay's work on frames already decoded: move, integrate, rank; seconds."""
    occupancy = lt.OccupancyGrid(lt.Grid(*GRID))
    mount = MAP_FROM_BASE @ camera_pose()
    start = time.perf_counter()
    before = None
    for step, (depth, labels) in enumerate(frames):
        pose = base_pose(step, steps)
        if before is not None:
            occupancy.move(MAP_FROM_BASE @ np.linalg.inv(before) @ pose @ MAP_FROM_BASE.T)
        before = pose
        occupancy.integrate_depth(depth, intrinsics, pose=mount, depth_scale=0.001,
                                  labels=labels)
        for eyes, box in PEOPLE.values():
            gaze = MAP_FROM_BASE @ np.linalg.inv(pose) @ look_at(eyes, box_centre(scene, box))
            _ranked(occupancy, gaze[:3, 3], gaze[:3, 2], DEFAULT_HALF_ANGLE, None, None, {},
                    _fixation_options(), centroids=False)
    return time.perf_counter() - start


def vote_every_ray(occupancy, hits, labels, n_rho):
    """``OccupancyGrid._vote`` without runs: every ray's vote sorted (two lexsorts), the A/B."""
    hit = hits >= 0
    cells, votes = hits[hit], labels[hit]
    if not cells.size:
        return
    if n_rho:  # column-major, as the walk gives them
        column, shell = np.divmod(cells, n_rho)
        cells = shell * (occupancy.grid.n_theta * occupancy.grid.n_phi) + column
    order = np.lexsort((votes, cells))
    cells, votes = cells[order], votes[order]
    new = np.ones(cells.shape[0], dtype=bool)
    new[1:] = (cells[1:] != cells[:-1]) | (votes[1:] != votes[:-1])
    starts = np.flatnonzero(new)
    counts = np.diff(np.append(starts, cells.shape[0]))
    cells, votes = cells[starts], votes[starts]
    order = np.lexsort((votes, -counts, cells))
    first = np.ones(order.shape[0], dtype=bool)
    first[1:] = cells[order][1:] != cells[order][:-1]
    winners = order[first]
    occupancy._labels.reshape(-1)[cells[winners]] = votes[winners]


@contextlib.contextmanager
def replaced(owner, name, value):
    """``owner.name`` is ``value`` in the block (an A/B's other side)."""
    saved = getattr(owner, name)
    setattr(owner, name, value)
    try:
        yield
    finally:
        setattr(owner, name, saved)


# The A/Bs: a replay with one shortcut switched off.
AB = (("A/B: with the label topic, every ray's vote sorted", "/camera/labels",
       lt.OccupancyGrid, "_vote", vote_every_ray),
      ("A/B: with the label topic, each transform looked up afresh", "/camera/labels",
       TransformTree, "_to_root", TransformTree._walk_to_root),
      ("A/B: without it, label_objects' labels in numpy's zeros", None, objects,
       "_untouched_zeros", lambda shape, dtype: np.zeros(shape, dtype=dtype)))


def decoded_frames(recording):
    """The recording's depth and label images as arrays, in order."""
    depth = [m.data.view(np.uint16).reshape(m.height, m.width)
             for _, topic, m in recording.messages if topic == "/camera/depth"]
    labels = [m.data.view(np.uint16).reshape(m.height, m.width)
              for _, topic, m in recording.messages if topic == "/camera/labels"]
    return list(zip(depth, labels))


def time_replay(bag, labels):
    """Seconds of one replay, and its summary."""
    replay = BagReplay(bag, *TOPICS, labels=labels, grid=lt.Grid(*GRID))
    start = time.perf_counter()
    for _ in replay:
        pass
    return time.perf_counter() - start, replay.summary


def label_objects_ms(repeats=20):
    """Best and median ms of label_objects on the Motorcycle frame's 64 x 360 x 180 map."""
    try:
        from logsph_trace import datasets

        frame = datasets.motorcycle()
    except ImportError:
        return None
    occupancy = lt.OccupancyGrid(lt.Grid(0.3, 8.0, 64, 360, 180))
    occupancy.integrate_depth(frame.depth, frame.intrinsics)
    times = []
    for _ in range(repeats + 1):
        start = time.perf_counter()
        lt.label_objects(occupancy, replace=True)
        times.append(time.perf_counter() - start)
    return min(times[1:]) * 1e3, float(np.median(times[1:])) * 1e3


# Run in a fresh Python after the timed runs, with the kernels in the cache.
FIRST_CALLS = """
import json, sys, time
start = time.perf_counter()
import numpy as np
import logsph_trace as lt
from logsph_trace import datasets
times = {"import logsph_trace": time.perf_counter() - start}
frame = datasets.motorcycle()
occupancy = lt.OccupancyGrid(lt.Grid(0.3, 8.0, 64, 360, 180))
calls = (("integrate_depth", lambda: occupancy.integrate_depth(frame.depth, frame.intrinsics)),
         ("label_objects", lambda: lt.label_objects(occupancy, replace=True)),
         ("gaze_objects", lambda: lt.gaze_objects(occupancy, [0.0, 0.0, 0.0], [0.0, 0.0, 1.0])))
for name, call in calls + calls:
    start = time.perf_counter()
    call()
    times.setdefault(name, []).append(time.perf_counter() - start)
json.dump(times, sys.stdout)
"""


def first_calls():
    """Seconds of the first and second calls in a fresh process (kernels cached), or None."""
    try:
        import skimage  # noqa: F401  (the Motorcycle frame)
    except ImportError:
        return None
    # Twice: the first process compiles and caches what the replays above did
    # not use (the cone of a gaze from the map's centre); the second is timed.
    for _ in range(2):
        done = subprocess.run([sys.executable, "-c", FIRST_CALLS], capture_output=True,
                              text=True, check=True, cwd=Path(__file__).resolve().parent.parent)
    return json.loads(done.stdout)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=300)
    parser.add_argument("--rounds", type=int, default=3,
                        help="rounds of the three replays, alternated (default 3)")
    args = parser.parse_args(argv)
    steps = args.frames - 1
    recording, scene = walking_robot(steps=steps, shape=(480, 640), rate=30.0)
    intrinsics = next(m for _, t, m in recording.messages if t == "/camera/camera_info").k
    frames = decoded_frames(recording)
    with tempfile.TemporaryDirectory() as folder:
        bag = recording.write(Path(folder) / "walk")
        del recording
        size = sum(f.stat().st_size for f in bag.iterdir()) / 2**20
        small = walking_robot(steps=2, shape=(480, 640), rate=30.0)[0].write(
            Path(folder) / "warm")
        for labels in ("/camera/labels", None):  # compiles what the timed runs use
            time_replay(small, labels)
        baseline(frames[:3], intrinsics.reshape(3, 3), scene, steps)
        runs = {}
        for _ in range(args.rounds):  # the three alternated, so that noise falls on each
            for name, labels in (("with the label topic", "/camera/labels"),
                                 ("without it (label_objects)", None)):
                seconds, summary = time_replay(bag, labels)
                runs.setdefault(name, []).append((seconds, summary.frames, summary.gazes))
            seconds = baseline(frames, intrinsics.reshape(3, 3), scene, steps)
            runs.setdefault(BASELINE, []).append((seconds, len(frames), 2 * len(frames)))
            for name, topic, owner, attribute, other in AB:
                with replaced(owner, attribute, other):
                    seconds, summary = time_replay(bag, topic)
                runs.setdefault(name, []).append((seconds, summary.frames, summary.gazes))
    rows = {}
    for name, timings in runs.items():
        seconds = [t[0] for t in timings]
        fps = sorted(t[1] / t[0] for t in timings)
        rows[name] = {"seconds": seconds, "fps": float(np.median(fps)), "fps_low": fps[0],
                      "fps_high": fps[-1], "frames": timings[0][1], "gazes": timings[0][2]}
    labelling = label_objects_ms()
    first = first_calls()
    lines = [f"{lt.Grid(*GRID)}, {numba.get_num_threads()} threads; a bag of {args.frames} "
             f"640 x 480 depth frames (16UC1) at 30 Hz with label images, odometry and two "
             f"people's gazes ({size:.0f} MB, MCAP)", "",
             f"| replay | frames a second, median of {args.rounds} | lowest, highest | frames "
             "| gazes |",
             "|---|---:|---:|---:|---:|"]
    for name, r in rows.items():
        lines.append(f"| {name} | {r['fps']:.1f} | {r['fps_low']:.1f}, {r['fps_high']:.1f} "
                     f"| {r['frames']} | {r['gazes']} |")
    if labelling is not None:
        lines += ["", f"`label_objects` on the Motorcycle frame's 64 x 360 x 180 map: best "
                      f"{labelling[0]:.1f} ms, median {labelling[1]:.1f} ms (20 runs)"]
    if first is not None:
        lines += ["", "A fresh process with the kernels cached, on the Motorcycle frame's map: "
                      f"`import logsph_trace` {first.pop('import logsph_trace') * 1e3:.0f} ms;",
                  "", "| call | first, ms | second, ms |", "|---|---:|---:|"]
        lines += [f"| {name} | {one * 1e3:.0f} | {two * 1e3:.1f} |"
                  for name, (one, two) in first.items()]
    write_results("replay", argv, "\n".join(lines),
                  {"threads": numba.get_num_threads(), "frames": args.frames,
                   "bag_mb": size, "rows": rows,
                   "label_objects_ms": None if labelling is None else
                   {"best": labelling[0], "median": labelling[1]},
                   "first_calls_s": first})


if __name__ == "__main__":
    main()
