"""Every input check of the public API, in one place and one style.

Each check takes the argument's name and value, returns the value in the form
the kernels need (contiguous float64 arrays, Python numbers), and raises a
``ValueError`` whose message names the argument, the bad row where there is
one, and the value -- before any kernel runs.
"""

import math
import os
import sys
import warnings

import numpy as np

from .kernels import locate as _locate

try:
    import resource
except ImportError:  # Windows
    resource = None

_FULL_TURN_TOL = 1e-12


_FLOAT_MAX = float(np.finfo(np.float64).max)


def count(name, value):
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer)):
        raise ValueError(f"{name} must be a positive integer, got {value!r}")
    if value < 1:
        raise ValueError(f"{name} must be a positive integer, got {value!r}")
    return int(value)


class WrongTypeError(TypeError, ValueError):
    """Text, None, complex numbers or other objects where numbers belong.

    A ``TypeError``, and a ``ValueError`` too, so that code that catches
    either of the two for bad input catches it.
    """


def _is_text(value):
    return isinstance(value, (str, bytes, np.str_, np.bytes_))


def _is_complex(value):
    """Whether ``value`` is a complex number or array (``float`` would drop the imaginary part)."""
    return isinstance(value, (complex, np.complexfloating)) or \
        getattr(getattr(value, "dtype", None), "kind", "") == "c"


def number(name, value, requirement):
    """``value`` as a Python float, else ValueError "``name`` must be ``requirement``, got ...".

    Text, None, complex numbers and other objects are refused with a
    :class:`WrongTypeError` (``float`` would parse ``"5"``); a value that is
    no number for other reasons with a ``ValueError``.
    """
    if value is None or _is_text(value) or _is_complex(value):
        raise WrongTypeError(f"{name} must be {requirement}, got {value!r}")
    try:
        return float(value)
    except TypeError:
        raise WrongTypeError(f"{name} must be {requirement}, got {value!r}") from None
    except ValueError:
        raise ValueError(f"{name} must be {requirement}, got {value!r}") from None


def real_array(name, value, requirement="numeric"):
    """``value`` as a float64 array (no copy when it is one), else ValueError naming ``name``.

    Integers, booleans and arrays of Python numbers convert as numpy converts
    them. Text (also inside an object array), dates and complex numbers are
    refused with a :class:`WrongTypeError`: numpy would parse the text, or
    drop the imaginary parts with only a warning.
    """
    kind = None
    try:
        array = np.asarray(value)
        kind = array.dtype.kind
        if kind == "O" and any(x is None or _is_text(x) or _is_complex(x) for x in array.flat):
            kind = "U"
        elif kind in "biufO":
            return array.astype(np.float64, copy=False)
    except (TypeError, ValueError):  # ragged rows, objects that are no numbers
        pass
    if kind == "c":
        raise WrongTypeError(f"{name} must be real, not complex, got {value!r}")
    if kind in "USMmV":
        raise WrongTypeError(f"{name} must be {requirement}, got {value!r}")
    raise ValueError(f"{name} must be {requirement}, got {value!r}")


# Bytes a grid holds per edge of an axis: the edges and, for the kernels, up to
# three derived arrays (squares, sines and cosines, tangents and signs).
_BYTES_PER_EDGE = 4 * 8


def cell_count(name, value):
    """Check a grid axis's cell count: a positive integer whose edges fit in memory."""
    value = count(name, value)
    fits(name, (value + 1) * _BYTES_PER_EDGE, f"a grid with {name}={value:,}")
    return value


def finite(name, value):
    result = number(name, value, "a finite number")
    if not math.isfinite(result):
        raise ValueError(f"{name} must be a finite number, got {value!r}")
    return result


def pair_range(name, value):
    try:
        low, high = value
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a pair (low, high), got {value!r}") from None
    low = finite(f"{name}[0]", low)
    high = finite(f"{name}[1]", high)
    if not low < high:
        raise ValueError(f"{name} must be increasing (low < high), got {value!r}")
    return low, high


