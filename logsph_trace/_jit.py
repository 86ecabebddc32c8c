"""One place for the Numba options every kernel shares, and the one way to apply them.

Every kernel is decorated where it is defined: ``@jit`` for serial code (with
``inline="always"`` for the small per-ray helpers), ``@jit(parallel=True)``
for a ``prange`` kernel that only runs in parallel, and ``@jit_twins`` for a
``prange`` kernel that also runs on one thread.

``cache=True`` keeps the first call after install cheap: each kernel compiles
once and is loaded from ``__pycache__`` afterwards. Numba checks a cached
kernel against its own file only, but a kernel inlines helpers and freezes
constants from other files; after an edit or a ``git pull`` that changed only
those, it would load the stale machine code. So the package's kernels are
checked against all of its sources (:func:`cache_by_package`): any change to
the package recompiles them, and so does a change of the Numba settings
that shape the code but are not in Numba's own key (:func:`codegen_settings`:
a run under ``NUMBA_ENABLE_PROFILING=1`` or ``NUMBA_BOUNDSCHECK=1`` leaves
nothing behind that later runs load). ``LOGSPH_TRACE_CACHE=0`` in the environment
turns the cache off (a read-only install). ``error_model="numpy"`` makes a
float division by zero return ``inf``/``nan`` as IEEE says instead of
raising, which the root solvers rely on (a ray parallel to a plane has its
crossing at infinity).
``fastmath`` stays off: it may reorder the tie rules and NaN checks the
exactness tests hold us to.

Two of Numba's private parts are used, each where a user gains, and each
with a fallback to plain Numba where a release lacks it: the package-wide
cache stamp extends ``caching._CacheLocator`` (without it, Numba's own
per-file stamp: :func:`cache_by_package` does nothing), and serial kernels
drop Numba's runtime through the ``_nrt`` option (without it they keep the
runtime: ``WITHOUT_RUNTIME``). ``tests/test_nojit.py`` removes each in a
fresh process and runs a trace.

**Threads and processes.** Numba runs ``prange`` loops on one of three
threading layers. GNU OpenMP (``omp``, the usual one on Linux) aborts any
child made by ``fork`` after a parallel call -- ``multiprocessing``'s default
on Linux -- and ``workqueue`` aborts when two Python threads run parallel
code at once. TBB (``tbb``) does neither, so the package depends on the
``tbb`` wheel where it exists and asks Numba to prefer it
(:func:`prefer_tbb`), unless ``NUMBA_THREADING_LAYER`` or
``NUMBA_THREADING_LAYER_PRIORITY`` says otherwise. Where ``workqueue`` ends
up in use anyway, every parallel kernel runs under one lock
(:class:`Guarded`): concurrent calls then take turns instead of aborting.
"""

import ctypes
import functools
import hashlib
import os
import signal
import sys
import threading
import types
from pathlib import Path
from typing import NamedTuple

import numba
from numba.core import caching, cpu, event


def prefer_tbb():
    """Make TBB Numba's first choice of threading layer, unless the user chose one.

    pip's ``tbb`` wheel puts ``libtbb.so.12`` in ``<prefix>/lib``, which the
    dynamic loader does not search inside a virtual environment; loading it
    here by path lets Numba's TBB layer find it by name. Takes effect only if
    no parallel code has run yet in this process.
    """
    if sys.platform.startswith("linux"):  # also when the user picks tbb by name
        for prefix in dict.fromkeys((sys.prefix, sys.base_prefix)):
            library = Path(prefix) / "lib" / "libtbb.so.12"
            if library.is_file():
                try:
                    ctypes.CDLL(str(library), mode=ctypes.RTLD_GLOBAL)
                except OSError:
                    continue
                break
    if not (os.environ.get("NUMBA_THREADING_LAYER")
            or os.environ.get("NUMBA_THREADING_LAYER_PRIORITY")):
        numba.config.THREADING_LAYER_PRIORITY = ["tbb", "omp", "workqueue"]


prefer_tbb()

_PARALLEL_LOCK = threading.Lock()
_layer = None


def _needs_lock():
    """Whether parallel calls must take turns: the workqueue layer, or not known yet."""
    global _layer
    if _layer is None:
        try:
            _layer = numba.threading_layer()
        except ValueError:  # no parallel code has run yet: be safe for this call
            return True
    return _layer == "workqueue"


