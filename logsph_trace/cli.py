"""The ``logsph-trace`` command line.

    logsph-trace demo [--synthetic]
    logsph-trace look DEPTH --intrinsics FX FY CX CY [--depth-scale S] [--labels FILE]
                      [--names FILE] --eyes X Y Z (--pitch-yaw P Y | --gaze DX DY DZ)
                      [--half-angle DEG] [--json] [--html FILE]
    logsph-trace replay BAG --depth TOPIC --camera-info TOPIC --base-frame FRAME
                        [--labels TOPIC] [--gaze-frames 'gaze_*'] [--half-angle DEG]
                        --out EVENTS.jsonl
    logsph-trace warmup
    logsph-trace trace --grid 0.3,10,64,360,180 --origin 0 2 2 --direction -0.3 -0.01 0
                       [--cone 5] [--format table|json|csv]
    logsph-trace trace --rays rays.npy --out traces.npz
    logsph-trace bench [--quick]

Errors (bad arguments, unreadable or unwritable files, invalid geometry, not
enough memory) are one line on stderr and exit status 2, never a traceback;
warnings (depth that looks like millimetres, say) are one line each;
Ctrl-C is one line and exit status 130. Angles are in degrees, in and out.
Output files are written atomically: a failure leaves no partial file and
keeps an older file of the same name.
"""

import argparse
import json
import math
import os
import re
import shutil
import sys
import time
import warnings
from pathlib import Path

import numpy as np

OUT_DIR = Path("logsph-trace-out")
CHUNK_RAYS = 65_536  # rays per batch chunk: bounds the memory of a large batch


class CliError(Exception):
    """An error to report in one line."""


def _grid_spec(spec):
    """``RHO_MIN,RHO_MAX,N_RHO,N_THETA,N_PHI[,SPACING]`` -> the grid options."""
    fields = [field.strip() for field in spec.split(",")]
    if len(fields) not in (5, 6):
        raise CliError(f"--grid takes RHO_MIN,RHO_MAX,N_RHO,N_THETA,N_PHI[,SPACING], got {spec!r}")
    try:
        rho = [float(fields[0]), float(fields[1])]
        cells = [int(fields[2]), int(fields[3]), int(fields[4])]
    except ValueError:
        raise CliError(f"--grid takes numbers: RHO_MIN,RHO_MAX,N_RHO,N_THETA,N_PHI, got {spec!r}") \
            from None
    return rho, cells, (fields[5] if len(fields) == 6 else "log")


def _grid(args):
    from .grid import Grid

    if getattr(args, "grid", None):
        args.rho, args.cells, args.spacing = _grid_spec(args.grid)
    for option, values, full in (("--theta-range", args.theta_range, 360.0),
                                 ("--phi-range", args.phi_range, 180.0)):
        low, high = values
        if max(abs(low), abs(high)) <= 2 * math.pi and high - low <= 2 * math.pi:
            _warn(f"{option} {low:g} {high:g} is in degrees: a {high - low:.3g}-degree range. "
                  f"Were those radians? The full range is {-full / 2:g} {full / 2:g}")
    theta = tuple(np.radians(args.theta_range))
    phi = tuple(np.radians(args.phi_range))
    return Grid(args.rho[0], args.rho[1], args.cells[0], args.cells[1], args.cells[2],
                theta_range=theta, phi_range=phi, spacing=args.spacing)


def _add_grid_options(parser):
    grid = parser.add_argument_group(
        "grid (default: the bounds and cells of the paper's worked example, decimetres; "
        "add --spacing paper for its Eq. 3 spacing)")
    grid.add_argument("--grid", metavar="SPEC",
                      help="RHO_MIN,RHO_MAX,N_RHO,N_THETA,N_PHI[,SPACING] (spacing default log); "
                           "overrides --rho, --cells and --spacing")
    grid.add_argument("--rho", nargs=2, type=float, default=[10.0, 80.0], metavar=("MIN", "MAX"),
                      help="radial bounds (default 10 80)")
    grid.add_argument("--cells", nargs=3, type=int, default=[10, 36, 18],
                      metavar=("N_RHO", "N_THETA", "N_PHI"), help="cell counts (default 10 36 18)")
    grid.add_argument("--spacing", choices=["log", "paper", "uniform"], default="log",
                      help="radial spacing (default log, as for --grid)")
    grid.add_argument("--theta-range", nargs=2, type=float, default=[-180.0, 180.0],
                      metavar=("MIN", "MAX"), help="azimuth range in degrees")
    grid.add_argument("--phi-range", nargs=2, type=float, default=[-90.0, 90.0],
                      metavar=("MIN", "MAX"), help="elevation range in degrees")


