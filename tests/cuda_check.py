"""Rays for the CUDA backend's equality checks, and the check itself.

Used in two ways: ``tests/test_cuda.py`` writes the rays and the CPU's
traces to a file and runs this module under Numba's CUDA simulator in a
subprocess (``python tests/cuda_check.py FILE``), where the per-ray code runs
as Python inside the simulated kernels; on a machine with a GPU the same
check runs in the test process itself.
"""

import sys
import tempfile
from pathlib import Path

import numpy as np
from singular import CLASSES, FACE_FAMILIES, face_rays, singular_rays, unit_at

import logsph_trace as lt

GRIDS = {
    "log": lambda: lt.Grid(0.3, 10.0, 12, 24, 12),
    "partial": lambda: lt.Grid(0.5, 6.0, 10, 16, 8, theta_range=(-1.0, 2.5),
                               phi_range=(-0.6, 1.1), spacing="uniform"),
    "paper": lambda: lt.Grid(1.0, 30.0, 12, 36, 18, spacing="paper"),
}


def cases(n_random, n_singular, seed=5):
    """{name: (grid name, origins, directions, t_max)} over every grid kind:
    random rays, a third of them cut short, each near-singular class, and
    each family of rays along faces."""
    rng = np.random.default_rng(seed)
    out = {}
    for name, make in GRIDS.items():
        grid = make()
        reach = 1.3 * grid.rho_max
        origins = rng.uniform(-reach, reach, (n_random, 3))
        directions = rng.normal(size=(n_random, 3))
        t_max = np.full(n_random, np.inf)
        t_max[::3] = rng.uniform(0.0, 2.0 * reach, t_max[::3].shape)
        out[f"{name} random"] = (name, origins, directions, t_max)
        for kind in CLASSES:
            o, d, _ = singular_rays(rng, grid, kind, n_singular, offsets=(0.0, 1e-12, 1e-6))
            out[f"{name} {kind}"] = (name, o, d, np.full(o.shape[0], np.inf))
        for family in FACE_FAMILIES:
            o, d = face_rays(rng, grid, family, n_singular)
            out[f"{name} {family}"] = (name, o, d, np.full(o.shape[0], np.inf))
    return out


def cpu_traces(all_cases):
    """The CPU's traces of every case, as arrays to save."""
    arrays = {}
    for key, (grid_name, origins, directions, t_max) in all_cases.items():
        traces = lt.trace_many(GRIDS[grid_name](), origins, directions, t_max=t_max)
        for field in ("offsets", "cells", "t_enter", "t_exit"):
            arrays[f"{key}|{field}"] = getattr(traces, field)
        arrays[f"{key}|rays"] = np.c_[origins, directions, t_max]
        arrays[f"{key}|grid"] = np.array(grid_name)
    return arrays


def point_cases(seed=7):
    """{name: (grid name, points)}: random points and points on every sphere,
    half-plane and cone of each grid (and an ulp off them), for ``cell_of``."""
    rng = np.random.default_rng(seed)
    out = {}
    for name, make in GRIDS.items():
        grid = make()
        rho = np.concatenate([grid.rho_edges, rng.uniform(0.0, 1.2 * grid.rho_max, 30)])
        theta = np.concatenate([grid.theta_edges, rng.uniform(-np.pi, np.pi, 30)])
        phi = np.concatenate([grid.phi_edges, rng.uniform(-np.pi / 2, np.pi / 2, 30)])
        n = 300
        r, t, p = rng.choice(rho, n), rng.choice(theta, n), rng.choice(phi, n)
        # The paper's frame: theta from +z towards +x, phi up from the x-z plane.
        points = np.c_[r * np.cos(p) * np.sin(t), r * np.sin(p), r * np.cos(p) * np.cos(t)]
        points = np.concatenate([points, np.nextafter(points, np.inf),
                                 np.nextafter(points, -np.inf)])
        out[f"{name} points"] = (name, points)
    return out


def cpu_cells(all_cases):
    """The CPU's ``Grid.cell_of`` of every case, as arrays to save."""
    arrays = {}
    for key, (grid_name, points) in all_cases.items():
        arrays[f"{key}|points"] = points
        arrays[f"{key}|cells"] = GRIDS[grid_name]().cell_of(points)
        arrays[f"{key}|grid"] = np.array(grid_name)
    return arrays


