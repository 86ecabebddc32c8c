"""Files that survive failures: every write goes to a temporary file first.

:func:`atomic_write` yields a binary stream on a temporary file in the target's
own directory (so the final rename never crosses file systems). Only when the
caller's block finishes is the file flushed, fsynced and moved over the target
with ``os.replace``, which is atomic on POSIX and Windows. On any failure --
a full disk, an exception, Ctrl-C -- the temporary file is removed and the old
target, if there was one, is left exactly as it was. A file replaced keeps its
permissions, and a symbolic link keeps pointing at the file it names, which
gets the new contents.
"""

import contextlib
import errno
import os
import tempfile
import zipfile
from pathlib import Path

import numpy as np


def _default_mode():
    """Permissions a newly created file gets under the current umask."""
    mask = os.umask(0)
    os.umask(mask)
    return 0o666 & ~mask


def _mode_of(path):
    """Return the permissions of ``path``, or those a new file gets under the umask."""
    try:
        return os.stat(path).st_mode & 0o7777
    except FileNotFoundError:
        return _default_mode()


@contextlib.contextmanager
def atomic_write(path):
    """Write ``path`` all or nothing: ``with atomic_write(path) as stream: ...``.

    An existing file keeps its permissions. A symbolic link is written
    through: its target gets the new contents (atomically, beside it) and
    the link stays a link.
    """
    path = Path(os.path.realpath(path))
    mode = _mode_of(path)
    try:
        descriptor, temporary = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.",
                                                 suffix=".part")
    except FileNotFoundError:  # name the target and its directory, not the temporary file
        raise FileNotFoundError(errno.ENOENT, f"no such directory: '{path.parent}'",
                                str(path)) from None
    try:
        os.fchmod(descriptor, mode)  # mkstemp makes it private (0600)
        with os.fdopen(descriptor, "wb") as stream:
            yield stream
            stream.flush()
            os.fsync(stream.fileno())
        os.replace(temporary, path)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(temporary)
        raise
    with contextlib.suppress(OSError):  # make the rename itself durable where it can be
        directory = os.open(path.parent, os.O_RDONLY)
        try:
            os.fsync(directory)
        finally:
            os.close(directory)


def npz_path(path):
    """Return the name ``numpy.savez`` would write: ``path`` with ``.npz`` added if missing."""
    path = Path(path)
    return path if path.suffix == ".npz" else path.with_name(path.name + ".npz")


def write_npz(stream, compress=False, **arrays):
    """Write ``arrays`` to ``stream`` as ``numpy.savez`` (``savez_compressed``) does.

    The archive is closed however the writing ends: numpy before 1.25 left
    it open on an exception (Ctrl-C), and its ``__del__``, run later against
    the closed file, printed a traceback after the command's one line.
    """
    compression = zipfile.ZIP_DEFLATED if compress else zipfile.ZIP_STORED
    with zipfile.ZipFile(stream, mode="w", compression=compression, allowZip64=True) as archive:
        for name, array in arrays.items():
            with archive.open(name + ".npy", mode="w", force_zip64=True) as member:
                np.lib.format.write_array(member, np.asanyarray(array), allow_pickle=False)


def write_text(path, text):
    """Write ``text`` (UTF-8) to ``path`` all or nothing."""
    with atomic_write(path) as stream:
        stream.write(text.encode("utf-8"))


def save_figure(figure, path, **options):
    """``figure.savefig(path, **options)``, all or nothing; the format is the suffix's."""
    path = Path(path)
    with atomic_write(path) as stream:
        figure.savefig(stream, format=path.suffix.lstrip(".") or None, **options)