def _warn(message):
    print(f"logsph-trace: warning: {message}", file=sys.stderr)


def _show_warning(message, category, filename, lineno, file=None, line=None):
    """Show a Python warning as the command's own one line."""
    _warn(str(message))


def _read_csv(path):
    """Read an (m, 6) CSV of numbers, with or without one header row."""
    with open(path, encoding="utf-8-sig") as stream:  # a byte-order mark is no data
        first = stream.readline()
    try:
        [float(field) for field in first.split(",")]
        header = 0
    except ValueError:
        header = 1  # a row of column names
    return np.loadtxt(path, delimiter=",", ndmin=2, skiprows=header, encoding="utf-8-sig")


def _load_rays(path):
    """Open the (m, 6) rays of a .npy (memory-mapped, read a chunk at a time) or .csv file."""
    path = Path(path)
    if not path.is_file():
        raise CliError(f"no such rays file: {path}")
    try:
        if path.suffix == ".npy":
            rays = np.load(path, mmap_mode="r", allow_pickle=False)
        elif path.suffix == ".csv":
            rays = _read_csv(path)  # no lazy CSV reader: read whole
        else:
            raise CliError(f"rays file must be .npy or .csv, got {path.name}")
    except CliError:
        raise
    except Exception as error:  # noqa: BLE001 - any reader failure is one line
        raise CliError(f"cannot read {path}: {error}") from None
    if rays.dtype.kind not in "iuf":  # complex, text, objects: name the dtype, not the data
        raise CliError(f"{path} must hold real numbers, got dtype {rays.dtype}")
    if rays.ndim != 2 or rays.shape[1] != 6:
        raise CliError(f"{path} must hold an (m, 6) array of origin + direction, got {rays.shape}")
    return rays


def _trace_batch(grid, rays, out, progress):
    """Trace in chunks and write one CSR .npz, holding one chunk in memory at a time.

    Each chunk's segments are appended to temporary files; the .npz is then
    written from memory maps of them, which numpy copies in buffered pieces.
    Besides one chunk, memory holds only the per-ray offsets.
    """
    import tempfile

    from tqdm import tqdm

    from ._files import atomic_write, write_npz
    from .trace import trace_many

    total = rays.shape[0]
    counts = np.zeros(total, dtype=np.int64)
    start = time.perf_counter()
    layout = {"cells": (np.int32, (3,)), "t_enter": (np.float64, ()), "t_exit": (np.float64, ())}
    with tempfile.TemporaryDirectory(dir=Path(out).resolve().parent) as scratch:
        files = {name: open(Path(scratch) / f"{name}.bin", "wb") for name in layout}
        # A terminal that reports no size (a bare pty) gets 80x24: tqdm would
        # hide its bar on a screen 0 lines high.
        screen = shutil.get_terminal_size()
        bar = tqdm(total=total, unit="ray", unit_scale=True, disable=not progress,
                   file=sys.stderr, ncols=screen.columns, nrows=screen.lines)
        try:
            for first in range(0, total, CHUNK_RAYS):
                try:
                    chunk = trace_many(grid,
                                       np.ascontiguousarray(rays[first:first + CHUNK_RAYS]))
                except ValueError as error:  # number the bad row in the file, not the chunk
                    raise CliError(re.sub(r"\brow (\d+)",
                                          lambda m: f"row {int(m.group(1)) + first}",
                                          str(error))) from None
                counts[first:first + len(chunk)] = chunk.counts
                for name, handle in files.items():
                    getattr(chunk, name).tofile(handle)
                bar.update(len(chunk))
        finally:
            bar.close()
            for handle in files.values():
                handle.close()
        offsets = np.zeros(total + 1, dtype=np.int64)
        np.cumsum(counts, out=offsets[1:])
        segments = int(offsets[-1])
        arrays = {}
        for name, (dtype, tail) in layout.items():
            if segments == 0:
                arrays[name] = np.empty((0,) + tail, dtype=dtype)
            else:
                arrays[name] = np.memmap(Path(scratch) / f"{name}.bin", dtype=dtype, mode="r",
                                         shape=(segments,) + tail)
        with atomic_write(out) as stream:
            write_npz(stream, offsets=offsets, **arrays)
        del arrays  # release the maps before the scratch folder goes
    return total, segments, time.perf_counter() - start


