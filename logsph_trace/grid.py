"""The bounded log-spherical partition of the paper's Eq. 1-3 (conventions: docs/geometry.md)."""

import math

import numpy as np

from . import _validate as validate
from .kernels import locate as _locate
from .kernels.crossings import FLAT_TAN2
from .trace import cuda_backend

SPACINGS = ("log", "paper", "uniform")
_SPACING_KIND = {"log": _locate.LOG, "paper": _locate.PAPER, "uniform": _locate.UNIFORM}


def _each(function, edges):
    """Return ``function`` (from ``math``) of every edge, one at a time, as float64.

    The kernels' sines, cosines and squared tangents of the edges come from
    the platform's libm rather than numpy's vectorised loops, whose results
    change by an ulp between numpy releases (numpy 1.24's sin differs from
    the correctly rounded value on most of the test grids' edges; its
    tan(pi/4) is 1.0). A ray tangent to a cone in exact arithmetic then had
    a short detour through the cell beyond it, or none, by numpy's version.
    """
    return np.array([function(edge) for edge in edges.tolist()], dtype=np.float64)


# An elevation edge this close to 0 is the plane y = 0 (``_flat_cone_to_plane``).
FLAT_CONE = 4 * np.finfo(np.float64).eps


def _flat_cone_to_plane(phi_edges):
    """Return ``phi_edges`` with an edge within ``FLAT_CONE`` of 0 set to exactly 0.

    ``np.linspace(-pi/2, pi/2, 101)`` puts its middle edge at 2.2e-16, not 0: a
    cone so flat that where a ray crosses it, its height above y = 0 is below
    the rounding of the crossing's height, so the trace's test of which half
    of the cone a crossing lies on was a coin toss, and a ray rising through
    it lost the crossing and every one after it (it kept the cell below the
    plane to its end). As the plane, its crossing is the plane's.
    """
    flat = np.abs(phi_edges) <= FLAT_CONE
    if not flat.any():
        return phi_edges
    if np.count_nonzero(flat) > 1:
        raise ValueError(f"phi_edges has {np.count_nonzero(flat)} edges within {FLAT_CONE:.2g} "
                         "of 0, which are all the plane y = 0: keep one")
    phi_edges = phi_edges.copy()
    phi_edges[flat] = 0.0
    return phi_edges


def rho_edges_for(rho_min, rho_max, n_rho, spacing="log"):
    """Radial edges for one of the named spacings (docs/geometry.md, "Radial spacings").

    Parameters
    ----------
    rho_min, rho_max : float
        Radial bounds of the region, in the user's length unit.
    n_rho : int
        Number of radial cells.
    spacing : {"log", "paper", "uniform"}
        ``log``: ``rho_min * (rho_max / rho_min) ** (i / n_rho)``;
        ``paper``: ``rho_min + b ** i`` with ``b = (rho_max - rho_min) ** (1 / n_rho)``
        (Eq. 3; cell 0 also holds ``[rho_min, rho_min + 1)``);
        ``uniform``: evenly spaced.

    Returns
    -------
    numpy.ndarray, shape (n_rho + 1,), float64
    """
    rho_min = validate.finite("rho_min", rho_min)
    rho_max = validate.finite("rho_max", rho_max)
    n_rho = validate.cell_count("n_rho", n_rho)
    if spacing not in SPACINGS:
        raise ValueError(f"spacing must be one of {SPACINGS}, got {spacing!r}")
    if rho_min < 0:
        raise ValueError(f"rho_min must be >= 0, got {rho_min!r}")
    if not rho_min < rho_max:
        raise ValueError(f"rho_min must be < rho_max, got rho_min={rho_min!r}, rho_max={rho_max!r}")
    index = np.arange(n_rho + 1, dtype=np.float64)
    if spacing == "log":
        if rho_min <= 0:
            raise ValueError(f"log spacing needs rho_min > 0, got rho_min={rho_min!r}")
        edges = rho_min * (rho_max / rho_min) ** (index / n_rho)
    elif spacing == "paper":
        if rho_max - rho_min <= 1:
            raise ValueError(
                "paper spacing needs rho_max - rho_min > 1 (Eq. 3 depends on the length unit), "
                f"got rho_max - rho_min={rho_max - rho_min!r}"
            )
        base = (rho_max - rho_min) ** (1.0 / n_rho)
        edges = rho_min + base**index
        edges[0] = rho_min
    else:
        edges = np.linspace(rho_min, rho_max, n_rho + 1)
    edges[0] = rho_min
    edges[-1] = rho_max
    validate.rho_scale(edges, "rho_min", "rho_max")
    if not np.all(np.diff(edges) > 0):
        raise ValueError(f"n_rho={n_rho} is too fine for rho in ({rho_min!r}, {rho_max!r})")
    return edges


