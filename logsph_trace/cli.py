"""The ``logsph-trace`` command line.

    logsph-trace demo
    logsph-trace trace --grid 0.3,10,64,360,180 --origin 0 2 2 --direction -0.3 -0.01 0
                       [--cone 5] [--format table|json|csv]
    logsph-trace trace --rays rays.npy --out traces.npz
    logsph-trace bench [--quick]

Errors (bad arguments, unreadable or unwritable files, invalid geometry, not
enough memory) are one line on stderr and exit status 2, never a traceback;
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

from ._files import save_figure

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


def _print_trace(result, fmt, stream):
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
    if cone:
        if not 0.0 <= args.cone < 90.0:
            raise CliError(f"--cone must be a half-angle in [0, 90) degrees, got {args.cone:g}")
        with warnings.catch_warnings():  # degrees were typed: radians came from np.radians
            warnings.simplefilter("ignore")
            result = trace_cone(grid, args.origin, args.direction, np.radians(args.cone))
        _print_cone(result, args.format, sys.stdout)
    else:
        _print_trace(trace(grid, args.origin, args.direction), args.format, sys.stdout)
    return 0


def cmd_demo(args):
    """Run the paper's worked example and a gaze cone into the synthetic scene.

    ``--real``: gazes at the parts of the real Motorcycle frame instead.
    """
    try:
        import matplotlib
    except ImportError:
        raise CliError("the demo draws figures with matplotlib: pip install 'logsph_trace[plot]'") \
            from None

    matplotlib.use("Agg")
    if args.real:
        return _real_demo(Path(args.out))
    from . import Grid, fixation_probability, gaze_targets, trace
    from .occupancy import OccupancyGrid
    from .plot import trace_figure
    from .scene import table_scene

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    start = time.perf_counter()
    grid = Grid.from_increments(10.0, 80.0, 10, d_theta=10.0, d_phi=10.0)
    origin, direction = (0.0, 20.0, 20.0), (-0.3, -0.01, 0.0)
    exact = trace(grid, origin, direction)
    bisect = trace(grid, origin, direction, method="bisect")
    print("The paper's worked example (Fig. 3), decimetres:")
    print(f"  gaze from {origin} along {direction}: {len(exact)} cells (exact); "
          f"Algorithm 1 with the paper's default_t reports {len(bisect)}")
    _print_trace(exact, "table", sys.stdout)
    figure = trace_figure(grid, origin, direction, exact, title="The paper's Fig. 3 example")
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
    _scene_figure(room, bvm, eyes, target, targets, points, out / "fig5_gaze_on_object.png")
    print(f"\nfigures written to {out}/ in {time.perf_counter() - start:.1f} s")
    return 0


def _scene_figure(grid, bvm, eyes, target, targets, points, path):
    import matplotlib.pyplot as plt

    from .plot import plot_cells

    fig = plt.figure(figsize=(7, 6))
    ax = fig.add_subplot(projection="3d")
    cloud = points[::97]
    ax.scatter(cloud[:, 0], cloud[:, 2], cloud[:, 1], s=0.5, color="tab:blue", alpha=0.3)
    occupied = bvm.occupied(0.6)
    near = occupied[grid.rho_edges[occupied[:, 0]] < 3.0]  # the wall behind would hide the rest
    hit = {tuple(c) for c in targets.cells.tolist()}
    near = np.array([c for c in near.tolist() if tuple(c) not in hit], dtype=np.int32)
    plot_cells(grid, near, ax=ax, color="tab:red", alpha=0.06)
    plot_cells(grid, targets.cells, ax=ax, color="tab:green", alpha=0.9)
    line = np.stack([eyes, eyes + 1.6 * (target - eyes)])
    ax.plot(line[:, 0], line[:, 2], line[:, 1], color="gold", linewidth=2)
    ax.set_xlim(-0.8, 1.2)  # the table, the object and the person
    ax.set_ylim(1.0, 2.4)
    ax.set_zlim(-0.8, 0.3)
    ax.view_init(elev=30, azim=-50)
    ax.set_xlabel("x")
    ax.set_ylabel("z")
    ax.set_zlabel("y (up)")
    ax.set_title("occupied cells nearer than 3 m (red; the wall is left out),\n"
                 "the gaze (yellow) and what it lands on (green)")
    save_figure(fig, path, dpi=90)
    plt.close(fig)


REAL_EYES = (-1.5, 0.3, 0.5)  # a person 1.5 m to the camera's left, metres


def _real_demo(out):
    """Integrate the Motorcycle frame with its parts boxed, gaze at each part."""
    from . import Grid, OccupancyGrid, depth_to_points, fit_plane, gaze_objects, label_objects

    try:
        from . import datasets

        frame = datasets.motorcycle()
    except ImportError as error:
        raise CliError(str(error)) from None
    out.mkdir(parents=True, exist_ok=True)
    start = time.perf_counter()
    grid = Grid(0.3, 8.0, 64, 360, 180)
    parts = datasets.MOTORCYCLE_PARTS
    labels = datasets.box_labels(frame.depth.shape, parts)
    bvm = OccupancyGrid(grid).integrate_depth(frame.depth, frame.intrinsics, labels=labels)
    stats = bvm.last_scan
    print(f"{frame.name}: {stats.rays:,} pixels with depth, {stats.invalid:,} without "
          f"(skipped) -> occupancy map {grid.shape}, rho 0.3-8 m")
    scan = depth_to_points(frame.depth, frame.intrinsics)
    of_points = labels[scan.pixels[:, 0], scan.pixels[:, 1]]
    eyes = np.array(REAL_EYES)
    print(f"A person at {REAL_EYES} m looks at each part through a 5-degree cone:")
    print(f"  {'looks at':>12} {'names':>12} {'probability':>12} {'reached at (m)':>15}")
    gazes = []
    for label, (name, _, _) in parts.items():
        target = np.median(scan.points[of_points == label], axis=0)
        objects = gaze_objects(bvm, eyes, target - eyes)
        named = parts[objects.top][0] if objects.top else "nothing"
        probability = objects.probabilities[0] if len(objects) else 0.0
        distance = objects.first_distances[0] if len(objects) else np.nan
        print(f"  {name:>12} {named:>12} {probability:12.3f} {distance:15.2f}")
        gazes.append((label, target, objects.top))
    # Without boxes: connected groups of occupied cells, leaving out the
    # floor (which every object touches) and cells with under 3 points.
    components = OccupancyGrid(grid).integrate_depth(frame.depth, frame.intrinsics)
    floor = fit_plane(scan.points, tolerance=0.03)
    exclude = grid.count_points(scan.points[floor.inliers]) > 0
    exclude |= grid.count_points(scan.points) < 3
    count = label_objects(components, exclude=exclude)
    print(f"Without boxes: label_objects finds {count} objects, leaving out the floor (fitted "
          f"{floor.offset:.2f} m below the camera) and cells with under 3 points.")
    point_labels = components.labels[tuple(grid.cell_of(scan.points).T)]
    tops = [gaze_objects(components, eyes, target - eyes).top for _, target, _ in gazes]
    for label in dict.fromkeys(tops):
        mine = point_labels == label
        distance = np.median(np.linalg.norm(scan.points[mine], axis=1)) if label else np.nan
        print(f"  {tops.count(label)} of the {len(tops)} gazes name object {label}: "
              f"{np.count_nonzero(mine):,} points, median {distance:.2f} m away")
    path = out / "motorcycle_gaze.png"
    _real_figure(frame, labels, parts, grid, bvm, scan, eyes, gazes, path)
    print(f"figure written to {path} in {time.perf_counter() - start:.1f} s")
    return 0


def _real_figure(frame, labels, parts, grid, bvm, scan, eyes, gazes, path):
    import matplotlib.pyplot as plt
    from matplotlib.patches import Rectangle

    colours = {label: colour for label, colour in
               zip(parts, ("tab:blue", "tab:orange", "tab:green", "tab:purple"))}
    fig, axes = plt.subplots(2, 2, figsize=(12, 8.5))
    image, depth, top, side = axes.ravel()
    image.imshow(frame.image)
    for label, (name, (c0, c1), (r0, r1)) in parts.items():
        image.add_patch(Rectangle((c0, r0), c1 - c0, r1 - r0, fill=False, linewidth=2,
                                  edgecolor=colours[label]))
        image.text(c0, r0 - 5, f"{label} {name}", color=colours[label], fontsize=9,
                   fontweight="bold")
    image.set_title("the left image and the parts boxed by hand (the labels)")
    shown = depth.imshow(np.where(frame.valid, frame.depth, np.nan), cmap="viridis")
    fig.colorbar(shown, ax=depth, label="Z (m)")
    depth.set_title("depth from the ground-truth disparity (white: none, skipped)")
    occupied = bvm.occupied(0.6)
    centres = grid.cell_centers(occupied)
    cell_labels = bvm.labels[tuple(occupied.T)]
    for ax, (a, b), names in ((top, (0, 2), ("x (m)", "z (m)")), (side, (2, 1),
                                                                   ("z (m)", "y (m, up)"))):
        ax.scatter(centres[:, a], centres[:, b], s=0.2, color="0.7")
        for label, colour in colours.items():
            mine = centres[cell_labels == label]
            ax.scatter(mine[:, a], mine[:, b], s=0.5, color=colour)
        for label, target, named in gazes:
            reach = np.stack([eyes, eyes + 1.15 * (target - eyes)])
            ax.plot(reach[:, a], reach[:, b], color=colours.get(named, "k"), linewidth=1.5)
        ax.plot(eyes[a], eyes[b], "k*", markersize=12)
        ax.set_xlabel(names[0])
        ax.set_ylabel(names[1])
        ax.set_aspect("equal")
    top.set_title("occupied cells from above, by label; each gaze in the colour of the part "
                  "it names", fontsize=9)
    side.set_title("the same from the side; the star is the person's eyes", fontsize=9)
    fig.tight_layout()
    save_figure(fig, path, dpi=80)
    plt.close(fig)


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
    demo = commands.add_parser("demo", help="the paper's example and a gaze into a scene")
    demo.add_argument("--out", default=str(OUT_DIR), help="folder for the figures")
    demo.add_argument("--real", action="store_true",
                      help="gazes at the parts of the real Middlebury Motorcycle frame "
                           "(needs scikit-image: pip install 'logsph_trace[data]')")
    demo.set_defaults(run=cmd_demo)
    trace = commands.add_parser("trace", help="trace one ray, a gaze cone, or a batch file")
    trace.add_argument("--origin", nargs=3, type=float, metavar=("X", "Y", "Z"))
    trace.add_argument("--direction", nargs=3, type=float, metavar=("X", "Y", "Z"))
    trace.add_argument("--cone", type=float, metavar="DEG", help="gaze cone half-angle in degrees")
    trace.add_argument("--format", choices=["table", "json", "csv"], default="table")
    trace.add_argument("--rays", metavar="FILE",
                       help="(m, 6) origin + direction: .npy (read a chunk at a time) or .csv")
    trace.add_argument("--out", metavar="FILE.npz", help="where a batch's traces go")
    trace.add_argument("--quiet", action="store_true",
                       help="no progress bar (there is none unless stderr is a terminal)")
    _add_grid_options(trace)
    trace.set_defaults(run=cmd_trace)
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