def _print_rows(rows, columns, fmt, stream):
    """Write ``rows`` (dicts) as JSON, CSV, or a table of ``columns`` ((name, table format))."""
    if fmt == "json":
        json.dump(rows, stream, indent=1)
        stream.write("\n")
    elif fmt == "csv":
        stream.write(",".join(name for name, _ in columns) + "\n")
        for row in rows:
            stream.write(",".join(repr(row[name]) for name, _ in columns) + "\n")
    else:
        widths = [len(format(rows[0][name], spec)) if rows else len(name) for name, spec in columns]
        header = (f"{name:>{max(w, len(name))}}" for (name, _), w in zip(columns, widths))
        stream.write(" ".join(header)
                     + "\n")
        for row in rows:
            stream.write(" ".join(f"{format(row[name], spec):>{max(w, len(name))}}"
                                  for (name, spec), w in zip(columns, widths)) + "\n")


def print_trace(result, fmt, stream):
    """Write one ray's cells as a table, JSON or CSV."""
    rows = [
        {"i": int(c[0]), "j": int(c[1]), "k": int(c[2]), "t_enter": float(a), "t_exit": float(b)}
        for c, a, b in zip(result.cells, result.t_enter, result.t_exit)
    ]
    columns = [("i", "4d"), ("j", "4d"), ("k", "4d"), ("t_enter", "10.4f"), ("t_exit", "10.4f")]
    if fmt == "table" and not rows:
        stream.write("0 cells: the ray misses the grid\n")
        return
    _print_rows(rows, columns, fmt, stream)


def _print_cone(cone, fmt, stream):
    rows = [{"i": int(c[0]), "j": int(c[1]), "k": int(c[2]), "weight": float(w),
             "t_first": float(t)} for c, w, t in zip(cone.cells, cone.weights, cone.t_first)]
    if fmt == "table":
        stream.write(f"{cone.directions.shape[0]} rays; {len(rows)} cells\n")
    columns = [("i", "4d"), ("j", "4d"), ("k", "4d"), ("weight", "9.5f"), ("t_first", "10.4f")]
    _print_rows(rows, columns, fmt, stream)


def cmd_trace(args):
    """``logsph-trace trace``: one ray, a gaze cone, or a batch file."""
    from ._batching import PARALLEL_MIN_RAYS
    from ._files import npz_path
    from .cone import trace_cone
    from .trace import trace, trace_many

    grid = _grid(args)
    cone = args.cone is not None
    if args.rays:
        if args.origin or args.direction or cone:
            raise CliError("--rays traces a batch: leave out --origin, --direction and --cone")
        if not args.out:
            raise CliError("--rays needs --out FILE.npz")
        out = npz_path(args.out)
        if not out.resolve().parent.is_dir():
            raise CliError(f"--out: no such directory: {out.parent}")
        rays = _load_rays(args.rays)
        # Compile (and say so, on a first run) before the progress bar starts:
        # the serial pass, and the parallel path if the batch is large enough
        # to take it.
        for n in (1024, PARALLEL_MIN_RAYS) if len(rays) >= PARALLEL_MIN_RAYS else (1024,):
            trace_many(grid, np.zeros((n, 3)), np.ones((n, 3)))
        progress = not args.quiet and sys.stderr.isatty()  # no \r frames in a log file
        count, segments, seconds = _trace_batch(grid, rays, out, progress=progress)
        print(f"{count:,} rays, {segments:,} segments in {seconds:.2f} s -> {out}")
        return 0
    if args.origin is None or args.direction is None:
        raise CliError("give --origin X Y Z and --direction X Y Z, or --rays FILE")
    if args.out:
        raise CliError("--out writes a batch's traces: it needs --rays FILE (one ray or cone "
                       "is printed; --format json or csv for a file)")
    if cone:
        if not 0.0 <= args.cone < 90.0:
            raise CliError(f"--cone must be a half-angle in [0, 90) degrees, got {args.cone:g}")
        with warnings.catch_warnings():  # degrees were typed: radians came from np.radians
            warnings.simplefilter("ignore")
            result = trace_cone(grid, args.origin, args.direction, np.radians(args.cone))
        _print_cone(result, args.format, sys.stdout)
    else:
        print_trace(trace(grid, args.origin, args.direction), args.format, sys.stdout)
    return 0


