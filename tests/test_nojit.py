"""The kernels stay plain Python: with NUMBA_DISABLE_JIT=1 they give the compiled answers.

Run in a subprocess on a small subset (the interpreter is ~100x slower), so
coverage tools can see the kernels and a reader can step through them. The
options the kernels compile with (the cache switch, Numba's runtime) are
checked here too.
"""

import inspect
import os
import subprocess
import sys
import textwrap

import numpy as np
import pytest

import logsph_trace as lt

SCRIPT = textwrap.dedent(
    """
    import sys
    import numpy as np
    import logsph_trace as lt
    from logsph_trace.cartesian import CartesianGrid

    rng = np.random.default_rng(12)
    grid = lt.Grid(0.3, 10.0, 6, 8, 5, theta_range=(-2.5, 2.0), phi_range=(-0.6, 1.0))
    origins = rng.uniform(-12, 12, (60, 3))
    directions = rng.normal(size=(60, 3))
    traces = lt.trace_many(grid, origins, directions, parallel=True)
    bisect = lt.trace_many(grid, origins, directions, method="bisect", default_t=0.7)
    thibaudeau = lt.trace_many(grid, origins, directions, method="thibaudeau")
    occupancy = lt.OccupancyGrid(grid).integrate(origins[:20] * 0.5, [0.2, 0.1, 0.0])
    # At the centre, each point twice: two rays end in every hit cell.
    radial = lt.OccupancyGrid(grid).integrate(np.repeat(origins[:20] * 0.5, 2, axis=0), [0, 0, 0])
    cone = lt.trace_cone(grid, [0.4, 1.5, 1.2], [-0.1, -0.4, 1.0], 0.1, n_rays=20)
    cart = CartesianGrid((-10.0, -10.0, -10.0), (10.0, 10.0, 10.0), (7, 8, 9))
    boxes = cart.trace_many(origins, directions)
    # The path of three threads or more, in chunks of a ray or two on 3 workers,
    # faulting its output in by blocks of 5 rows (many blocks, some claimed
    # ahead by the pacing, some by the chunks' copies). The block size is
    # read in Python at each call and passed to the kernels: were it frozen
    # into them, as it once was, they would be cached so (and served to later
    # processes, which hung when they mixed them with kernels compiled with
    # the real size).
    from logsph_trace import _batching, _validate
    from logsph_trace.kernels import ordered as ordered_kernels
    _batching.ORDERED_SEGMENTS = 200
    ordered_kernels.TOUCH_ROWS = 5
    o, d = _validate.rays(origins, directions)
    ordered = _batching.run_exact_ordered(grid, o, d, np.full(len(o), np.inf), 3)
    np.savez(sys.argv[1], offsets=traces.offsets, cells=traces.cells, t_enter=traces.t_enter,
             t_exit=traces.t_exit, box_offsets=boxes.offsets, box_cells=boxes.cells,
             points=grid.cell_of(origins), bisect_cells=bisect.cells,
             bisect_offsets=bisect.offsets, thibaudeau_cells=thibaudeau.cells,
             thibaudeau_offsets=thibaudeau.offsets, log_odds=occupancy.log_odds,
             radial_log_odds=radial.log_odds,
             cone_cells=cone.cells, cone_weights=cone.weights, ordered_offsets=ordered.offsets,
             ordered_cells=ordered.cells, ordered_t_exit=ordered.t_exit)
    """
)


