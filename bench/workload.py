"""The benchmark workload, shared by the script and the pytest-benchmark suite.

A BVM-like log-spherical grid (rho 0.1..10 m, full circle, full elevation) and
rays whose origins are uniform in its ball and whose directions are uniform on
the sphere: a person standing anywhere in the robot's map, looking anywhere.
The Amanatides-Woo reference traces the same rays through the cube of equal
voxel count that holds the ball.
"""

import time

import numpy as np

import logsph_trace as lt
from logsph_trace.cartesian import CartesianGrid

RHO_MIN = 0.1
RHO_MAX = 10.0


def make_grid(cells=128):
    return lt.Grid(RHO_MIN, RHO_MAX, cells, cells, cells, spacing="log")


def make_box(cells=128):
    return CartesianGrid((-RHO_MAX,) * 3, (RHO_MAX,) * 3, (cells,) * 3)


def make_rays(n_rays=100_000, seed=0):
    rng = np.random.default_rng(seed)
    directions = rng.normal(size=(n_rays, 3))
    directions /= np.linalg.norm(directions, axis=1)[:, None]
    radial = rng.normal(size=(n_rays, 3))
    radial /= np.linalg.norm(radial, axis=1)[:, None]
    origins = radial * RHO_MAX * rng.random(n_rays)[:, None] ** (1 / 3)
    return origins, directions


def prime_memory(megabytes):
    """Write once to every page of ``megabytes`` of fresh memory, then free it.

    A virtual machine's first write to memory its guest has never used costs
    the host a fault of its own: on a 2-core cloud virtual machine, 200 MB
    took 0.21 s to fault in the first time and 0.03 s each time after. A
    fresh process timed there measures that, not the library, and worst on many threads, whose
    faults the host takes one at a time. The benchmarks that time calls into
    fresh output first write to about twice what they will allocate at
    once; freed, the pages go back to the guest's free lists, where the
    process's later allocations find them.

    Returns (megabytes, seconds) for :func:`prime_note`, or None where
    ``megabytes`` is not positive (nothing primed).
    """
    if not megabytes > 0:
        return None
    start = time.perf_counter()
    block = np.empty(int(megabytes * 2**20), dtype=np.uint8)
    block[::4096] = 1
    del block
    return megabytes, time.perf_counter() - start


def prime_note(primed):
    """The table line that says how much memory was primed (``prime_memory``), and in what time."""
    if primed is None:
        return ("memory not primed (--prime 0): a fresh virtual machine's first touch is in "
                "the figures")
    megabytes, seconds = primed
    return (f"memory primed: {megabytes:,.0f} MB written once before timing, in {seconds:.2f} s "
            "(a virtual machine's first write to fresh memory costs far more than a later one)")


def add_prime_option(parser, default):
    """Add ``--prime MB`` (None: ``default``, the benchmark's own size; 0: none) to ``parser``."""
    parser.add_argument("--prime", type=float, default=None,
                        help=f"MB of memory to write once before timing (default: {default}; "
                             "0: none; see bench.workload.prime_memory)")


def best_time(func, repeats):
    """(shortest wall time of ``repeats`` calls, the last result)."""
    best = np.inf
    result = None
    for _ in range(repeats):
        start = time.perf_counter()
        result = func()
        best = min(best, time.perf_counter() - start)
    return best, result


def timed(call, best=None, keep=lambda result: None):
    """Run ``call`` once with the phase clock on; return its record (``seconds``,
    ``phases``, ``kept``: ``keep(result)``) if it beats ``best``, else ``best``."""
    from logsph_trace import _batching

    with _batching.phase_times() as phases:
        start = time.perf_counter()
        result = call()
        seconds = time.perf_counter() - start
    if best is None or seconds < best["seconds"]:
        return {"seconds": seconds, "phases": dict(phases), "kept": keep(result)}
    return best