def edges(name, edges):
    array = real_array(name, edges, "a 1-D array of numbers").copy()
    if array.ndim != 1 or array.shape[0] < 2:
        raise ValueError(f"{name} must be 1-D with at least 2 edges, got shape {array.shape}")
    if not np.all(np.isfinite(array)):
        raise ValueError(f"{name} must be finite, got {array!r}")
    steps = np.diff(array)
    if not np.all(steps > 0):
        bad = int(np.argmin(steps))
        raise ValueError(
            f"{name} must be strictly increasing; edges[{bad}]={float(array[bad])!r} "
            f">= edges[{bad + 1}]={float(array[bad + 1])!r}"
        )
    return array


# The lengths traces are exact for (docs/geometry.md, "Supported magnitudes").
# Within them every square and product of squares the kernels form stays a
# normal float64; outside, squares underflow to 0 or overflow to inf.
SMALLEST_LENGTH = 1e-100
LARGEST_LENGTH = 1e100
# The thinnest radial cell, as a share of rho_max: ten times the slivers a
# trace absorbs (1e-12 of its scene), so a ray from the centre keeps every shell.
THINNEST_SHELL = 1e-11
# Origins farther than this many rho_max from the centre: rounding of the line
# (eps |o|) and the slivers absorbed (1e-12 of the scene) outgrow the cells.
# (``TOO_FAR`` says it in words.)
FARTHEST = 1e9


def rho_scale(rho_edges, low_name, high_name):
    """Reject radii outside ``[SMALLEST_LENGTH, LARGEST_LENGTH]`` (``rho_edges[0]`` may be 0).

    ``low_name`` and ``high_name`` name the argument that gave the first
    and the last edge.
    """
    positive = rho_edges[rho_edges > 0.0]
    if positive[-1] > LARGEST_LENGTH:
        name, bad = high_name, rho_edges[-1]
    elif positive[0] < SMALLEST_LENGTH:
        name, bad = low_name if rho_edges[0] > 0.0 else high_name, positive[0]
    else:
        widths = np.diff(rho_edges)
        thinnest = int(np.argmin(widths))
        if widths[thinnest] < THINNEST_SHELL * rho_edges[-1]:
            raise ValueError(
                f"radial cells must be at least {THINNEST_SHELL:g} rho_max wide, got cell "
                f"{thinnest} of {widths[thinnest]:.3g} (rho_max {rho_edges[-1]:.3g}): a trace "
                "absorbs slivers of 1e-12 of its scene, so a ray from the centre would drop "
                "such a shell that a map's scan marks"
            )
        return
    raise ValueError(
        f"{name} must lie within [{SMALLEST_LENGTH:g}, {LARGEST_LENGTH:g}], got {float(bad)!r}: "
        "traces are exact for lengths in that range (rho_min may be 0); measure in another "
        "unit to bring the grid into it"
    )


def theta_width(low, high, name):
    width = high - low
    if width > 2 * np.pi + _FULL_TURN_TOL:
        raise ValueError(f"{name} spans {width!r} rad; an azimuth range is at most 2*pi")
    return abs(width - 2 * np.pi) <= _FULL_TURN_TOL


def phi_range(low, high, name):
    half = np.pi / 2
    if low < -half - _FULL_TURN_TOL or high > half + _FULL_TURN_TOL:
        raise ValueError(f"{name} must lie in [-pi/2, pi/2], got ({low!r}, {high!r})")


def points(name, points):
    """Coerce to a C-contiguous (M, 3) float64 array of finite points; and whether one was given."""
    array = real_array(name, points)
    single = array.ndim == 1
    if single:
        array = array[None, :]
    if array.ndim != 2 or array.shape[1] != 3:
        raise ValueError(f"{name} must have shape (M, 3) or (3,), got {np.shape(points)}")
    array = np.ascontiguousarray(array)
    _require_finite(name, array)
    return array, single


def grid(grid):
    """``grid`` must be a :class:`~logsph_trace.Grid`."""
    from .grid import Grid  # grid.py validates with this module: import when called

    if not isinstance(grid, Grid):
        raise ValueError(f"grid must be a logsph_trace.Grid, got {type(grid).__name__}")


def choice(name, value, options):
    """``value`` must be one of ``options``."""
    if value not in options:
        raise ValueError(f"{name} must be one of {options}, got {value!r}")
    return value


# How a bad row is reported, worded once for the checks on the host and on the GPU.
NOT_FINITE = "{name} must be finite; row {row} is {value}"
TOO_LONG = ("{name} must be shorter than about 1e154 (its square must be finite); "
            "row {row} is {value}")