class Grid:
    """A bounded log-spherical partition: ``rho x theta x phi`` cells (paper Eq. 1-2).

    Parameters
    ----------
    rho_min, rho_max : float
        Radial bounds. ``rho < rho_min`` is the egocentric gap (not part of the region).
    n_rho, n_theta, n_phi : int
        Cell counts along rho, theta (azimuth) and phi (elevation).
    theta_range : (float, float), optional
        Azimuth range in radians, width in ``(0, 2*pi]``; it may start anywhere.
        Default ``(-pi, pi)``, the full circle.
    phi_range : (float, float), optional
        Elevation range in radians within ``[-pi/2, pi/2]``. Default the full range.
    spacing : {"log", "paper", "uniform"}, optional
        Radial spacing, see :func:`rho_edges_for`. Default ``"log"``.

    Attributes
    ----------
    rho_edges, theta_edges, phi_edges : numpy.ndarray
        Strictly increasing cell edges, float64, lengths ``n + 1``.
    shape : tuple of int
        ``(n_rho, n_theta, n_phi)``; an occupancy array over the grid has this shape.
    spacing : str
        ``"log"``, ``"paper"``, ``"uniform"`` or ``"explicit"``.

    Notes
    -----
    The frame (docs/geometry.md): ``theta = atan2(x, z)`` is the azimuth about the y
    axis from +z towards +x, ``phi = atan2(y, sqrt(x^2 + z^2))`` the elevation.
    Cell ``(i, j, k)`` holds ``rho_edges[i] <= rho < rho_edges[i+1]`` and likewise
    for theta and phi; a value on the last edge of an axis belongs to the last cell.
    """

    def __init__(self, rho_min, rho_max, n_rho, n_theta, n_phi,
                 theta_range=(-np.pi, np.pi), phi_range=(-np.pi / 2, np.pi / 2),
                 spacing="log"):
        rho_edges = rho_edges_for(rho_min, rho_max, n_rho, spacing)
        n_theta = validate.cell_count("n_theta", n_theta)
        n_phi = validate.cell_count("n_phi", n_phi)
        theta_min, theta_max = validate.pair_range("theta_range", theta_range)
        phi_min, phi_max = validate.pair_range("phi_range", phi_range)
        if validate.theta_width(theta_min, theta_max, "theta_range"):
            theta_max = theta_min + 2 * np.pi
        validate.phi_range(phi_min, phi_max, "phi_range")
        theta_edges = np.linspace(theta_min, theta_max, n_theta + 1)
        phi_edges = _flat_cone_to_plane(
            np.linspace(max(phi_min, -np.pi / 2), min(phi_max, np.pi / 2), n_phi + 1))
        self._setup(rho_edges, theta_edges, phi_edges, spacing,
                    _SPACING_KIND[spacing], _locate.UNIFORM, _locate.UNIFORM)

    @classmethod
    def from_edges(cls, rho_edges, theta_edges, phi_edges, spacing=None):
        """Build a grid from any strictly increasing edges (radians for the angles).

        The paper's remark that the method generalises "by substituting the
        conversion function": lookups use binary search on these edges.
        ``rho_edges[0]`` must be ``>= 0``; ``theta_edges`` may span at most ``2*pi``
        (exactly ``2*pi`` is the full circle with a seam at ``theta_edges[0]``);
        ``phi_edges`` must lie in ``[-pi/2, pi/2]``.

        ``spacing`` (``"log"``, ``"paper"`` or ``"uniform"``) restores a grid
        made with that radial spacing, such as a saved map's, with its
        closed-form lookups: the radial edges must then be exactly that
        spacing's, and evenly spaced angular edges get the closed form too.
        """
        rho = validate.edges("rho_edges", rho_edges)
        theta = validate.edges("theta_edges", theta_edges)
        phi = validate.edges("phi_edges", phi_edges)
        if rho[0] < 0:
            raise ValueError(f"rho_edges[0] must be >= 0, got {rho[0]!r}")
        validate.rho_scale(rho, "rho_edges", "rho_edges")
        if validate.theta_width(theta[0], theta[-1], "theta_edges"):
            theta[-1] = theta[0] + 2 * np.pi
        validate.phi_range(phi[0], phi[-1], "phi_edges")
        phi = _flat_cone_to_plane(np.clip(phi, -np.pi / 2, np.pi / 2))
        kinds = [_locate.EXPLICIT] * 3
        if spacing is None or spacing == "explicit":
            spacing = "explicit"
        else:
            if spacing not in SPACINGS:
                raise ValueError(f"spacing must be one of {SPACINGS} or None, got {spacing!r}")
            if not np.array_equal(rho, rho_edges_for(rho[0], rho[-1], rho.size - 1, spacing)):
                raise ValueError(f"rho_edges are not the edges of {spacing!r} spacing")
            kinds[0] = _SPACING_KIND[spacing]
            for axis, edges, even in ((1, theta, np.linspace(theta[0], theta[-1], theta.size)),
                                      (2, phi, _flat_cone_to_plane(
                                          np.linspace(phi[0], phi[-1], phi.size)))):
                if np.array_equal(edges, even):
                    kinds[axis] = _locate.UNIFORM
        grid = cls.__new__(cls)
        grid._setup(rho, theta, phi, spacing, *kinds)  # Grid's own set-up, after its checks
        return grid

    @classmethod
    def from_increments(cls, rho_min, rho_max, n_rho, d_theta=1.0, d_phi=1.0,
                        theta_range=(-180.0, 180.0), phi_range=(-90.0, 90.0), spacing="paper"):
        """Build a grid in the paper's terms: angular increments and ranges in **degrees**.

        ``d_theta`` and ``d_phi`` must divide their ranges into a whole number of
        cells (section 2.1: "discretised into cells by defining the increment in
        the angles"). The default radial spacing is the paper's Eq. 3.
        """
        d_theta = validate.finite("d_theta", d_theta)
        d_phi = validate.finite("d_phi", d_phi)
        counts = []
        for name, step, span in (("d_theta", d_theta, theta_range), ("d_phi", d_phi, phi_range)):
            low, high = validate.pair_range(name.replace("d_", "") + "_range", span)
            if step <= 0:
                raise ValueError(f"{name} must be > 0 degrees, got {step!r}")
            cells = (high - low) / step
            if abs(cells - round(cells)) > 1e-9 * max(1.0, cells):
                raise ValueError(
                    f"{name}={step!r} degrees does not divide the range {span!r} into whole cells"
                )
            counts.append(max(int(round(cells)), 1))
        return cls(rho_min, rho_max, n_rho, counts[0], counts[1],
                   theta_range=tuple(np.radians(theta_range)),
                   phi_range=tuple(np.radians(phi_range)), spacing=spacing)

    def _setup(self, rho_edges, theta_edges, phi_edges, spacing, rho_kind, theta_kind, phi_kind):
        # What a grid and one trace through it hold, all axes together: the
        # kernels' tables (edges and squares; edges, sines and cosines; edges,
        # squared tangents, signs, sines and cosines) and a ray's scratch of
        # crossing times and zones (two int64/float64 rows of 3 x the most
        # crossings of any family).
        edges = (rho_edges.size, theta_edges.size, phi_edges.size)
        tables = 8 * (2 * edges[0] + 3 * edges[1] + 5 * edges[2])
        scratch = 48 * (max(2 * edges[0] + 1, edges[1] + 1, 2 * edges[2] + 1) + 16)
        validate.fits("grid", tables + scratch,
                      f"a grid of {edges[0] - 1:,} x {edges[1] - 1:,} x {edges[2] - 1:,} cells "
                      "(its tables and a trace's scratch)")
        for array in (rho_edges, theta_edges, phi_edges):
            array.setflags(write=False)
        fields = dict(
            rho_edges=rho_edges, theta_edges=theta_edges, phi_edges=phi_edges, spacing=spacing,
            rho_kind=int(rho_kind), theta_kind=int(theta_kind), phi_kind=int(phi_kind),
            theta_full=bool(theta_edges[-1] - theta_edges[0] >= 2 * np.pi),
            # the narrowest cell's angle, theta or phi (a scan's plan and a cone's ray
            # count read it)
            _narrowest_angle=float(min(np.min(np.diff(theta_edges)), np.min(np.diff(phi_edges)))),
        )
        for name, value in fields.items():
            object.__setattr__(self, name, value)

    def __setstate__(self, state):
        # A pickled or deep-copied grid (a spawned worker's) comes back with
        # writeable arrays: read-only again, and its kernels' bundle made anew.
        state = dict(state)
        state.pop("_kernel_args", None)
        for value in state.values():
            if isinstance(value, np.ndarray):
                value.setflags(write=False)
        for name, value in state.items():
            object.__setattr__(self, name, value)

    def __setattr__(self, name, value):
        # A grid is shared by maps, traces and the kernels' cached bundle: a
        # changed edge array would make them disagree (and index out of bounds).
        raise AttributeError(f"Grid is immutable; build a new one instead of setting {name!r}")

    # ---- shape and bounds -------------------------------------------------
    @property
    def shape(self):
        """``(n_rho, n_theta, n_phi)``."""
        return (self.rho_edges.size - 1, self.theta_edges.size - 1, self.phi_edges.size - 1)

    @property
    def n_rho(self):
        """Number of radial cells."""
        return self.shape[0]

    @property
    def n_theta(self):
        """Number of azimuthal cells."""
        return self.shape[1]

    @property
    def n_phi(self):
        """Number of elevation cells."""
        return self.shape[2]

    @property
    def rho_min(self):
        """Inner radius of the region (the egocentric gap is below it)."""
        return float(self.rho_edges[0])

    @property
    def rho_max(self):
        """Outer radius of the region."""
        return float(self.rho_edges[-1])

    @property
    def theta_range(self):
        """``(theta_min, theta_max)`` in radians."""
        return float(self.theta_edges[0]), float(self.theta_edges[-1])

    @property
    def phi_range(self):
        """``(phi_min, phi_max)`` in radians."""
        return float(self.phi_edges[0]), float(self.phi_edges[-1])

    def __repr__(self):
        n_rho, n_theta, n_phi = self.shape
        return (
            f"Grid(rho=({self.rho_min:g}, {self.rho_max:g}) x {n_rho} [{self.spacing}], "
            f"theta=({self.theta_range[0]:.6g}, {self.theta_range[1]:.6g}) x {n_theta}, "
            f"phi=({self.phi_range[0]:.6g}, {self.phi_range[1]:.6g}) x {n_phi})"
        )

    def __eq__(self, other):
        if not isinstance(other, Grid):
            return NotImplemented
        return (
            np.array_equal(self.rho_edges, other.rho_edges)
            and np.array_equal(self.theta_edges, other.theta_edges)
            and np.array_equal(self.phi_edges, other.phi_edges)
        )

    __hash__ = None

    # ---- arrays the kernels take ------------------------------------------
    def kernel_args(self):
        """Return the grid as the kernels take it: one ``GridArrays`` bundle (cached).

        The cone arrays (``phi_tan2``, ``phi_nappe``) end in
        ``CONE_BLOCK - 1`` zeros, for the exact kernel's blocks of cones.
        Every array is read-only, like the edges: the bundle is shared by
        every later call on this grid.
        """
        cached = getattr(self, "_kernel_args", None)
        if cached is None:
            theta = self.theta_edges
            phi = self.phi_edges
            pad = np.zeros(_locate.CONE_BLOCK - 1)
            tan2 = _each(math.tan, phi) ** 2
            flat = np.flatnonzero((tan2 > 0.0) & (tan2 < FLAT_TAN2))
            cached = _locate.GridArrays(
                self.rho_edges, self.rho_edges**2, self.rho_kind,
                theta, _each(math.sin, theta), _each(math.cos, theta), self.theta_kind,
                self.theta_full,
                phi, np.concatenate([tan2, pad]),
                np.concatenate([np.sign(phi), pad]), self.phi_kind,
                _each(math.sin, phi), _each(math.cos, phi),
                int(flat[0]) if flat.size else 0, int(flat[-1]) + 1 if flat.size else 0,
            )
            for array in cached:
                if isinstance(array, np.ndarray):
                    array.setflags(write=False)
            object.__setattr__(self, "_kernel_args", cached)
        return cached

    # ---- conversions ------------------------------------------------------
    def cell_of(self, points, device="cpu"):
        """Cell index of each point.

        Parameters
        ----------
        points : array_like, shape (M, 3) or (3,)
            Cartesian points (x, y, z).
        device : {"cpu", "cuda"}
            ``"cuda"``: look the points up on an NVIDIA GPU (see
            :func:`~logsph_trace.trace_many`); the cells stay there.
            ``points`` may then be a GPU array (CUDA Array Interface), shape
            (M, 3), read in place.

        Returns
        -------
        numpy.ndarray, int32, shape (M, 3) (or (3,))
            ``(i, j, k)`` per point; ``-1`` in all three columns outside the
            region. With ``device="cuda"``, a numba-cuda device array (CUDA
            Array Interface; ``.copy_to_host()`` gives the numpy array).

        Raises
        ------
        ValueError
            Wrong shape, NaN or infinite points, unknown ``device``.
        RuntimeError
            ``device="cuda"`` without a usable GPU or numba-cuda.
        """
        validate.device(device)
        validate.host_only(device, points=points)
        if validate.on_gpu(points):
            return cuda_backend().cells_of_gpu_points(self, points)
        array, single = validate.points("points", points)
        if device == "cuda":
            cells = cuda_backend().cells_of(self, array)
        else:
            cells = _locate.cells_of_points(array, self.kernel_args())
        return cells[0] if single else cells

    def count_points(self, points):
        """How many of ``points`` lie in each cell: int64, shape ``self.shape``.

        Points outside the region are not counted. With a scan's points this
        is each cell's support, e.g. to leave cells with few returns out of
        :func:`~logsph_trace.label_objects`.
        """
        cells = np.atleast_2d(self.cell_of(points))
        inside = cells[cells[:, 0] >= 0]
        flat = np.ravel_multi_index(tuple(inside.T), self.shape)
        return np.bincount(flat, minlength=int(np.prod(self.shape))).reshape(self.shape)

    def contains(self, points):
        """Boolean mask: which points lie inside the region."""
        cells = self.cell_of(points)
        return cells[..., 0] >= 0

    def cell_bounds(self, cells):
        """Bounds of cells: ``(rho_lo, rho_hi, theta_lo, theta_hi, phi_lo, phi_hi)`` per row.

        Parameters
        ----------
        cells : array_like of int, shape (M, 3) or (3,)

        Returns
        -------
        numpy.ndarray, float64, shape (M, 6) (or (6,))
        """
        array = np.asarray(cells)
        single = array.ndim == 1
        array = np.atleast_2d(array)
        if array.ndim != 2 or array.shape[1] != 3 or not np.issubdtype(array.dtype, np.integer):
            raise ValueError(f"cells must be an integer array of shape (M, 3), got {array.shape}")
        limits = np.array(self.shape)
        if np.any(array < 0) or np.any(array >= limits):
            bad = array[np.any((array < 0) | (array >= limits), axis=1)][0]
            raise ValueError(f"cells must lie in the grid of shape {self.shape}, got {tuple(bad)}")
        i, j, k = array[:, 0], array[:, 1], array[:, 2]
        out = np.stack([
            self.rho_edges[i], self.rho_edges[i + 1],
            self.theta_edges[j], self.theta_edges[j + 1],
            self.phi_edges[k], self.phi_edges[k + 1],
        ], axis=1)
        return out[0] if single else out

    def cell_centers(self, cells):
        """Cartesian centre (mid-rho, mid-theta, mid-phi) of each cell, shape (M, 3)."""
        bounds = np.atleast_2d(self.cell_bounds(cells))
        sph = np.stack([
            0.5 * (bounds[:, 0] + bounds[:, 1]),
            0.5 * (bounds[:, 2] + bounds[:, 3]),
            0.5 * (bounds[:, 4] + bounds[:, 5]),
        ], axis=1)
        centers = spherical_to_cartesian(sph)
        return centers[0] if np.asarray(cells).ndim == 1 else centers