GAZES = (((0.4, 1.5, 1.2), (-0.1, -0.4, 1.0), 0.3), ((-2.0, 0.3, -1.0), (1.0, -0.1, 0.8), 0.0))


def map_cases(seed=8, n_points=45):
    """{name: (grid name, points (s, n, 3), sensors (s, 3), max_range)}: scans
    integrated in a row into one map, from the centre, 10 cm off it, from the
    egocentric gap and from inside the region; a third of each scan's points
    on the grid's spheres (the end cells the trace decides by its own
    crossing times). The last sensor sits in the gap on an edge's cone and
    half-plane, and the rest of its points lie on its own line through the
    centre: lines along faces (``singular.face_rays``)."""
    rng = np.random.default_rng(seed)
    out = {}
    for name, make in GRIDS.items():
        grid = make()
        phi, theta = grid.phi_edges[1], grid.theta_edges[1]
        unit = unit_at(phi, theta)
        on_faces = 2.0 ** np.floor(np.log2(grid.rho_min / 2)) * unit
        sensors = np.array([[0.0, 0.0, 0.0], [0.06, 0.08, 0.0],
                            [0.3 * grid.rho_min, 0.0, -0.2 * grid.rho_min],
                            [0.2 * grid.rho_max, 0.1 * grid.rho_max, 0.3 * grid.rho_max],
                            on_faces])
        scans = []
        for s, sensor in enumerate(sensors):
            points = rng.uniform(-grid.rho_max, grid.rho_max, (n_points, 3))
            on = points[: n_points // 3]
            radius = rng.choice(grid.rho_edges, on.shape[0])
            on *= (radius / np.linalg.norm(on, axis=1))[:, None]
            if s == len(sensors) - 1:
                reach = rng.uniform(-1.3, 1.3, (n_points - on.shape[0], 1)) * grid.rho_max
                points[on.shape[0]:] = sensor + reach * unit
            scans.append(points)
        out[f"{name} map"] = (name, np.array(scans), sensors, 0.8 * grid.rho_max)
    return out


def _map_steps(occupancy, scans, sensors, max_range):
    """Integrate the scans, decay, then look: {name: array} of what each step gives."""
    steps = {}
    for s, (points, sensor) in enumerate(zip(scans, sensors)):
        occupancy.integrate(points, sensor, max_range=max_range if s % 2 else None,
                            labels=np.arange(points.shape[0]) % 4)
        steps[f"after scan {s}"] = occupancy.to_host().log_odds.copy()
        steps[f"labels after scan {s}"] = occupancy.labels.copy()
    # A small depth image with holes, from a camera turned and moved off the centre.
    rng = np.random.default_rng(10)
    rho_max = occupancy.grid.rho_max
    depth = rng.uniform(0.02 * rho_max, 0.9 * rho_max, (9, 12))
    depth[rng.random(depth.shape) < 0.15] = np.nan
    turn = np.array([[0.0, 0.0, 1.0], [0.0, -1.0, 0.0], [1.0, 0.0, 0.0]])
    occupancy.integrate_depth(depth, (9.1, 8.7, 5.6, 4.3), (turn, [0.07, 0.02, -0.05]),
                              labels=rng.integers(0, 3, depth.shape))
    steps["after a depth image"] = occupancy.to_host().log_odds.copy()
    occupancy.decay(0.8)
    steps["decayed"] = occupancy.to_host().log_odds.copy()
    for g, (origin, direction, half_angle) in enumerate(GAZES):
        fixation = lt.fixation_probability(occupancy, origin, direction, half_angle=half_angle,
                                           n_rays=20, unknown=0.1)
        targets = lt.gaze_targets(occupancy, origin, direction, threshold=0.45)
        for field in ("cells", "values", "t_enter"):
            steps[f"fixation {g} {field}"] = getattr(fixation, field)
            steps[f"targets {g} {field}"] = getattr(targets, field)
    with tempfile.TemporaryDirectory() as folder:
        loaded = lt.OccupancyGrid.load(occupancy.save(Path(folder) / "map"),
                                       device=occupancy.device)
    assert loaded.device == occupancy.device
    steps["saved and loaded"] = loaded.to_host().log_odds
    return steps


def cpu_maps(all_cases):
    """The CPU map's steps of every case, as arrays to save."""
    arrays = {}
    for key, (grid_name, scans, sensors, max_range) in all_cases.items():
        steps = _map_steps(lt.OccupancyGrid(GRIDS[grid_name]()), scans, sensors, max_range)
        arrays.update({f"{key}|{step}": value for step, value in steps.items()})
        arrays[f"{key}|scans"] = scans
        arrays[f"{key}|sensors"] = sensors
        arrays[f"{key}|max_range"] = np.array(max_range)
        arrays[f"{key}|grid"] = np.array(grid_name)
    return arrays


def compare_map(arrays, key):
    """The same steps on a GPU map: maps and cells identical, values within 1e-12."""
    occupancy = lt.OccupancyGrid(GRIDS[str(arrays[f"{key}|grid"])](), device="cuda")
    steps = _map_steps(occupancy, arrays[f"{key}|scans"], arrays[f"{key}|sensors"],
                       float(arrays[f"{key}|max_range"]))
    problems = []
    for step, got in steps.items():
        want = arrays[f"{key}|{step}"]
        if got.shape != want.shape:
            problems.append(f"{key} {step}: shape {got.shape}, not {want.shape}")
        elif step.endswith(("values", "t_enter")):
            _close(got, want, f"{key} {step}", problems)
        elif not np.array_equal(got, want):
            problems.append(f"{key} {step}: differs")
    try:  # a GPU map does not move: a clear error, the map as it was
        occupancy.move(np.eye(4))
        problems.append(f"{key}: move on a GPU map raised nothing")
    except NotImplementedError as error:
        if "to_host" not in str(error):
            problems.append(f"{key}: move's error does not say what to do: {error}")
    return problems


def gpu_input_cases(seed=9, n=60):
    """{name: (origins, directions, t_max)} for inputs already on the GPU: random
    rays on the log grid as float64 and float32, one combined (m, 6) array, and
    bad rows (NaN, an origin too long to square, a zero direction, a negative
    t_max) whose errors must read as the CPU's; and one origin or one direction
    for every ray (given to the GPU as its one row)."""
    rng = np.random.default_rng(seed)
    origins = rng.uniform(-13.0, 13.0, (n, 3))
    directions = rng.normal(size=(n, 3))
    t_max = rng.uniform(0.0, 26.0, n)
    t_max[::4] = np.inf
    bad = {}
    for what, name, row, value in (("nan origin", "origins", 7, [np.nan, 0.0, 1.0]),
                                   ("huge origin", "origins", 5, [1e200, 0.0, 0.0]),
                                   ("inf direction", "directions", 3, [0.0, -np.inf, 0.0]),
                                   ("zero direction", "directions", 9, [0.0, 0.0, 0.0])):
        arrays = {"origins": origins.copy(), "directions": directions.copy()}
        arrays[name][row] = value
        bad[what] = (arrays["origins"], arrays["directions"], t_max)
    negative = t_max.copy()
    negative[11] = -0.5
    bad["negative t_max"] = (origins, directions, negative)
    return {"float64": (origins, directions, t_max),
            "float32": (origins.astype(np.float32), directions.astype(np.float32), t_max),
            "one origin": (np.repeat(origins[:1], n, axis=0), directions, t_max),
            "one direction": (origins, np.repeat(directions[:1], n, axis=0), t_max),
            **{f"bad {what}": case for what, case in bad.items()}}


def cpu_gpu_inputs(all_cases):
    """The CPU's traces of each good case and its error message for each bad one."""
    arrays = {}
    for key, (origins, directions, t_max) in all_cases.items():
        arrays[f"gpu inputs {key}|rays"] = np.c_[origins, directions, t_max]
        arrays[f"gpu inputs {key}|dtype"] = np.array(str(origins.dtype))
        try:
            traces = lt.trace_many(GRIDS["log"](), origins, directions, t_max=t_max)
        except ValueError as error:
            arrays[f"gpu inputs {key}|error"] = np.array(str(error))
            continue
        for field in ("offsets", "cells", "t_enter", "t_exit"):
            arrays[f"gpu inputs {key}|{field}"] = getattr(traces, field)
    return arrays


def compare_gpu_inputs(arrays, key):
    """The case traced from arrays put on the GPU first (and once as one (m, 6) array)."""
    from numba import cuda

    rays = arrays[f"{key}|rays"]
    dtype = str(arrays[f"{key}|dtype"])
    shared = {"one origin": 0, "one direction": 3}.get(key.split("gpu inputs ")[-1])
    origins, directions = (
        cuda.to_device(np.ascontiguousarray(rays[:1 if first == shared else None,
                                                 first:first + 3].astype(dtype)))
        for first in (0, 3))
    calls = [lambda: lt.trace_many(GRIDS["log"](), origins, directions,
                                   t_max=cuda.to_device(rays[:, 6].copy()), device="cuda")]
    if dtype == "float64" and f"{key}|error" not in arrays and shared is None:
        calls.append(lambda: lt.trace_many(GRIDS["log"](), cuda.to_device(rays[:, :6].copy()),
                                           t_max=rays[:, 6], device="cuda"))
    problems = []
    for call in calls:
        if f"{key}|error" in arrays:
            want = str(arrays[f"{key}|error"])
            try:
                call()
                problems.append(f"{key}: no error, the CPU said {want!r}")
            except ValueError as error:
                if str(error) != want:
                    problems.append(f"{key}: {str(error)!r}, the CPU said {want!r}")
            continue
        got = call().to_host()
        if not (np.array_equal(got.offsets, arrays[f"{key}|offsets"])
                and np.array_equal(got.cells, arrays[f"{key}|cells"])):
            problems.append(f"{key}: cells differ")
            continue
        for field in ("t_enter", "t_exit"):
            _close(getattr(got, field), arrays[f"{key}|{field}"], f"{key}: {field}", problems)
    return problems


def cone_cases(seed=6):
    """{name: (grid name, apexes, axes, half-angles, n_rays)}: batches of gaze cones on
    every grid kind -- from outside, from the egocentric gap and the centre itself,
    across the theta seam, along the y axis, a single ray -- and random cones."""
    rng = np.random.default_rng(seed)
    out = {}
    for name, make in GRIDS.items():
        grid = make()
        named = np.array([
            # apex, axis, half-angle
            [-1.3 * grid.rho_max, 0.1, 0.2, 1.0, 0.0, 0.05, 0.15],
            [0.0, 0.0, 0.0, 0.3, -0.2, 1.0, 0.3],
            [0.01 * grid.rho_min, 0.0, 0.0, 0.0, 1.0, 0.0, 0.1],
            [0.5 * grid.rho_max, 0.0, 0.0, -1.0, 1e-9, 0.0, 0.2],
            [0.2, 1.5, 1.2, -0.1, -0.4, 1.0, 0.0],
        ])
        random = np.c_[rng.uniform(-grid.rho_max, grid.rho_max, (4, 3)), rng.normal(size=(4, 3)),
                       rng.uniform(0.01, 0.4, 4)]
        for kind, table in (("named", named), ("random", random)):
            out[f"{name} cones {kind}"] = (name, table[:, :3], table[:, 3:6], table[:, 6], 24)
    return out


def cpu_cones(all_cases):
    """The CPU's ``trace_cones`` of every case, as arrays to save."""
    arrays = {}
    for key, (grid_name, apexes, axes, half_angles, n_rays) in all_cases.items():
        cones = lt.trace_cones(GRIDS[grid_name](), apexes, axes, half_angles, n_rays=n_rays)
        for c, cone in enumerate(cones):
            for field in ("cells", "weights", "t_first"):
                arrays[f"{key}|{c}|{field}"] = getattr(cone, field)
        arrays[f"{key}|cones"] = np.c_[apexes, axes, half_angles]
        arrays[f"{key}|n_rays"] = np.array(n_rays)
        arrays[f"{key}|grid"] = np.array(grid_name)
    return arrays


def _close(got, want, name, problems):
    scale = np.maximum(np.abs(want), 1.0)
    error = np.max(np.abs(got - want) / scale, initial=0.0)
    if error > 1e-12:
        problems.append(f"{name} differs by {error:.2e} (relative)")


def compare_cones(arrays, key):
    """``trace_cones(device="cuda")`` of case ``key`` against the saved CPU cones:
    the same cells in the same order, weights and first reaches within 1e-12."""
    table = arrays[f"{key}|cones"]
    cones = lt.trace_cones(GRIDS[str(arrays[f"{key}|grid"])](), table[:, :3], table[:, 3:6],
                           table[:, 6], n_rays=int(arrays[f"{key}|n_rays"]), device="cuda")
    problems = []
    for c, cone in enumerate(cones):
        if not np.array_equal(cone.cells, arrays[f"{key}|{c}|cells"]):
            problems.append(f"{key} cone {c}: cells differ")
            continue
        for field in ("weights", "t_first"):
            _close(getattr(cone, field), arrays[f"{key}|{c}|{field}"], f"{key} cone {c}: {field}",
                   problems)
    return problems


def compare(arrays):
    """Trace every case with ``device="cuda"``; return the mismatches found (a list of str)."""
    problems = []
    keys = sorted({key.split("|")[0] for key in arrays})
    for key in keys:
        if " cones " in key:
            problems += compare_cones(arrays, key)
            continue
        if key.startswith("gpu inputs"):
            problems += compare_gpu_inputs(arrays, key)
            continue
        if key.endswith(" map"):
            problems += compare_map(arrays, key)
            continue
        if key.endswith(" points"):
            from numba import cuda

            points = arrays[f"{key}|points"]
            grid = GRIDS[str(arrays[f"{key}|grid"])]()
            for where, given in (("host", points), ("GPU", cuda.to_device(points))):
                got = grid.cell_of(given, device="cuda")
                if not np.array_equal(got.copy_to_host(), arrays[f"{key}|cells"]):
                    problems.append(f"{key} from the {where}: cells differ")
            continue
        rays = arrays[f"{key}|rays"]
        grid = GRIDS[str(arrays[f"{key}|grid"])]()
        got = lt.trace_many(grid, rays[:, :3], rays[:, 3:6], t_max=rays[:, 6],
                            device="cuda").to_host()
        if not np.array_equal(got.offsets, arrays[f"{key}|offsets"]):
            problems.append(f"{key}: segment counts differ")
            continue
        if not np.array_equal(got.cells, arrays[f"{key}|cells"]):
            problems.append(f"{key}: cells differ")
        for field in ("t_enter", "t_exit"):
            _close(getattr(got, field), arrays[f"{key}|{field}"], f"{key}: {field}", problems)
    return problems


class DeviceCalls:
    """Count, under the simulator, what calls ask of the device.

    Wraps numba-cuda's entry points: a kernel's launch, every way to
    allocate device memory, and the copies back to the host. A wait is a
    copy back or a synchronisation after new work was launched: copies in a
    row with no launch between are one wait, and each is one copy.
    """

    ALLOCATORS = ("device_array", "to_device", "device_array_like", "pinned_array",
                  "mapped_array", "managed_array")

    def __init__(self):
        self.launches = self.allocations = self.waits = self.copies = 0
        self._since_wait = True

    def __enter__(self):
        from numba import cuda

        from logsph_trace import _cuda

        kernel_type = type(_cuda._fill_kernel)
        array_type = type(cuda.device_array(1))
        self._undo = []

        def wrap(owner, name, before):
            original = getattr(owner, name)

            def counted(*args, **kwargs):
                before()
                return original(*args, **kwargs)

            setattr(owner, name, counted)
            self._undo.append((owner, name, original))

        wrap(kernel_type, "__call__", self._launched)
        for name in self.ALLOCATORS:
            if hasattr(cuda, name):
                wrap(cuda, name, self._allocated)
        wrap(array_type, "copy_to_host", self._copied)
        wrap(cuda, "synchronize", self._waited)
        return self

    def __exit__(self, *exc):
        for owner, name, original in reversed(self._undo):
            setattr(owner, name, original)

    def _launched(self):
        self.launches += 1
        self._since_wait = False

    def _allocated(self):
        self.allocations += 1

    def _copied(self):
        self.copies += 1
        self._waited()

    def _waited(self):
        if not self._since_wait:
            self.waits += 1
        self._since_wait = True

    def counts(self):
        return {"launches": self.launches, "allocations": self.allocations,
                "waits": self.waits, "copies back": self.copies}


# What each call may ask of the device once a first call of its size has made the
# workspace: (launches, allocations, waits, copies back), each at most. trace_many
# allocates the four arrays of the Traces it returns; a cone copies back a count
# and the cells it reached.
BUDGETS = {
    "integrate from the centre": (2, 0, 0, 0),
    "integrate off the centre": (2, 0, 0, 0),
    "integrate with labels": (2, 0, 1, 1),
    "trace_cone": (2, 0, 1, 2),
    "trace_cones (3 cones)": (2, 0, 1, 2),
    "fixation_probability": (2, 0, 1, 2),
    "gaze_objects": (2, 0, 1, 2),
    "trace_many": (7, 4, 2, 2),
}


def budget_calls():
    """{name: call} for ``BUDGETS``: each a call of the public API on a small grid."""
    grid = lt.Grid(0.3, 10.0, 8, 16, 8)
    rng = np.random.default_rng(3)
    points = rng.normal(scale=3.0, size=(300, 3))
    labels = rng.integers(1, 4, 300)
    occupancy = lt.OccupancyGrid(grid, device="cuda")
    occupancy.integrate(points, [0.0, 0.0, 0.0], labels=labels)
    origins = rng.normal(scale=4.0, size=(50, 3))
    directions = rng.normal(size=(50, 3))
    eyes, axis = [0.21, 0.13, -0.17], [0.3, 0.1, 1.0]
    return {
        "integrate from the centre": lambda: occupancy.integrate(points, [0.0, 0.0, 0.0]),
        "integrate off the centre": lambda: occupancy.integrate(points, [0.11, -0.04, 0.07]),
        "integrate with labels": lambda: occupancy.integrate(points, [0.11, -0.04, 0.07],
                                                             labels=labels),
        "trace_cone": lambda: lt.trace_cone(grid, eyes, axis, 0.1, n_rays=40, device="cuda"),
        "trace_cones (3 cones)": lambda: lt.trace_cones(grid, origins[:3] / 8, directions[:3],
                                                        0.1, n_rays=20, device="cuda"),
        "fixation_probability": lambda: lt.fixation_probability(occupancy, eyes, axis, 0.1,
                                                                n_rays=40),
        "gaze_objects": lambda: lt.gaze_objects(occupancy, eyes, axis, 0.1, n_rays=40),
        "trace_many": lambda: lt.trace_many(grid, origins, directions, device="cuda"),
    }


def check_budgets():
    """Run each call twice; return the second call's counts over budget (a list of str)."""
    problems, made = [], 0
    for name, call in budget_calls().items():
        with DeviceCalls() as first:
            call()
        made += first.allocations
        with DeviceCalls() as calls:
            call()
        print(name, calls.counts())
        for what, got, most in zip(("launches", "allocations", "waits", "copies back"),
                                   (calls.launches, calls.allocations, calls.waits,
                                    calls.copies), BUDGETS[name]):
            if got > most:
                problems.append(f"{name}: {got} {what}, at most {most}")
    if not made:  # the first calls make the workspace: a count of none counts nothing
        problems.append("no first call allocated: the allocations are not being counted")
    return problems


if __name__ == "__main__":
    from logsph_trace import _cuda

    if sys.argv[1] == "budgets":
        problems = check_budgets()
        print("\n".join(problems) if problems else "within budget")
        sys.exit(1 if problems else 0)

    with np.load(sys.argv[1]) as saved:
        arrays = dict(saved)
    if len(sys.argv) > 2:  # few rays in flight: many rounds of the trace loop
        _cuda.RAYS_IN_FLIGHT = int(sys.argv[2])
    if len(sys.argv) > 3:  # no memory to spare: one ray in flight, one part per ray
        _cuda.MEMORY_SHARE = 1e-15
    problems = compare(arrays)
    print("\n".join(problems) if problems else "all equal")
    sys.exit(1 if problems else 0)