TOO_FAR = ("{name} must lie within 1e9 rho_max ({reach:.3g}) of the grid's centre, where "
           "traces are exact; row {row} is {value}, {distance:.3g} away (a mix-up of units or "
           "frames?)")
ZERO = "{name} must be non-zero; row {row} is {value}"
NEGATIVE = "{name} must be >= 0 (inf allowed); row {row} is {value}"

DEVICES = ("cpu", "cuda")


def device(value):
    """``device`` must be "cpu" or "cuda" (whether CUDA works is asked later, on use)."""
    return choice("device", value, DEVICES)


def on_gpu(value):
    """Tell whether ``value`` is a GPU array.

    It speaks the CUDA Array Interface (CuPy, PyTorch, numba-cuda), or is a
    device array of Numba's CUDA simulator.
    """
    return (hasattr(value, "__cuda_array_interface__")
            or type(value).__module__.startswith("numba.cuda.simulator"))


def host_only(device, **values):
    """GPU arrays need ``device="cuda"``: say so rather than fail inside numpy."""
    if device != "cuda":
        for name, value in values.items():
            if on_gpu(value):
                raise ValueError(f"{name} is a GPU array: pass device='cuda', or copy it to "
                                 "the host first")


def _rows_of_three(name, value):
    """Coerce to a (m, 3) float64 array (a (3,) vector is one row)."""
    array = real_array(name, value)
    if array.ndim == 1:
        array = array[None, :]
    if array.ndim != 2 or array.shape[1] != 3:
        raise ValueError(f"{name} must have shape (m, 3) or (3,), got {np.shape(value)}")
    return array


# From this many rows on, rows' lengths are taken on all threads (``row_norms``);
# below, one thread is quicker than waking the threads (and the serial build
# of ``row_norms`` compiles faster).
PARALLEL_CHECK_ROWS = 1 << 15


def _all_finite(array):
    """Whether a C-contiguous (m, 3) float64 array holds no NaN or inf (one flat pass).

    numpy's, on one thread: a parallel kernel took 0.47 ms against numpy's
    1.01 ms for a million rows (2 threads; the Motorcycle frame's scan has a
    third of that), and 0.7 s to compile on the first call.
    """
    return bool(np.isfinite(array).all())  # a reduction per row costs 30x more


def _require_finite(name, array):
    """Raise ValueError naming the first row with NaN or inf (one flat pass).

    ``array``: C-contiguous (m, 3) float64.
    """
    if not _all_finite(array):
        row = int(np.argmin(np.all(np.isfinite(array), axis=1)))
        raise ValueError(NOT_FINITE.format(name=name, row=row, value=array[row].tolist()))


def vectors(name, value):
    """Coerce to a C-contiguous (m, 3) float64 array; reject NaN and inf."""
    array = np.ascontiguousarray(_rows_of_three(name, value))
    _require_finite(name, array)
    return array


def finite_rows(name, value):
    """Coerce to a C-contiguous (m, 3) float64 array without its NaN or infinite rows.

    Returns (the array, the rows kept: a boolean mask, or None when all are).
    """
    array = np.ascontiguousarray(_rows_of_three(name, value))
    if _all_finite(array):  # the usual case: one flat pass
        return array, None
    keep = np.all(np.isfinite(array), axis=1)
    return np.ascontiguousarray(array[keep]), keep


# The largest object label: a map stores its labels as int32.
LARGEST_LABEL = int(np.iinfo(np.int32).max)


def labels(name, value, shape):
    """Object labels: integers in ``[0, LARGEST_LABEL]`` of ``shape``, as contiguous int64.

    Compared in their own dtype before any conversion, so that no value
    wraps (``uint32`` 0xFFFFFFFF is not -1, 2**32 + 5 is not 5).
    """
    array = np.asarray(value)
    if array.shape != shape:
        raise ValueError(f"{name} must have shape {shape}, got {array.shape}")
    if array.dtype.kind not in "iub":
        raise ValueError(f"{name} must be integers (0 = no object), got dtype {array.dtype}")
    if array.size and array.min() < 0:
        raise ValueError(f"{name} must be >= 0 (0 = no object), got {int(array.min())}")
    if array.size and array.max() > LARGEST_LABEL:
        raise ValueError(f"{name} must be at most {LARGEST_LABEL:,} (a map stores int32 "
                         f"labels), got {int(array.max())}")
    return np.ascontiguousarray(array, dtype=np.int64)


