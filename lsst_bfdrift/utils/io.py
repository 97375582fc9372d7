"""File helpers shared by the package: atomic output, image input."""

import contextlib
import os
import tempfile

import numpy as np
from lsst_bfdrift.utils.errors import InputError, OutputExistsError

__all__ = ["atomic_output", "write_text", "write_json", "read_image", "data_path"]


@contextlib.contextmanager
def atomic_output(path, *, overwrite=True):
    """Yield a temporary path next to ``path``; rename it to ``path`` on success.

    The file appears complete or not at all; on error the temporary file is
    removed and ``path`` is untouched. Permissions follow the umask (like a
    plain ``open``), not mkstemp's 0600.
    """
    path = os.fspath(path)
    if os.path.exists(path) and not overwrite:
        raise OutputExistsError(f"{path} exists (use overwrite)")
    directory = os.path.dirname(os.path.abspath(path))
    os.makedirs(directory, exist_ok=True)
    suffix = os.path.splitext(path)[1] or ".tmp"
    fd, tmp = tempfile.mkstemp(prefix=".tmp-", suffix=suffix, dir=directory)
    os.close(fd)
    try:
        yield tmp
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.remove(tmp)


def write_text(path, text):
    """Write ``text`` to ``path`` atomically (:func:`atomic_output`)."""
    with atomic_output(path) as tmp, open(tmp, "w") as fh:
        fh.write(text)


def write_json(path, obj, **dump_kwargs):
    """Write ``obj`` as JSON to ``path`` atomically; ``dump_kwargs`` go to
    :func:`json.dump` (e.g. ``indent=2, default=float``)."""
    import json

    with atomic_output(path) as tmp, open(tmp, "w") as fh:
        json.dump(obj, fh, **dump_kwargs)


def read_image(path, *, hdu=None):
    """Image (float64 copy) and mask from a FITS file; NaN/inf are masked."""
    from astropy.io import fits

    with fits.open(path, memmap=False) as hdul:
        if hdu is None:
            hdu = next((k for k, h in enumerate(hdul) if getattr(h, "data", None) is not None
                        and h.data.ndim == 2), None)
            if hdu is None:
                raise InputError(f"{path}: no 2-d image HDU")
        data = np.array(hdul[hdu].data, dtype=np.float64)
        header = hdul[hdu].header.copy()
    return data, ~np.isfinite(data), header


def data_path(name):
    """Path of a file bundled in the package's ``data`` directory."""
    return os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "data", name)