# SIGINTs held back while the main thread runs a parallel kernel
# (``interrupts_after``): how deep it is in such calls, and whether one came.
_depth = 0
_received = False
_NOT_MAIN = object()


def _record(signum, frame):
    global _received
    _received = True


def _hold():
    """Start holding SIGINT back; return what :func:`_release` needs.

    The handler is swapped before the depth counts it: a KeyboardInterrupt
    from a signal that came before leaves nothing half done.
    """
    global _depth, _received
    if threading.current_thread() is not threading.main_thread():
        return _NOT_MAIN  # Python runs signal handlers in the main thread only
    if _depth:
        _depth += 1
        return None  # held already, by an enclosing call
    _received = False
    try:
        previous = signal.signal(signal.SIGINT, _record)
    except ValueError:  # not the main interpreter
        return _NOT_MAIN
    _depth = 1
    return previous


def _release(previous):
    """Stop holding SIGINT back (``previous``: :func:`_hold`'s); deliver one that came."""
    global _depth, _received
    if previous is _NOT_MAIN:
        return
    _depth -= 1
    if previous is None:
        return
    signal.signal(signal.SIGINT, previous)
    if _received:
        _received = False
        signal.raise_signal(signal.SIGINT)


def interrupts_after(function):
    """Decorate ``function`` so that Ctrl-C (SIGINT) waits until it returns.

    A parallel kernel calls into Python now and then (Numba unpickles what it
    needs at run time), and Python runs a pending signal's handler at such a
    call. There ``KeyboardInterrupt`` surfaced as a ``SystemError`` from the
    dispatcher, with the kernel's threads still writing into arrays being
    freed: the process could crash. While ``function`` runs, a SIGINT is
    only recorded; afterwards the handler in place before is restored and
    the signal raised again, so it acts as it would have
    (``KeyboardInterrupt`` by default). Every parallel kernel is run so
    (:class:`Guarded`); a public call that runs several holds the signal
    once for all of them (swapping the handler costs a few microseconds).
    Python handles signals in its main thread only, so other threads run
    ``function`` as it is.
    """

    @functools.wraps(function)
    def holding(*args, **kwargs):
        previous = _hold()
        try:
            return function(*args, **kwargs)
        finally:
            _release(previous)

    return holding


def _atomics():
    """Whether the parallel kernels' atomics are at hand (``kernels.atomic.AVAILABLE``)."""
    from .kernels import atomic  # not at import: that module imports this one

    return atomic.AVAILABLE


class Guarded:
    """A parallel kernel, run so that Ctrl-C waits for it to end.

    See :func:`interrupts_after`. Calls take turns under a lock where the
    threading layer needs it.
    """

    def __init__(self, dispatcher):
        self.dispatcher = dispatcher
        self.__doc__ = dispatcher.__doc__
        self.__name__ = dispatcher.__name__

    def __call__(self, *args):
        """Run the kernel (locked on workqueue; one thread without ``kernels.atomic``)."""
        previous = _hold()
        try:
            if not _atomics():
                threads = numba.get_num_threads()
                numba.set_num_threads(1)
                try:
                    return self.dispatcher(*args)
                finally:
                    numba.set_num_threads(threads)
            if _needs_lock():
                with _PARALLEL_LOCK:
                    return self.dispatcher(*args)
            return self.dispatcher(*args)
        finally:
            _release(previous)

    def __getattr__(self, name):
        return getattr(self.dispatcher, name)

CACHE = os.environ.get("LOGSPH_TRACE_CACHE", "1").strip() != "0"

# Package roots whose kernels are checked against all their sources, and the
# digest of those sources (computed when the first kernel there is cached).
_ROOTS = {}


def _sources_digest(root):
    """SHA-256 of every ``.py`` file under ``root``: its path and its bytes."""
    digest = hashlib.sha256()
    for path in sorted(root.rglob("*.py")):
        digest.update(path.relative_to(root).as_posix().encode() + b"\0")
        digest.update(path.read_bytes() + b"\0")
    return digest.hexdigest()