def row_norms(vectors):
    """Euclidean length of each row of an (m, 3) float64 array, without overflow or underflow.

    Computed in parallel by ``kernels.locate.norm3``, the one definition every
    path shares: ordinary rows are ``sqrt(x*x + y*y + z*z)``, rows beyond
    ~1e154 or below ~1e-154 are scaled by their largest component first.
    """
    norms = np.empty(vectors.shape[0])
    kernel = _locate.row_norms.pick(vectors.shape[0] >= PARALLEL_CHECK_ROWS)
    kernel(np.ascontiguousarray(vectors, dtype=np.float64), norms)
    return norms


def unit_directions(directions, name="directions"):
    """Rows scaled to unit length without overflow or underflow; zero rows are an error."""
    norms = row_norms(directions)
    if np.any(norms == 0.0):
        row = int(np.argmin(norms))
        raise ValueError(ZERO.format(name=name, row=row, value=directions[row].tolist()))
    return np.ascontiguousarray(directions / norms[:, None])


def reach(grid):
    """How far from ``grid``'s centre an origin may lie: ``FARTHEST`` rho_max."""
    return FARTHEST * grid.rho_max


def _too_far(name, row, value, limit):
    return ValueError(TOO_FAR.format(name=name, reach=limit, row=row, value=value,
                                     distance=math.hypot(*value)))


def origin_size(name, origins, limit=math.inf):
    """Reject origins whose squared length overflows, or farther than ``limit``.

    The kernels use the squared length; ``limit`` is :func:`reach` of the grid.
    """
    squares = np.einsum("ij,ij->i", origins, origins)
    if not np.all(np.isfinite(squares)):
        row = int(np.argmin(np.isfinite(squares)))
        raise ValueError(TOO_LONG.format(name=name, row=row, value=origins[row].tolist()))
    beyond = squares > limit * limit
    if np.any(beyond):
        row = int(np.argmax(beyond))
        raise _too_far(name, row, origins[row].tolist(), limit)
    return origins


def _repeat_row(row, n):
    return np.ascontiguousarray(np.broadcast_to(row, (n, row.shape[1])))


def shared_rows(origins, directions, repeat=_repeat_row):
    """Pair (m, 3) origins with (m, 3) directions; a single row on either side serves every ray.

    That is numpy's broadcasting of a row of one: one eye and many
    directions, or many origins and one direction. The shared row is
    repeated, ``repeat(row, m)``, since every ray needs its own (24 bytes
    a ray); the GPU passes its own ``repeat``.
    """
    m, n = origins.shape[0], directions.shape[0]
    if m == 1 and n != 1:
        origins = repeat(origins, n)
    elif n == 1 and m != 1:
        directions = repeat(directions, m)
    elif m != n:
        raise ValueError(f"directions has {n} rows but origins has {m}")
    return origins, directions


def rays(origins, directions, limit=math.inf):
    """Check a batch of rays: C-contiguous (m, 3) float64 origins and unit directions.

    ``directions=None`` reads (m, 6) rows of origin + direction; otherwise a
    single origin or direction is shared by every ray (:func:`shared_rows`).
    Origins farther than ``limit`` from the centre are an error (:func:`reach`).
    """
    if directions is None:
        array = real_array("origins", origins)
        if array.ndim != 2 or array.shape[1] != 6:
            raise ValueError(
                "with directions=None, origins must be one (m, 6) array of origin + direction, "
                f"got shape {np.shape(origins)}"
            )
        origins, directions = array[:, :3], array[:, 3:]
    origins, directions = (np.ascontiguousarray(array) for array in shared_rows(
        _rows_of_three("origins", origins), _rows_of_three("directions", directions)))
    if origins.shape[0] >= PARALLEL_CHECK_ROWS:  # below, one thread beats waking the others
        # Every row checked and scaled in one pass; on a fault, the checks in
        # turn below name the first (the units are the same array for array).
        units = np.empty(origins.shape)
        if _locate.unit_rays(origins, directions, units, min(limit * limit, _FLOAT_MAX)):
            return origins, units
    origins = origin_size("origins", vectors("origins", origins), limit)
    return origins, unit_directions(vectors("directions", directions))


