"""Tracing rays: ``trace`` and ``trace_many``, and the dispatch to each method.

Inputs are checked once (``_validate``); batches go to the kernels through
the memory strategy of ``_batching``; results are ``Trace`` and ``Traces``.
"""

import time

import numpy as np

from . import _batching as batching
from . import _validate as validate
from ._jit import interrupts_after
from .kernels.baselines import algorithm1 as _bisect
from .kernels.baselines import thibaudeau as _thibaudeau
from .traces import TraceBuffers

METHODS = ("exact", "bisect", "thibaudeau")


PAPER_DEFAULT_T = 1.5531  # metres: the step the paper tuned for Algorithm 1 (section 3.2)


@interrupts_after
def trace_many(grid, origins, directions=None, method="exact", parallel=True,
               default_t=PAPER_DEFAULT_T, max_iter=None, t_max=None, out=None, device="cpu"):
    """Trace many rays through ``grid``.

    Parameters
    ----------
    grid : Grid
    origins : array_like, shape (m, 3) or (3,), or (m, 6) with ``directions=None``
        Ray origins; or one array of origin + direction per row (as Open3D does).
        One origin, shape (3,) or (1, 3), is every ray's (an eye or a sensor).
    directions : array_like, shape (m, 3) or (3,), optional
        Ray directions, any non-zero length; they are normalised, so every
        ``t`` returned is a distance from the origin. One direction is
        every ray's (parallel rays from many origins).
    method : {"exact", "bisect", "thibaudeau"}
        ``"exact"`` (default): boundary stepping -- every cell, exact entry and
        exit distances. ``"bisect"``: the paper's Algorithm 1, a baseline that
        may skip cells and stops at the first exit; its distances are sample
        positions, not boundaries. ``"thibaudeau"``: all crossings with all
        boundaries, sorted and classified -- exact but O(n log n).
    parallel : bool
        Trace rays on all Numba threads (``prange``). The output is identical
        to the serial run. For ``"exact"`` every ray is traced once: serially
        by appending (a batch under 2,048 rays, or one thread); on two
        threads or more in small chunks taken in order,
        each traced into a scratch buffer of its thread's and copied to its
        place by that thread as soon as the chunks before it are counted.
        The baselines use a count pass and a fill pass.
    default_t : float
        ``"bisect"`` only: the first step of every search, in length units
        (paper: 1.5531 m).
    max_iter : int, optional
        ``"bisect"`` only: samples allowed per ray, so a ray grazing a boundary
        cannot loop forever. Default ``64 * (2 n_rho + n_theta + 2 n_phi + 4)``.
    t_max : float or array_like, shape (m,), optional
        ``"exact"`` only: trace each ray up to this distance (e.g. a sensor
        ray up to its hit point); the last segment ends there. Default: to the
        end of the region.
    out : TraceBuffers, optional
        ``"exact"`` only: write into these arrays, kept from an earlier call,
        instead of fresh ones (no allocation, no first touch of new pages).
        The result is then views of ``out``, valid until its next use.
    device : {"cpu", "cuda"}
        ``"cuda"``: ``"exact"`` only, on an NVIDIA GPU through numba-cuda
        (``pip install "logsph_trace[cuda]"``), the same traversal source as
        the CPU's. The inputs are numpy arrays, copied to the GPU, or GPU
        arrays (any CUDA Array Interface object: CuPy, PyTorch, numba-cuda),
        read in place when float64 and converted on the device otherwise,
        and checked there as numpy inputs are on the host. The result's
        arrays stay on the GPU (see :class:`Traces`). ``parallel`` does not
        apply; ``out`` is not supported.

    Returns
    -------
    Traces
        CSR segments: ``traces[r]`` is the :class:`Trace` of ray ``r``.

    Raises
    ------
    ValueError
        Wrong shapes, NaN or infinite values, zero directions, unknown method
        or device, bad ``default_t``, ``max_iter`` or ``t_max``, ``out`` with
        another method or with ``device="cuda"``, ``out`` whose arrays were
        changed in place (their shape, dtype or flags), GPU arrays without
        ``device="cuda"``, or ``grid`` not a :class:`Grid` -- before any
        traversal runs.
    TypeError
        ``out`` not a :class:`TraceBuffers`.
    RuntimeError
        ``device="cuda"`` without a usable GPU or numba-cuda.
    """
    start = time.perf_counter()
    validate.grid(grid)
    validate.choice("method", method, METHODS)
    validate.device(device)
    if device == "cuda":
        if method != "exact":
            raise ValueError(f"device='cuda' supports method='exact' only, got {method!r}")
        if out is not None:
            raise ValueError("out is not supported with device='cuda'")
    if method == "bisect":
        default_t, max_iter = validate.bisect_options(grid, default_t, max_iter)
    for name, value in (("t_max", t_max), ("out", out)):
        if value is not None and method != "exact":
            raise ValueError(f"{name} is supported by method='exact' only, got method={method!r}")
    if out is not None:
        if not isinstance(out, TraceBuffers):
            raise TypeError(f"out must be a TraceBuffers, got {type(out).__name__}")
        out.check()
    validate.host_only(device, origins=origins, directions=directions, t_max=t_max)
    if device == "cuda" and any(validate.on_gpu(v) for v in (origins, directions, t_max)):
        return cuda_backend().trace_gpu_inputs(grid, origins, directions, t_max)
    origins, directions = validate.rays(origins, directions, validate.reach(grid))
    parallel = bool(parallel)
    if method == "exact":
        t_max = validate.distances(t_max, origins.shape[0])
        batching.lap("check", start)
        if device == "cuda":
            return cuda_backend().trace_many(grid, origins, directions, t_max)
        return batching.run_exact(grid, origins, directions, t_max, parallel, out)
    if method == "bisect":
        args = (grid.kernel_args(), default_t, max_iter)
        rows = _bisect.bisect_rows
    else:
        args = (grid.kernel_args(),)
        rows = _thibaudeau.thibaudeau_rows
    return batching.run_csr(rows.pick(parallel), origins, directions, args)


def cuda_backend():
    """Import the CUDA backend on first use; raise one clear error without CUDA."""
    try:
        from . import _cuda
    except ImportError as error:
        raise RuntimeError(
            f"device='cuda' needs numba-cuda (pip install 'logsph_trace[cuda]'): {error}"
        ) from None
    _cuda.require()
    return _cuda


def trace(grid, origin, direction, method="exact", default_t=PAPER_DEFAULT_T, max_iter=None,
          t_max=None):
    """Trace one ray; see :func:`trace_many`.

    Parameters
    ----------
    grid : Grid
    origin, direction : array_like, shape (3,)
    method : {"exact", "bisect", "thibaudeau"}
    default_t, max_iter :
        ``"bisect"`` only, see :func:`trace_many`.
    t_max : float, optional
        ``"exact"`` only: trace up to this distance.

    Returns
    -------
    Trace
    """
    for name, value in (("origin", origin), ("direction", direction)):
        if np.shape(value) != (3,):
            raise ValueError(f"{name} must have shape (3,), got {np.shape(value)}")
    return trace_many(grid, origin, direction, method=method, parallel=False,
                      default_t=default_t, max_iter=max_iter, t_max=t_max)[0]