# Numba settings that change the machine code of a kernel but are not in
# the key of Numba's cache index (that holds the signature, the bytecode and
# the CPU). ``NUMBA_ENABLE_PROFILING=1``, which perf and VTune need, turns on
# ``NUMBA_DEBUGINFO``, and Numba compiles debug info with every variable kept
# alive: the exact trace compiled so ran at 1,780 ns a ray against 760,
# and without these in the stamp every later run would load that code from
# the cache. ``NUMBA_BOUNDSCHECK=1`` the
# other way round would load kernels that check nothing.
_CODEGEN_SETTINGS = ("OPT", "DEBUGINFO_DEFAULT", "BOUNDSCHECK", "EXTEND_VARIABLE_LIFETIMES",
                     "LOOP_VECTORIZE", "SLP_VECTORIZE", "USING_SVML")


def codegen_settings():
    """Return ``_CODEGEN_SETTINGS`` in ``numba.config`` now, and the fallbacks taken, as strings.

    The fallbacks (``WITHOUT_RUNTIME``, ``kernels.atomic.AVAILABLE``) are
    part of the stamp: a kernel compiled with plain stores for atomics must
    never be loaded where threads share them.
    """
    return tuple(str(getattr(numba.config, name, None)) for name in _CODEGEN_SETTINGS) + (
        f"without runtime {WITHOUT_RUNTIME}", f"atomics {_atomics()}")


# Numba's base class of cache locators (private): None where a release lacks it.
_NumbaLocator = getattr(caching, "_CacheLocator", None) or object


class _PackageLocator(_NumbaLocator):
    """Numba's own cache locator for a function, with the package's sources in its stamp.

    Numba stores a locator's source stamp in the cache index and throws the
    cached code away when it differs. Its own locators stamp the function's
    file only; this one adds the digest of every source file of the package
    the function is defined in, and the Numba settings that change the code
    (``codegen_settings``), and leaves where the cache lives (and
    everything else) to the locator Numba would have picked from
    ``impl._locator_classes`` (``impl``: the ``CacheImpl`` of Numba or of
    numba-cuda, set per subclass by ``cache_by_package``).
    """

    impl = None

    def __init__(self, base, digest):
        self._base = base
        self._digest = digest
        self._py_file = base._py_file  # Numba names it in its can't-cache warning

    def ensure_cache_path(self):
        self._base.ensure_cache_path()

    def get_cache_path(self):
        return self._base.get_cache_path()

    def get_source_stamp(self):
        return (self._base.get_source_stamp(), self._digest, codegen_settings())

    def get_disambiguator(self):
        return self._base.get_disambiguator()

    @classmethod
    def from_function(cls, py_func, py_file):
        path = Path(os.path.realpath(py_file))
        root = next((root for root in _ROOTS if root in path.parents), None)
        if root is None:
            return None  # not ours: Numba's next locator takes it
        for other in cls.impl._locator_classes:
            if issubclass(other, _PackageLocator):
                continue
            base = other.from_function(py_func, py_file)
            if base is not None:
                if _ROOTS[root] is None:
                    _ROOTS[root] = _sources_digest(root)
                return cls(base, _ROOTS[root])
        return None


def cache_by_package(root, impl=None):
    """Check the cached kernels defined under ``root`` against all of its ``.py`` files.

    ``impl``: the ``CacheImpl`` whose locators to extend, Numba's by default
    (numba-cuda has its own). Called for this package on import; a test
    registers a package of its own. Returns whether it took effect: not
    where Numba lacks the private parts it extends (``_CacheLocator``, a
    ``CacheImpl`` with ``_locator_classes``), which leaves Numba's own
    per-file stamp, stale after an edit of another file only.
    """
    if impl is None:  # numba 0.59 calls it _CacheImpl
        impl = getattr(caching, "CacheImpl", None) or getattr(caching, "_CacheImpl", None)
    locators = getattr(impl, "_locator_classes", None)
    if _NumbaLocator is object or not isinstance(locators, list):
        return False
    _ROOTS.setdefault(Path(os.path.realpath(root)), None)
    if not any(issubclass(other, _PackageLocator) for other in locators):
        locators.insert(0, type("_PackageLocator", (_PackageLocator,),
                                     {"impl": impl, "__module__": __name__}))
    return True


cache_by_package(Path(__file__).parent)
_OPTIONS = dict(cache=CACHE, nogil=True, error_model="numpy")
# Whether this Numba takes the private ``_nrt`` option (see ``jit``).
WITHOUT_RUNTIME = hasattr(cpu.CPUTargetOptions, "_nrt")