def distances(t_max, n_rays):
    """``t_max`` as a contiguous (m,) float64 array; ``None`` is no limit."""
    if t_max is None:
        return np.full(n_rays, np.inf)
    array = real_array("t_max", t_max, "a number or an array of numbers")
    if array.ndim == 0:
        array = np.full(n_rays, float(array))
    if array.shape != (n_rays,):
        raise ValueError(f"t_max must be a number or have shape ({n_rays},), got {array.shape}")
    if np.any(np.isnan(array)) or np.any(array < 0):
        bad = int(np.argmax(np.isnan(array) | (array < 0)))
        raise ValueError(NEGATIVE.format(name="t_max", row=bad, value=float(array[bad])))
    return np.ascontiguousarray(array)


MAX_ITERATIONS = int(np.iinfo(np.int64).max)


def bisect_options(grid, default_t, max_iter):
    default_t = number("default_t", default_t, "a positive number")
    if not (np.isfinite(default_t) and default_t > 0):
        raise ValueError(f"default_t must be a positive finite number, got {default_t!r}")
    if max_iter is None:
        n_rho, n_theta, n_phi = grid.shape
        max_iter = 64 * (2 * n_rho + n_theta + 2 * n_phi + 4)
    if (isinstance(max_iter, bool) or not isinstance(max_iter, (int, np.integer))
            or not 1 <= max_iter <= MAX_ITERATIONS):
        raise ValueError(f"max_iter must be a positive integer up to {MAX_ITERATIONS:,} "
                         f"(an int64), got {max_iter!r}")
    return default_t, int(max_iter)


def half_angle(half_angle, name="half_angle"):
    """Check a cone half-angle: radians in [0, pi/2); warn above ``DEGREES_LIKELY``."""
    value = number(name, half_angle, "a number of radians")
    if not (np.isfinite(value) and 0.0 <= value < np.pi / 2):
        raise ValueError(f"{name} must be in [0, pi/2) radians, got {half_angle!r}")
    if value > DEGREES_LIKELY:
        warn(
            f"{name}={value:g} rad is a {math.degrees(value):.1f}-degree cone; angles are in "
            f"radians (np.radians({value:g}) if you meant {value:g} degrees)",
            AngleUnitWarning)
    return value


def half_angles(name, values, count):
    """Cone half-angles: one number or ``count`` of them, each as :func:`half_angle` checks it.

    Returns a (count,) float64 array; warns once if any is above ``DEGREES_LIKELY``.
    """
    angles = real_array(name, values, "numbers of radians")
    if angles.ndim > 1 or (angles.ndim == 1 and angles.shape[0] != count):
        raise ValueError(f"{name} must be one number or one per cone ({count}), "
                         f"got shape {angles.shape}")
    angles = np.ascontiguousarray(np.broadcast_to(angles, (count,)))
    bad = ~((angles >= 0.0) & (angles < np.pi / 2))  # NaN fails both
    if np.any(bad):
        row = int(np.argmax(bad))
        raise ValueError(f"{name} must be in [0, pi/2) radians, got {angles[row]!r} "
                         f"(cone {row})")
    if count and angles.max() > DEGREES_LIKELY:
        half_angle(angles.max(), name)  # its warning, for the widest
    return angles


def vector(name, value):
    """One 3-vector: shape (3,) (or (1, 3)), finite, returned as (3,) float64."""
    array = np.ascontiguousarray(_rows_of_three(name, value))
    if array.shape[0] == 1:
        # Checked as Python floats: a numpy reduction costs microseconds, and
        # ten times that with the caches cold after a scan's kernels.
        row = array[0].tolist()
        if not all(map(math.isfinite, row)):
            raise ValueError(NOT_FINITE.format(name=name, row=0, value=row))
        return array[0]
    vectors(name, array)  # names a row that is not finite first, as for many vectors
    raise ValueError(f"{name} must be one vector of shape (3,), got shape {np.shape(value)}")


def point(name, value, limit=math.inf):
    """One position: a finite :func:`vector` at most ``limit`` from the centre.

    Its squared length must be finite too (see :func:`origin_size`).
    """
    array = vector(name, value)
    x, y, z = array.tolist()
    if not math.isfinite(x * x + y * y + z * z):
        raise ValueError(TOO_LONG.format(name=name, row=0, value=[x, y, z]))
    if not math.hypot(x, y, z) <= limit:
        raise _too_far(name, 0, [x, y, z], limit)
    return array