def thread_arguments(description, repeats, argv, prime=None, **sizes):
    """Parse a benchmark's ``--threads`` and ``--repeats``, and an integer option per
    keyword of ``sizes`` (``rays=100_000``: ``--rays``, default 100,000); with
    ``prime`` (the default's words), ``--prime`` too (``add_prime_option``);
    return (args, thread counts)."""
    import argparse

    import numba

    parser = argparse.ArgumentParser(description=description)
    parser.add_argument("--threads", default=f"1,{numba.get_num_threads()}",
                        help="comma-separated thread counts (default: 1 and all)")
    parser.add_argument("--repeats", type=int, default=repeats)
    for name, default in sizes.items():
        parser.add_argument(f"--{name}", type=int, default=default)
    if prime is not None:
        add_prime_option(parser, prime)
    args = parser.parse_args(argv)
    return args, thread_counts(args.threads)


def thread_counts(text):
    """``"1,2,4"`` -> [1, 2, 4], always with 1 and capped at Numba's thread count."""
    import numba

    most = numba.get_num_threads()
    return sorted({1, *(min(int(t), most) for t in text.split(","))})


def motorcycle_points(sensor=(0.0, 0.0, 0.0)):
    """The Middlebury 2014 Motorcycle frame (``logsph_trace.datasets.motorcycle``) as
    points in a map's frame, the camera at ``sensor`` looking along +z with
    image-up along +y (``depth_to_points``' default pose, moved); pixels
    without depth dropped."""
    from logsph_trace import datasets

    frame = datasets.motorcycle()
    pose = (np.diag([-1.0, -1.0, 1.0]), np.asarray(sensor, dtype=np.float64))
    return lt.depth_to_points(frame.depth, frame.intrinsics, pose).points


def fresh_processes(code):
    """Run ``code`` in two fresh Pythons sharing one new Numba cache: the first
    finds it empty, the second finds what the first wrote. Returns the
    numbers each printed last, as two lists of floats."""
    import os
    import subprocess
    import sys
    import tempfile

    with tempfile.TemporaryDirectory() as cache:
        env = dict(os.environ, NUMBA_CACHE_DIR=cache)
        return [[float(value) for value in subprocess.run(
            [sys.executable, "-c", code], env=env, check=True, capture_output=True,
            text=True).stdout.split()] for _ in range(2)]


def environment():
    """The machine and versions a record was measured with (a dict), and one line for its page."""
    import os
    import platform

    import numba

    import logsph_trace

    cpu = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo") as stream:
            models = [line.split(":", 1)[1].strip() for line in stream
                      if line.startswith("model name")]
        cpu = models[0] if models else cpu
    except OSError:
        pass
    found = {"cpu": cpu, "cores": os.cpu_count(), "system": platform.system(),
             "python": platform.python_version(), "numpy": np.__version__,
             "numba": numba.__version__, "logsph_trace": logsph_trace.__version__}
    line = (f"Machine: {found['cpu']}, {found['cores']} cores, {found['system']}; Python "
            f"{found['python']}, numpy {found['numpy']}, numba {found['numba']}.")
    return found, line


def write_results(name, argv, text, record, out=None):
    """Print ``text`` and write the benchmark's record, each file atomically.

    ``<name>.json`` holds ``record`` with the command, the date, the machine
    and the versions; ``<name>.md`` the command, the machine line, then
    ``text``. ``out``: the JSON file's path (default bench/results/<name>.json);
    the page goes beside it. Both are overwritten on every run.
    """
    import json
    import sys
    from pathlib import Path

    from logsph_trace._files import write_text

    out = Path(out) if out is not None else (
        Path(__file__).resolve().parent / "results" / f"{name}.json")
    arguments = argv if argv is not None else sys.argv[1:]
    command = (f"python -m bench.{name} " + " ".join(arguments)).strip()
    machine, line = environment()
    print(text)
    out.parent.mkdir(parents=True, exist_ok=True)
    stamped = {"command": command, "date": time.strftime("%Y-%m-%d %H:%M:%S %Z"),
               "machine": machine, **record}
    write_text(out, json.dumps(stamped, indent=2) + "\n")
    write_text(out.with_suffix(".md"), f"`{command}`\n\n{line}\n\n{text}\n")