def cartesian_to_spherical(points):
    """(M, 3) Cartesian to (M, 3) ``(rho, theta, phi)``.

    ``theta`` lies in (-pi, pi] and ``phi`` in [-pi/2, pi/2].
    """
    array, single = validate.points("points", points)
    # Rows whose squares would overflow or underflow are scaled by a power of two
    # first (exactly), as the kernels' row norms are: [1e-200] * 3 is at 35.26 deg.
    largest = np.max(np.abs(array), axis=1)
    _, exponent = np.frexp(np.where((largest > 1e150) | (largest < 1e-150), largest, 1.0))
    x, y, z = (np.ldexp(array[:, axis], -exponent) for axis in range(3))
    out = np.stack([
        np.ldexp(np.sqrt(x * x + y * y + z * z), exponent),
        np.arctan2(x + 0.0, z + 0.0),
        np.arctan2(y + 0.0, np.sqrt(x * x + z * z)),
    ], axis=1)
    return out[0] if single else out


def spherical_to_cartesian(spherical):
    """(M, 3) ``(rho, theta, phi)`` -> (M, 3) Cartesian (x, y, z) in this package's frame."""
    array, single = validate.points("spherical", spherical)
    rho, theta, phi = array[:, 0], array[:, 1], array[:, 2]
    out = np.stack([
        rho * np.cos(phi) * np.sin(theta),
        rho * np.sin(phi),
        rho * np.cos(phi) * np.cos(theta),
    ], axis=1)
    return out[0] if single else out


# A ROS body frame (x forward, y left, z up) maps to this package's frame
# (z forward, y up, x = y cross z towards theta = +90 deg) by a fixed rotation; applied only
# when asked, never silently.
ROS_TO_GRID = np.array([[0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [1.0, 0.0, 0.0]])


def from_ros(vectors):
    """Map (M, 3) points or directions from a ROS frame (x fwd, y left, z up) to the grid frame.

    ROS forward (+x) becomes +z (theta = 0), ROS up (+z) becomes +y (phi = pi/2),
    ROS left (+y) becomes +x (theta = +pi/2): a proper rotation (determinant +1), so
    handedness is kept.
    """
    array, single = validate.points("vectors", vectors)
    out = array @ ROS_TO_GRID.T
    return out[0] if single else out