def unit(name, value):
    """One direction, scaled to unit length; zero is an error."""
    return unit_directions(vector(name, value)[None, :], name)[0]


_PACKAGE = os.path.dirname(os.path.abspath(__file__))


def warn(message, category):
    """Warn, attributed to the user's line: the first caller outside this package."""
    frame, level = sys._getframe(1), 2  # level 1 is this function
    while frame is not None and os.path.abspath(frame.f_code.co_filename).startswith(_PACKAGE):
        frame, level = frame.f_back, level + 1
    warnings.warn(message, category, stacklevel=level)


class UnitWarning(UserWarning):
    """An input whose values suggest a mistake of units or frames."""


class AngleUnitWarning(UnitWarning):
    """An angle that is probably in degrees where radians are expected."""


class DepthUnitWarning(UnitWarning):
    """A depth image or scan whose scale does not fit the map (millimetres as metres, say)."""


# Above this a cone half-angle is more likely degrees typed as radians
# (half_angle=5 meaning 5 degrees) than a gaze: 30 degrees.
DEGREES_LIKELY = math.radians(30.0)


def probability(name, value, low=0.0, high=1.0):
    result = number(name, value, "a probability")
    if not (low < result < high):
        raise ValueError(f"{name} must be in ({low:g}, {high:g}), got {value!r}")
    return result


def held(what, array, dtype, shape, remedy, write=True):
    """Raise ValueError unless an array an object holds between calls is as the kernels need it.

    ``array`` must still be a C-contiguous, aligned ``dtype`` array of
    ``shape`` (``None``: any length on that axis), writeable when ``write``.
    O(1), for every use: numpy lets an array's shape, dtype and flags be
    changed in place (``a.dtype = np.float64`` halves a float32 array), and a
    kernel indexing the old layout would read or write past its end.
    """
    if not isinstance(array, np.ndarray):
        raise ValueError(f"{what} must be a numpy array, got {type(array).__name__}")
    flags = array.flags
    fits = array.dtype == dtype and array.ndim == len(shape) and all(
        want is None or got == want for got, want in zip(array.shape, shape))
    if not (fits and flags.c_contiguous and flags.aligned and (flags.writeable or not write)):
        wanted = "(" + ", ".join("n" if n is None else str(n) for n in shape) + \
            ("," if len(shape) == 1 else "") + ")"
        raise ValueError(
            f"{what} was changed in place: it must stay a {'writeable, ' if write else ''}"
            f"C-contiguous {np.dtype(dtype)} array of shape {wanted}, got {array.dtype} "
            f"{array.shape}, writeable={flags.writeable}, C-contiguous={flags.c_contiguous}; "
            f"{remedy}")


def log_odds(value, shape):
    """Check a map's log-odds: return a writeable C-contiguous float32 array of ``shape``."""
    try:
        array = np.asarray(value)
        if array.dtype.kind not in "biuf":
            raise TypeError
    except (TypeError, ValueError):
        raise ValueError(
            f"log_odds must be an array of numbers of shape {shape}, got {type(value).__name__}"
        ) from None
    if array.shape != tuple(shape):
        raise ValueError(f"log_odds has shape {array.shape} but the grid has shape {tuple(shape)}")
    array = np.require(array, dtype=np.float32, requirements=["C", "W", "A"])
    if not np.all(np.isfinite(array)):
        raise ValueError("log_odds must be finite")
    return array


def _read_small(path):
    """Return the bytes of a small file (under /proc or /sys), or None if it cannot be read.

    One ``os.read``: a text-mode ``open`` costs several times as much, and
    this runs before every large batch.
    """
    try:
        descriptor = os.open(path, os.O_RDONLY)
    except OSError:
        return None
    try:
        return os.read(descriptor, 1 << 16)
    except OSError:
        return None
    finally:
        os.close(descriptor)


def _mem_available(meminfo):
    """Return ``MemAvailable`` in bytes from the text of /proc/meminfo, or None."""
    text = b"\n" + meminfo
    at = text.find(b"\nMemAvailable:")
    if at < 0:
        return None
    try:
        return int(text[at + 14:].split(b"\n", 1)[0].split()[0]) * 1024
    except (ValueError, IndexError):
        return None