def test_kernels_run_without_jit(tmp_path):
    out = tmp_path / "nojit.npz"
    env = dict(os.environ, NUMBA_DISABLE_JIT="1")
    subprocess.run([sys.executable, "-c", SCRIPT, str(out)], env=env, check=True, timeout=300)
    plain = np.load(out)
    jitted_out = tmp_path / "jit.npz"
    env.pop("NUMBA_DISABLE_JIT")
    subprocess.run([sys.executable, "-c", SCRIPT, str(jitted_out)], env=env, check=True,
                   timeout=300)
    jitted = np.load(jitted_out)
    for name in ("offsets", "cells", "box_offsets", "box_cells", "points", "bisect_cells",
                 "bisect_offsets", "thibaudeau_cells", "thibaudeau_offsets"):
        np.testing.assert_array_equal(plain[name], jitted[name], err_msg=name)
    np.testing.assert_allclose(plain["t_enter"], jitted["t_enter"], rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(plain["t_exit"], jitted["t_exit"], rtol=1e-12, atol=1e-12)
    for run in (plain, jitted):
        np.testing.assert_array_equal(run["ordered_offsets"], run["offsets"])
        np.testing.assert_array_equal(run["ordered_cells"], run["cells"])
        np.testing.assert_array_equal(run["ordered_t_exit"], run["t_exit"])
    np.testing.assert_array_equal(plain["log_odds"], jitted["log_odds"])
    np.testing.assert_array_equal(plain["radial_log_odds"], jitted["radial_log_odds"])
    assert np.any(jitted["radial_log_odds"] > 0)
    np.testing.assert_array_equal(plain["cone_cells"], jitted["cone_cells"])
    np.testing.assert_allclose(plain["cone_weights"], jitted["cone_weights"], rtol=1e-12)
    assert lt.Grid(0.3, 10.0, 6, 8, 5).shape == (6, 8, 5)


def test_the_cache_switch_turns_numba_caching_off():
    probe = ("import logsph_trace._jit as j; from logsph_trace.kernels import locate; "
             "print(j.CACHE, type(locate.locate._cache).__name__)")
    for value, want in (("0", "False NullCache"), ("1", "True FunctionCache")):
        env = dict(os.environ, LOGSPH_TRACE_CACHE=value)
        out = subprocess.run([sys.executable, "-c", probe], env=env, check=True,
                             capture_output=True, text=True, timeout=300).stdout
        assert out.split() == want.split(), out


STALE_HELPER = """
from logsph_trace._jit import jit
VALUE = {value}
@jit
def value():
    return VALUE
"""

STALE_CALLER = """
from logsph_trace._jit import jit
from .helper import value
@jit
def read():
    return value()
"""


def _package(tmp_path, main, probe):
    """A package ``pkg`` in ``tmp_path`` whose ``main.py`` is ``main``, its kernels
    cached by the package's locator. Returns the package's folder,
    ``run(**settings)``: ``probe`` in a fresh interpreter there, with those
    environment variables (and no Numba setting of the caller's), as the
    words it prints, and ``start()``: the same probe started, its
    ``subprocess.Popen`` (stdout piped) returned at once."""
    package = tmp_path / "pkg"
    package.mkdir()
    (package / "__init__.py").write_text("")
    (package / "main.py").write_text(main)
    command = [sys.executable, "-c",
               "import logsph_trace._jit as j; j.cache_by_package('pkg')\n" + probe]
    base = {key: value for key, value in os.environ.items()
            if key not in ("NUMBA_BOUNDSCHECK", "NUMBA_DEBUGINFO", "NUMBA_ENABLE_PROFILING")}
    base.update(LOGSPH_TRACE_CACHE="1", PYTHONDONTWRITEBYTECODE="1")

    def run(**settings):
        return subprocess.run(command, cwd=tmp_path, env=dict(base, **settings), check=True,
                              capture_output=True, text=True, timeout=300).stdout.split()

    def start():
        return subprocess.Popen(command, cwd=tmp_path, env=base, stdout=subprocess.PIPE,
                                text=True)

    return package, run, start


def test_a_cached_kernel_recompiles_when_a_helper_in_another_file_changes(tmp_path):
    """Numba alone checks a cached kernel against its own file, so ``read`` would
    keep returning the old ``VALUE`` it inlined from ``helper.py``; the package's
    locator checks it against every source file of its package."""
    package, run, _ = _package(
        tmp_path, STALE_CALLER,
        "from pkg.main import read; from pkg.helper import value; "
        "print(read(), value(), read.stats.cache_hits.get(read.signatures[0], 0), "
        "type(read._cache._impl.locator).__name__)")
    (package / "helper.py").write_text(STALE_HELPER.format(value=1))
    assert run() == ["1", "1", "0", "_PackageLocator"]
    assert run() == ["1", "1", "1", "_PackageLocator"]  # the cache still serves
    (package / "helper.py").write_text(STALE_HELPER.format(value=2))
    assert run() == ["2", "2", "0", "_PackageLocator"]
    assert run() == ["2", "2", "1", "_PackageLocator"]


PEEK = """
from logsph_trace._jit import jit
@jit
def peek(values, at):
    return values[at]
"""


def test_a_kernel_cached_under_other_numba_settings_is_compiled_again(tmp_path):
    """Numba's cache index is keyed by the signature, the bytecode and the CPU,
    not by settings such as ``NUMBA_BOUNDSCHECK``: a kernel cached with bounds
    checks, or with the debug info ``NUMBA_ENABLE_PROFILING=1`` turns on for
    perf, would be loaded by every later run, and one cached without them by
    a run that asks for them. The package's stamp holds those settings."""
    _, run, _ = _package(
        tmp_path, PEEK,
        "import numpy as np\nfrom pkg.main import peek\n"
        "try:\n    peek(np.zeros(1), 1); checked = 0\n"
        "except IndexError:\n    checked = 1\n"
        "print(checked, peek.stats.cache_hits.get(peek.signatures[0], 0))")
    assert run() == ["0", "0"]
    assert run() == ["0", "1"]  # the cache serves the same settings
    assert run(NUMBA_BOUNDSCHECK="1") == ["1", "0"]
    assert run() == ["0", "0"]  # not the checked code from the cache
    assert run(NUMBA_ENABLE_PROFILING="1") == ["0", "0"]  # debug info: other code
    assert run() == ["0", "0"]
    assert run() == ["0", "1"]


WITHOUT_PRIVATE_PARTS = textwrap.dedent(
    """
    import sys
    import numba.extending
    from numba.core import caching, cpu

    plain = sys.argv[2] == "plain"
    if plain:
        # What a Numba release could drop: the base class of cache locators,
        # the option that compiles a kernel without the runtime, and the
        # intrinsics the atomics are written with.
        del caching._CacheLocator
        delattr(next(c for c in cpu.CPUTargetOptions.__mro__ if "_nrt" in vars(c)), "_nrt")
        del numba.extending.intrinsic

    import numpy as np
    import logsph_trace as lt
    from logsph_trace import _jit
    from logsph_trace.kernels import atomic, exact

    assert _jit.WITHOUT_RUNTIME == atomic.AVAILABLE == (not plain)
    assert _jit.cache_by_package(_jit.Path(exact.__file__).parent) == (not plain)
    rng = np.random.default_rng(4)
    grid = lt.Grid(0.3, 10.0, 8, 12, 6)
    origins = rng.uniform(-12, 12, (3000, 3))
    directions = rng.normal(size=(3000, 3))
    traces = lt.trace_many(grid, origins, directions, parallel=True)
    map = lt.OccupancyGrid(grid).integrate(origins * 0.5, [0.2, 0.1, 0.0])
    radial = lt.OccupancyGrid(grid).integrate(np.repeat(origins * 0.5, 2, axis=0), [0, 0, 0])
    cone = lt.trace_cone(grid, [0.4, 1.5, 1.2], [-0.1, -0.4, 1.0], 0.1, n_rays=700)
    np.savez(sys.argv[1], offsets=traces.offsets, cells=traces.cells, t_exit=traces.t_exit,
             log_odds=map.log_odds, radial=radial.log_odds, cone_cells=cone.cells,
             cone_weights=cone.weights)
    """
)


def test_without_numbas_private_parts_the_package_falls_back_to_plain_numba(tmp_path):
    """Three private parts of Numba are used (the cache locator's base class,
    the ``_nrt`` option, ``intrinsic`` for the atomics); each has a fallback.
    Removed in a fresh process before the import, the package still gives
    the answers it gives with them (on all threads, from the cache): the
    batches and the parallel kernels then run on one thread."""
    results = {}
    for kind, cache in (("plain", "0"), ("full", "1")):
        results[kind] = tmp_path / f"{kind}.npz"
        env = dict(os.environ, LOGSPH_TRACE_CACHE=cache, LOGSPH_TRACE_COMPILE_NOTE="0")
        subprocess.run([sys.executable, "-c", WITHOUT_PRIVATE_PARTS, str(results[kind]), kind],
                       check=True, env=env, timeout=600)
    got, want = np.load(results["plain"]), np.load(results["full"])
    assert want["cells"].shape[0] > 5000 and np.any(want["log_odds"] != 0)
    for name in want.files:
        np.testing.assert_array_equal(got[name], want[name], err_msg=name)


def test_the_package_kernels_are_checked_against_all_its_sources():
    from pathlib import Path

    from logsph_trace import _jit
    from logsph_trace.kernels import exact

    if not _jit.CACHE:
        pytest.skip("LOGSPH_TRACE_CACHE=0: nothing is cached")
    locator = exact.trace_span._cache._impl.locator
    assert isinstance(locator, _jit._PackageLocator)
    assert locator.get_source_stamp()[1] == _jit._sources_digest(Path(_jit.__file__).parent)
    assert locator.get_cache_path() == str(Path(exact.__file__).parent / "__pycache__")


def test_the_gpu_kernels_are_checked_against_all_the_package_sources():
    """Whether ``numba.cuda`` is numba-cuda (its own ``CacheImpl``) or Numba's
    built-in one, the CUDA kernels' cache is stamped like the CPU's."""
    from pathlib import Path

    from logsph_trace import _jit

    if not _jit.CACHE:
        pytest.skip("LOGSPH_TRACE_CACHE=0: nothing is cached")
    cuda_module = pytest.importorskip("logsph_trace._cuda")
    kernels = [value for value in vars(cuda_module).values() if hasattr(value, "_cache")]
    assert len(kernels) > 10
    digest = _jit._sources_digest(Path(_jit.__file__).parent)
    for kernel in kernels:
        locator = kernel._cache._impl.locator
        assert isinstance(locator, _jit._PackageLocator), kernel
        assert locator.get_source_stamp()[1] == digest


def test_serial_kernels_borrow_their_arrays():
    """Serial kernels run without Numba's runtime, so a call counts no references
    (``_jit.jit``); only those that allocate, sort or return an array keep it."""
    import importlib
    import pkgutil

    import numba

    from logsph_trace import kernels

    keep = {"bisect_ray", "bisect_rows", "box_bases", "cells_of_points", "components", "entry_time",
            "first_reach_order", "sparse_cone", "thibaudeau_ray", "thibaudeau_rows"}
    needs_runtime = (".sort(", "np.empty(", "np.zeros(", "np.full(", ".copy(")
    seen = set()
    for info in pkgutil.walk_packages(kernels.__path__, "logsph_trace.kernels."):
        module = importlib.import_module(info.name)
        for name, value in vars(module).items():
            value = getattr(value, "serial", value)  # the serial build of a jit_twins pair
            if (isinstance(value, numba.core.registry.CPUDispatcher)
                    and value.__module__ == module.__name__):
                seen.add(name)
                assert value.targetoptions.get("_nrt", True) == (name in keep), name
                if not value.targetoptions.get("inline", "never") == "always":
                    source = inspect.getsource(value.py_func)
                    if any(call in source for call in needs_runtime):
                        assert name in keep, f"{name} allocates or sorts"
    assert {"trace_span", "ray_bound", "box_span", "walk_ray", "locate"} <= seen
    assert keep <= seen


@pytest.mark.parametrize("method", ["bisect", "thibaudeau"])
def test_each_method_compiles_first_in_a_fresh_process(method):
    """A kernel compiled without the runtime can still type when an earlier call
    compiled the sort it uses with the runtime (the suite's order hid one such
    kernel): each baseline method is compiled first, in a process of its own."""
    probe = ("import numpy as np, logsph_trace as lt; "
             "g = lt.Grid(0.3, 10.0, 4, 6, 5); o = np.zeros((3, 3)); "
             "d = np.eye(3) + 0.1; "
             f"print(len(lt.trace_many(g, o, d, method={method!r}, parallel=False).cells))")
    env = dict(os.environ, LOGSPH_TRACE_CACHE="0")
    out = subprocess.run([sys.executable, "-c", probe], env=env, capture_output=True, text=True,
                         timeout=300)
    assert out.returncode == 0, out.stderr[-2000:]
    assert int(out.stdout.split()[-1]) > 0


def _njit_in(module):
    """A fresh Numba function that says it is defined in ``module``."""
    import numba

    def twice(x):
        return 2 * x

    twice.__module__ = module
    return numba.njit(cache=False)(twice)


@pytest.fixture
def listening(monkeypatch):
    """``listening(on)``: a fresh compile note, on or off, listening while the test runs."""
    import io

    import numba.core.event as event

    from logsph_trace import _jit

    notes = []

    def start(on):
        monkeypatch.setattr(_jit, "NOTE", on)
        note = _jit.CompileNote("logsph_trace", io.StringIO())
        event.register("numba:compile", note)
        notes.append(note)
        return note

    yield start
    for note in notes:
        event.unregister("numba:compile", note)


def test_a_first_compile_is_noted_once_per_process(listening):
    note = listening(True)
    assert _njit_in("other_package.kernels")(1.5) == 3.0  # not ours: no note
    assert note.stream.getvalue() == ""
    assert _njit_in("logsph_trace.kernels.probe")(2) == 4
    assert _njit_in("logsph_trace.kernels.probe")(2.5) == 5.0
    assert note.stream.getvalue() == note.message() + "\n"
    assert "compiling Numba kernels" in note.message()


def test_the_compile_note_can_be_silenced(listening):
    note = listening(False)
    assert _njit_in("logsph_trace.kernels.probe")(3) == 6
    assert note.said and note.stream.getvalue() == ""
