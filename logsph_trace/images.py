"""Depth and label images from files: ``.npy``, 16-bit PNG and PFM.

:func:`read_image` returns the array as stored; what a depth value means
(metres, millimetres) is the caller's ``depth_scale``. PNG needs Pillow
(``pip install "logsph_trace[images]"``); ``.npy`` and PFM need nothing.
"""

from pathlib import Path

import numpy as np

FORMATS = (".npy", ".png", ".pfm")


def read_image(path, what="image"):
    """Read a 2-D image from a ``.npy``, PNG or PFM file.

    Parameters
    ----------
    path : str or path-like
    what : str
        What the image is, for error messages ("depth", "labels").

    Returns
    -------
    numpy.ndarray, shape (rows, columns)
        ``.npy``: as saved. PNG: 8- or 16-bit greyscale as ``uint8`` or
        ``uint16`` (depth cameras write millimetres). PFM: ``float32``,
        top row first (the file stores the bottom row first).

    Raises
    ------
    ValueError
        An unknown extension, a file that is not a 2-D image of numbers.
    OSError
        The file cannot be read.
    ImportError
        A PNG without Pillow.
    """
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in FORMATS:
        raise ValueError(f"{what} must be a .npy, .png or .pfm file, got {path.name}")
    if not path.is_file():
        raise FileNotFoundError(f"no such {what} file: {path}")
    if suffix == ".npy":
        try:
            array = np.load(path, allow_pickle=False)
        except ValueError as error:  # pickled objects, a corrupt header
            raise ValueError(f"cannot read {path} as an array: {error}") from None
    elif suffix == ".pfm":
        array = _read_pfm(path)
    else:
        array = _read_png(path)
    if array.ndim != 2 or array.dtype.kind not in "fiu":
        raise ValueError(f"{path} must hold a 2-D image of numbers, got {array.dtype} of shape "
                         f"{array.shape}")
    return array


def _read_png(path):
    try:
        from PIL import Image
    except ImportError:
        raise ImportError("reading PNG images needs Pillow: pip install 'logsph_trace[images]'") \
            from None
    try:
        with Image.open(path) as image:
            if image.mode not in ("L", "I;16", "I;16B", "I", "F"):
                raise ValueError(f"{path} must be a greyscale image (8 or 16 bits), got mode "
                                 f"{image.mode}")
            return np.array(image)
    except OSError as error:  # Pillow's "cannot identify image file"
        raise ValueError(f"cannot read {path} as a PNG image: {error}") from None


def _read_pfm(path):
    """Read a greyscale Portable Float Map (``Pf``), as Middlebury ships disparities."""
    with open(path, "rb") as stream:
        header = [stream.readline() for _ in range(3)]
        data = stream.read()
    try:
        kind = header[0].strip()
        columns, rows = (int(field) for field in header[1].split())
        scale = float(header[2])
    except ValueError:
        raise ValueError(f"{path} is not a PFM file (bad header)") from None
    if kind == b"PF":
        raise ValueError(f"{path} is a colour PFM: depth and labels are greyscale (Pf)")
    if kind != b"Pf" or rows <= 0 or columns <= 0 or scale == 0:
        raise ValueError(f"{path} is not a greyscale PFM file (bad header)")
    dtype = np.dtype("<f4" if scale < 0 else ">f4")
    if len(data) < rows * columns * 4:
        raise ValueError(f"{path} is truncated: {len(data):,} bytes of pixels, "
                         f"{rows * columns * 4:,} expected")
    array = np.frombuffer(data, dtype=dtype, count=rows * columns).reshape(rows, columns)
    return np.ascontiguousarray(array[::-1]).astype(np.float32)