# The first use after an install compiles the kernels a call needs, which
# takes seconds (``logsph-trace demo``: about 30 s on the 2-core test
# machine) with nothing on screen; a cached kernel loads in milliseconds.
NOTE = os.environ.get("LOGSPH_TRACE_COMPILE_NOTE", "1").strip() != "0"


class CompileNote(event.Listener):
    """Say on stderr, once per process, that the package's kernels are compiling.

    Numba fires a ``numba:compile`` event only when it compiles, never when
    it loads a kernel from the cache, so the note appears exactly on a cold
    first use: the first run after an install or an edit, or every run under
    ``LOGSPH_TRACE_CACHE=0``. ``LOGSPH_TRACE_COMPILE_NOTE=0`` silences it.
    Other packages' Numba functions are none of its business.
    """

    def __init__(self, package, stream=None):
        self.package = package
        self.stream = stream  # None: sys.stderr at the time of the note
        self.said = False
        self._lock = threading.Lock()

    def message(self):
        """Return the line, saying whether later runs will load the kernels from the cache."""
        after = ("cached for later runs" if CACHE
                 else "not cached: LOGSPH_TRACE_CACHE=0")
        return (f"{self.package}: compiling Numba kernels for their first use "
                f"({after})...")

    def on_start(self, ev):
        if self.said:
            return
        dispatcher = (ev.data or {}).get("dispatcher")
        module = getattr(getattr(dispatcher, "py_func", None), "__module__", None) or ""
        if module.partition(".")[0] != self.package:
            return
        with self._lock:
            if self.said:
                return
            self.said = True
        stream = self.stream if self.stream is not None else sys.stderr
        if NOTE and stream is not None:
            print(self.message(), file=stream, flush=True)

    def on_end(self, ev):
        pass


COMPILE_NOTE = CompileNote(__name__.partition(".")[0])
event.register("numba:compile", COMPILE_NOTE)


def jit(func=None, runtime=False, **overrides):
    """``numba.njit`` with the project's options (``parallel=True`` may be added).

    A parallel kernel comes back :class:`Guarded`: callable from Python, not
    from other kernels.

    A serial kernel is compiled without Numba's runtime (NRT) unless it says
    ``runtime=True`` (it allocates, sorts or returns an array). Without the
    runtime a kernel borrows the arrays it is given instead of counting
    references to them. With it, every call of a kernel that is not inlined
    takes and drops a reference to each array it is passed or reads out of
    a bundle: two atomic operations per array, about 40 per ray when the
    exact traversal was called once per ray, a third of its set-up. A kernel that
    needs the runtime and lacks it fails to compile, loudly; so does one
    without it that calls a kernel that sorts, though only if that sort was
    not compiled earlier in the process (``tests/test_nojit.py`` compiles
    each method first in a fresh process). numba-cuda ignores the option.
    ``_nrt`` is a private option of Numba's: where a release has no such
    option (``WITHOUT_RUNTIME`` False), every kernel keeps the runtime.
    """
    options = dict(_OPTIONS, **overrides)
    if not (runtime or options.get("parallel")) and WITHOUT_RUNTIME:
        options["_nrt"] = False

    def build(f):
        dispatcher = numba.njit(**options)(f)
        return Guarded(dispatcher) if options.get("parallel") else dispatcher

    return build if func is None else build(func)


class Twins(NamedTuple):
    """The serial and the parallel build of one ``prange`` kernel."""

    serial: object
    parallel: object

    def pick(self, parallel):
        """Return the build for ``parallel`` (True: all threads; False: this thread)."""
        return self.parallel if parallel else self.serial


def jit_twins(func=None, runtime=True):
    """Compile one ``prange`` source twice, serially and with ``parallel=True``.

    ``runtime``: whether the serial build keeps Numba's runtime (see ``jit``;
    a ``prange`` body that allocates needs it).

    Numba's on-disk cache names its files after the function's qualified name,
    so the two builds of one function would overwrite each other's cache and a
    later process could load the serial code for the parallel entry point. The
    parallel build therefore gets its own copy of the function, named
    ``<name>_parallel``.
    """
    def build(func):
        twin = types.FunctionType(
            func.__code__, func.__globals__, func.__name__ + "_parallel",
            func.__defaults__, func.__closure__,
        )
        twin.__qualname__ = func.__qualname__ + "_parallel"
        twin.__doc__ = func.__doc__
        return Twins(jit(func, runtime=runtime), jit(twin, parallel=True))

    return build if func is None else build(func)