def cmd_demo(args):
    """``logsph-trace demo``: the main job on the real Motorcycle frame (or ``--synthetic``)."""
    try:
        import matplotlib
    except ImportError:
        raise CliError("the demo draws figures with matplotlib: pip install "
                       "'logsph_trace[demo]'") from None
    matplotlib.use("Agg")
    from . import demo

    if args.synthetic:
        demo.run_synthetic(args.out)
        return 0
    try:
        demo.run(args.out)
    except ImportError as error:
        raise CliError(f"{error} (the demo needs: pip install 'logsph_trace[demo]')") from None
    return 0


def _read_names(path):
    """Read a JSON object of label -> name (``{"1": "motorcycle"}``)."""
    try:
        with open(path, encoding="utf-8-sig") as stream:
            names = json.load(stream)
    except FileNotFoundError:
        raise CliError(f"no such names file: {path}") from None
    except (OSError, ValueError) as error:
        raise CliError(f"cannot read {path} as JSON: {error}") from None
    if not isinstance(names, dict):
        raise CliError(f"{path} must hold a JSON object of label -> name, like "
                       f'{{"1": "motorcycle"}}, got a {type(names).__name__}')
    try:
        return {int(label): str(name) for label, name in names.items()}
    except ValueError:
        raise CliError(f"{path}: labels must be whole numbers, got "
                       f"{sorted(names)[:3]}") from None


def _look_grid(args, depth_points):
    """Return the map's grid: --grid, or 0.3 m to past the farthest point, 64 x 360 x 180."""
    from .grid import Grid

    if args.grid:
        rho, cells, spacing = _grid_spec(args.grid)
        return Grid(rho[0], rho[1], *cells, spacing=spacing)
    farthest = float(np.max(np.linalg.norm(depth_points, axis=1))) if len(depth_points) else 0.0
    if not farthest > 0.3:
        raise CliError(f"the depth image has no point beyond 0.3 m (the farthest is "
                       f"{farthest:.3g} m): is it in metres? (--depth-scale)")
    return Grid(0.3, math.ceil(farthest * 1.05 * 2) / 2, 64, 360, 180)


def _look_inputs(args, read_image):
    """Read and check ``look``'s depth image, labels (or None) and names (or None)."""
    if args.names and not args.labels:
        raise CliError("--names names the labels of --labels: give --labels FILE too")
    if not 0.0 <= args.half_angle < 90.0:
        raise CliError(f"--half-angle must be in [0, 90) degrees, got {args.half_angle:g}")
    depth = read_image(args.depth, "depth")
    labels = read_image(args.labels, "labels") if args.labels else None
    if labels is not None:
        if labels.shape != depth.shape:
            raise CliError(f"--labels must match the depth image's {depth.shape[1]} x "
                           f"{depth.shape[0]} pixels, got {labels.shape[1]} x {labels.shape[0]}")
        if labels.dtype.kind not in "iu":
            raise CliError(f"--labels must hold whole numbers, got {labels.dtype}")
    return depth, labels, _read_names(args.names) if args.names else None


def _look_row(hit, names, camera_from_map):
    """One ``look`` result: the object, its name (with ``names``), probability, point, distance."""
    row = {"object": hit.id}
    if names is not None:
        row["name"] = hit.name
    row.update(probability=hit.probability,
               point=[round(v, 4) for v in (camera_from_map @ hit.point).tolist()],
               distance=hit.distance)
    return row