# The memory cgroup's mount, (limit, usage) files, and the controllers field of
# its line in /proc/self/cgroup: cgroup v2, then v1.
CGROUP_MEMORY = (("/sys/fs/cgroup", "memory.max", "memory.current", b""),
                 ("/sys/fs/cgroup/memory", "memory.limit_in_bytes", "memory.usage_in_bytes",
                  b"memory"))


def _cgroup_paths():
    """Return the process's cgroup path per hierarchy (/proc/self/cgroup): {controllers: path}.

    A v2 line is ``0::/path``; a v1 memory line ``N:memory:/path`` (or
    ``N:memory,other:/path``). Unknown: the root.
    """
    paths = {}
    for line in (_read_small("/proc/self/cgroup") or b"").splitlines():
        parts = line.split(b":", 2)
        if len(parts) == 3:
            controllers = b"memory" if b"memory" in parts[1].split(b",") else parts[1]
            paths.setdefault(controllers, parts[2].decode(errors="replace").strip())
    return paths


def _cgroup_room():
    """Return the least room (limit less usage) of the process's memory cgroups, or None.

    Its own cgroup and each one above it count: a container's limit often
    sits below the root. cgroup v2 first; v1 only where v2's files are not
    there. None when no limit is set.
    """
    paths = _cgroup_paths()
    for mount, limit_name, usage_name, controllers in CGROUP_MEMORY:
        parts = [part for part in paths.get(controllers, "/").split("/") if part]
        rooms, found = [], False
        for depth in range(len(parts), -1, -1):  # innermost first, the mount's root last
            folder = "/".join([mount, *parts[:depth]])
            limit = _read_small(f"{folder}/{limit_name}")
            usage = _read_small(f"{folder}/{usage_name}")
            if limit is None or usage is None:
                continue
            found = True
            try:
                if limit.strip() != b"max":
                    rooms.append(int(limit) - int(usage))
            except ValueError:
                continue
        if found:
            return min(rooms) if rooms else None
    return None


def _address_space_room():
    """Return ``RLIMIT_AS`` less the process's address space (``VmSize``); None if unlimited."""
    try:
        limit = resource.getrlimit(resource.RLIMIT_AS)[0]
    except (AttributeError, OSError, ValueError):  # no resource module (Windows)
        return None
    if limit == resource.RLIM_INFINITY:
        return None
    status = b"\n" + (_read_small("/proc/self/status") or b"")
    at = status.find(b"\nVmSize:")
    try:
        used = int(status[at + 8:].split(b"\n", 1)[0].split()[0]) * 1024 if at >= 0 else 0
    except (ValueError, IndexError):
        used = 0
    return limit - used


def available_memory():
    """Return the bytes this process can still allocate, or None if unknown.

    The smallest of the system's ``MemAvailable``, each enclosing memory
    cgroup's limit less its usage (v2, or v1), and ``RLIMIT_AS`` less the
    address space in use.
    """
    meminfo = _read_small("/proc/meminfo")
    limits = [None if meminfo is None else _mem_available(meminfo), _cgroup_room(),
              _address_space_room()]
    limits = [limit for limit in limits if limit is not None]
    return min(limits) if limits else None


# A request below this many bytes is not checked by ``fits``: reading the
# available memory (/proc and the cgroup's files) costs about 0.05 ms, a share
# of a small cone's time that grows with the threads, and a machine that
# cannot spare this much fails in numpy's own allocation anyway.
SMALL_REQUEST_BYTES = 1 << 24


def fits(name, nbytes, what):
    """Raise ``MemoryError`` naming ``name`` before allocating ``nbytes`` that cannot fit.

    Checked against :func:`available_memory`, so a request that is bound to
    fail does so at once with a message, not after minutes of swapping or
    with the process killed silently by the kernel. Requests under
    ``SMALL_REQUEST_BYTES`` (16 MiB) pass unchecked.
    """
    if nbytes < SMALL_REQUEST_BYTES:
        return
    free = available_memory()
    if free is not None and nbytes > free:
        raise MemoryError(
            f"{name}: {what} needs about {nbytes / 2**30:.1f} GiB, but only "
            f"{max(free, 0) / 2**30:.1f} GiB is available"
        )