def cmd_look(args):
    """``logsph-trace look``: rank the objects a gaze may land on, in a depth image."""
    from . import OccupancyGrid, depth_to_points, fit_plane, gaze_objects, label_objects
    from .demo import CAMERA_FROM_MAP
    from .images import read_image
    from .sensor import gaze_from_pitch_yaw, gaze_from_vector

    depth, labels, names = _look_inputs(args, read_image)
    scan = depth_to_points(depth, args.intrinsics, depth_scale=args.depth_scale)
    grid = _look_grid(args, scan.points)
    bvm = OccupancyGrid(grid).integrate_depth(depth, args.intrinsics,
                                              depth_scale=args.depth_scale, labels=labels)
    if labels is None:  # objects from the map itself: the floor and sparse cells left out
        exclude = grid.count_points(scan.points) < 3
        try:
            floor = fit_plane(scan.points, tolerance=0.03)
            exclude |= grid.count_points(scan.points[floor.inliers]) > 0
        except ValueError:
            pass  # no plane: nothing to leave out
        label_objects(bvm, exclude=exclude)
    if args.pitch_yaw is not None:
        pitch, yaw = args.pitch_yaw
        gaze = gaze_from_pitch_yaw(math.radians(pitch), math.radians(yaw), args.eyes)
    else:
        gaze = gaze_from_vector(args.gaze, args.eyes)
    objects = gaze_objects(bvm, gaze, half_angle=math.radians(args.half_angle), names=names)
    rows = [_look_row(hit, names, CAMERA_FROM_MAP) for hit in objects]
    if args.json:
        json.dump(rows, sys.stdout, indent=1)
        sys.stdout.write("\n")
    elif not rows:
        print(f"the gaze reaches no object (it stops at unlabelled cells with probability "
              f"{objects.unlabelled:.3f})")
    else:
        print(f"{'rank':>4} {'object':>6} {'name':<16} {'probability':>11} {'distance (m)':>12}  "
              f"point (m, camera frame)")
        for rank, row in enumerate(rows, 1):
            x, y, z = row["point"]
            print(f"{rank:4d} {row['object']:6d} {str(row.get('name') or '-'):<16} "
                  f"{row['probability']:11.3f} {row['distance']:12.2f}  "
                  f"({x:.2f}, {y:.2f}, {z:.2f})")
    if args.html:
        from .demo import MAP_AXES
        from .view import write_view

        try:
            write_view(args.html, bvm, gaze, objects, math.radians(args.half_angle), names=names,
                       axis_titles=MAP_AXES, title=f"{Path(args.depth).name}: the gaze")
        except ImportError as error:
            raise CliError(str(error)) from None
    return 0


def cmd_replay(args):
    """``logsph-trace replay``: a ROS 2 bag's gazes, ranked, as JSON Lines."""
    from ._files import atomic_write
    from .ros import BagReplay

    grid = None
    if args.grid:
        from .grid import Grid

        rho, cells, spacing = _grid_spec(args.grid)
        grid = Grid(*rho, *cells, spacing=spacing)
    try:
        replay = BagReplay(args.bag, args.depth, args.camera_info, args.base_frame,
                           labels=args.labels, gaze_frames=args.gaze_frames,
                           half_angle=math.radians(args.half_angle), grid=grid,
                           progress=not args.quiet and sys.stderr.isatty())
    except ImportError as error:
        raise CliError(str(error)) from None
    with atomic_write(args.out) as stream:
        for event in replay:
            stream.write((json.dumps(event.as_dict()) + "\n").encode("utf-8"))
    summary = replay.summary
    print(f"{args.bag}: {summary.line()}; events in {args.out}")
    if summary.truncated:
        print(f"logsph-trace: error: the bag ends early ({summary.truncated}); wrote the "
              f"{summary.events} events before it", file=sys.stderr)
        return 1
    return 0


def cmd_warmup(args):
    """``logsph-trace warmup``: compile and cache every CPU kernel now."""
    from ._jit import CACHE
    from .warmup import warmup

    seconds = warmup()
    where = ("cached for later processes" if CACHE
             else "not cached (LOGSPH_TRACE_CACHE=0): later processes compile again")
    print(f"logsph_trace: every CPU kernel ready in {seconds:.1f} s, {where}")
    return 0


def cmd_bench(args):
    """Run the Fig. 4 timing study: ``bench/fig4.py`` of the source checkout.

    The timing study lives beside the package, not in it, so it runs from a
    clone (an editable install included) wherever the command is started,
    and an installed wheel says what it needs instead. Only the package's own
    checkout is put on ``sys.path``, never the working directory.
    """
    checkout = Path(__file__).resolve().parents[1]
    if not (checkout / "bench" / "fig4.py").is_file():
        raise CliError("logsph-trace bench runs bench/fig4.py from the source repository, which "
                       "an installed wheel does not include: clone the repository, install it "
                       "with pip install -e, and run it there")
    if str(checkout) not in sys.path:
        sys.path.insert(0, str(checkout))
    from bench import fig4
    argv = ["--sizes", "8", "16", "32", "--repetitions", "20"] if args.quick else []
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    fig4.main(argv + ["--out", str(out / "fig4.json")])
    return 0


def build_parser():
    """Build the argparse parser of ``logsph-trace`` and its subcommands."""
    parser = argparse.ArgumentParser(
        prog="logsph-trace",
        description="Exact ray traversal of bounded log-spherical grids (gaze tracing).",
    )
    commands = parser.add_subparsers(dest="command", required=True)
    demo = commands.add_parser(
        "demo", help="which object a person looks at, on a real depth frame",
        description="Build the occupancy map of the Middlebury Motorcycle frame with its "
                    "objects, name what each of a few gazes lands on, and write a figure and "
                    "an interactive 3-D view (pip install 'logsph_trace[demo]').")
    demo.add_argument("--out", default=str(OUT_DIR), help="folder for the figures")
    demo.add_argument("--synthetic", action="store_true",
                      help="the paper's worked example and a gaze into a synthetic room instead "
                           "(no data needed)")
    demo.set_defaults(run=cmd_demo)
    look = commands.add_parser(
        "look", help="which object a gaze lands on, in a depth image",
        description="Build an occupancy map from one depth image and rank the objects a gaze "
                    "may land on. Positions and directions are in the camera's OpenCV frame "
                    "(x right, y down, z forward), in metres.")
    look.add_argument("depth", metavar="DEPTH",
                      help="the depth image: .npy, 16-bit PNG or PFM; metres unless "
                           "--depth-scale says otherwise; 0, NaN and inf are no depth")
    look.add_argument("--intrinsics", nargs=4, type=float, required=True,
                      metavar=("FX", "FY", "CX", "CY"), help="the depth camera's, in pixels")
    look.add_argument("--depth-scale", type=float, default=1.0, metavar="S",
                      help="metres per depth unit (0.001 for a millimetre PNG; default 1)")
    look.add_argument("--labels", metavar="FILE",
                      help="an instance image aligned with the depth (0: no object), .npy, PNG "
                           "or PFM; without it, objects are the map's connected groups of "
                           "occupied cells, the floor left out")
    look.add_argument("--names", metavar="FILE",
                      help='a JSON object naming the labels: {"1": "motorcycle", ...}')
    look.add_argument("--eyes", nargs=3, type=float, required=True, metavar=("X", "Y", "Z"),
                      help="the eyes' position in the camera's frame (m), as gaze estimators "
                           "give it")
    aim = look.add_mutually_exclusive_group(required=True)
    aim.add_argument("--pitch-yaw", nargs=2, type=float, metavar=("PITCH", "YAW"),
                     help="degrees, L2CS-Net's convention: 0 0 looks into the camera; positive "
                          "pitch up, positive yaw to the image's left")
    aim.add_argument("--gaze", nargs=3, type=float, metavar=("DX", "DY", "DZ"),
                     help="the gaze direction in the camera's frame (any length)")
    look.add_argument("--half-angle", type=float, default=5.0, metavar="DEG",
                      help="the gaze cone's half-angle: the estimator's error (default 5)")
    look.add_argument("--grid", metavar="SPEC",
                      help="RHO_MIN,RHO_MAX,N_RHO,N_THETA,N_PHI[,SPACING] in metres (default "
                           "0.3 m to just beyond the farthest point, 64 x 360 x 180)")
    look.add_argument("--json", action="store_true",
                      help="print a JSON list, most probable first")
    look.add_argument("--html", metavar="FILE.html",
                      help="also write an interactive 3-D view (pip install "
                           "'logsph_trace[view]')")
    look.set_defaults(run=cmd_look)
    replay = commands.add_parser(
        "replay", help="who looked at what in a ROS 2 bag, as JSON Lines",
        description="Replay a ROS 2 bag (MCAP or sqlite3; pip install 'logsph_trace[ros]'): "
                    "the depth images build the robot's egocentric map, moved by the "
                    "odometry on /tf, and at each gaze (a TF frame per person whose z axis is "
                    "the gaze, as ROS4HRI publishes them) the objects are ranked. One JSON "
                    "line per gaze and object: stamp, person, frame_id, object (0: none), "
                    "probability, point (m, in the base frame), distance (m).")
    replay.add_argument("bag", metavar="BAG", help="the rosbag2 folder")
    replay.add_argument("--depth", required=True, metavar="TOPIC",
                        help="sensor_msgs/Image depth: 16UC1 (mm) or 32FC1 (m)")
    replay.add_argument("--camera-info", required=True, metavar="TOPIC",
                        help="its sensor_msgs/CameraInfo")
    replay.add_argument("--base-frame", required=True, metavar="FRAME",
                        help="the robot's base frame (the map's and the events' frame)")
    replay.add_argument("--labels", metavar="TOPIC",
                        help="an instance-label image topic with the depth's stamps (0: no "
                             "object); without it, objects are found in the map")
    replay.add_argument("--gaze-frames", default="gaze_*", metavar="PATTERN",
                        help="the gaze frames on /tf (default 'gaze_*'; the wildcard's part "
                             "names the person)")
    replay.add_argument("--half-angle", type=float, default=5.0, metavar="DEG",
                        help="the gaze cone's half-angle, degrees (default 5)")
    replay.add_argument("--grid", metavar="SPEC",
                        help="RHO_MIN,RHO_MAX,N_RHO,N_THETA,N_PHI[,SPACING] in metres (default "
                             "0.3,10,64,360,180)")
    replay.add_argument("--out", required=True, metavar="EVENTS.jsonl")
    replay.add_argument("--quiet", action="store_true",
                        help="no progress bar (there is none unless stderr is a terminal)")
    replay.set_defaults(run=cmd_replay)
    trace = commands.add_parser("trace", help="trace one ray, a gaze cone, or a batch file")
    trace.add_argument("--origin", nargs=3, type=float, metavar=("X", "Y", "Z"),
                       help="where the ray starts, in the grid's frame and length unit (the "
                            "default grid is the paper's example, in decimetres)")
    trace.add_argument("--direction", nargs=3, type=float, metavar=("X", "Y", "Z"),
                       help="the ray's direction in the grid's frame (any length)")
    trace.add_argument("--cone", type=float, metavar="DEG", help="gaze cone half-angle in degrees")
    trace.add_argument("--format", choices=["table", "json", "csv"], default="table")
    trace.add_argument("--rays", metavar="FILE",
                       help="(m, 6) origin + direction: .npy (read a chunk at a time) or .csv")
    trace.add_argument("--out", metavar="FILE.npz", help="where a batch's traces go (--rays only)")
    trace.add_argument("--quiet", action="store_true",
                       help="no progress bar (there is none unless stderr is a terminal)")
    _add_grid_options(trace)
    trace.set_defaults(run=cmd_trace)
    warm = commands.add_parser(
        "warmup", help="compile and cache every kernel now, not on the first call",
        description="Compile every CPU kernel once and cache it beside the package, so that "
                    "the first real call is fast (for robots and container images; run it on "
                    "the machine and as the user that will use it).")
    warm.set_defaults(run=cmd_warmup)
    bench = commands.add_parser("bench", help="the timing study (Fig. 4)")
    bench.add_argument("--quick", action="store_true", help="small sizes, 20 repetitions")
    bench.add_argument("--out", default=str(OUT_DIR), help="folder for fig4.json/.md/.png")
    bench.set_defaults(run=cmd_bench)
    return parser


def main(argv=None):
    """Run ``logsph-trace`` with ``argv`` (default ``sys.argv[1:]``); returns the exit status."""
    parser = build_parser()
    args = parser.parse_args(argv)  # argparse reports its own errors in one line (exit 2)
    try:
        with warnings.catch_warnings():
            warnings.showwarning = _show_warning
            return args.run(args)
    except BrokenPipeError:
        # The reader (e.g. ``| head``) stopped reading: not our error, no traceback.
        # Point stdout at devnull so the interpreter's final flush cannot fail too.
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        return 1
    except KeyboardInterrupt:
        print("\nlogsph-trace: interrupted; no partial output was written", file=sys.stderr)
        return 130
    except MemoryError as error:
        print(f"logsph-trace: error: not enough memory: {error or 'allocation failed'}",
              file=sys.stderr)
        return 2
    except (CliError, ValueError, OSError) as error:
        print(f"logsph-trace: error: {error}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
