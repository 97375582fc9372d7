"""File helpers shared by the package: atomic output, the overwrite rule, FITS input,
text tables of numbers."""

import contextlib
import json
import os
import re
import socket
import tempfile
import time

import numpy as np
from astropy.io import fits

from lsst_bfdrift.utils.errors import (InputFileError, InputNotFoundError,
                                       OutputExistsError)

__all__ = ["TMP_PREFIX", "STALE_AGE", "is_temporary", "temporary_owner", "is_stale_temporary",
           "remove_stale_temporaries", "data_files", "check_output", "atomic_output",
           "write_text", "write_json", "FITS_MAGIC", "not_fits_reason", "astropy_message",
           "open_fits", "hdu_pixels", "data_path", "read_text_rows"]

#: Prefix of the temporary files of :func:`atomic_output`; directory readers
#: ignore files whose name starts with it (:func:`is_temporary`).
TMP_PREFIX = ".tmp-"


#: Age (s) after which a temporary file whose owner cannot be checked (written on
#: another host, or named without a PID) is taken as a leftover.
STALE_AGE = 3600.0

# .tmp-<pid>-<host>-<8 random characters of mkstemp><suffix>
_TMP_NAME = re.compile(r"^\.tmp-(?P<pid>\d+)-(?P<host>[A-Za-z0-9.]*)-[a-z0-9_]{8}")
# before the PID was in the name: .tmp-<8 random characters><suffix>
_OLD_TMP_NAME = re.compile(r"^\.tmp-[a-z0-9_]{8}\.[^.]*$")


def _host_tag():
    """This machine's name as it appears in temporary names (letters, digits, dots)."""
    return re.sub(r"[^A-Za-z0-9.]", "", socket.gethostname())[:40]


def is_temporary(path):
    """Whether ``path`` names a temporary file of :func:`atomic_output`.

    Parameters
    ----------
    path : str or path-like

    Returns
    -------
    bool
        True when the file name starts with :data:`TMP_PREFIX` (e.g. a
        partial file left by a killed run).
    """
    return os.path.basename(os.fspath(path)).startswith(TMP_PREFIX)


def temporary_owner(path):
    """The process that wrote the temporary file ``path``, from its name.

    :func:`atomic_output` names its temporary files
    ``.tmp-<pid>-<host>-<random><suffix>``.

    Parameters
    ----------
    path : str or path-like

    Returns
    -------
    (int, str) or None
        The PID and host name (letters, digits and dots only), or None when
        the name does not follow that scheme.
    """
    m = _TMP_NAME.match(os.path.basename(os.fspath(path)))
    return None if m is None else (int(m["pid"]), m["host"])


def _pid_running(pid):
    """Whether a process ``pid`` exists on this machine."""
    if pid <= 0:
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # another user's process
        return True
    except OSError:
        return False
    return True


def is_stale_temporary(path, *, max_age=STALE_AGE, now=None):
    """Whether ``path`` is a temporary file of :func:`atomic_output` left by a dead run.

    A file named by this machine's process ``pid`` (:func:`temporary_owner`)
    is stale exactly when that process no longer runs, whatever its age: a
    running writer's file is never taken. A file whose owner cannot be
    checked (written on another host sharing the directory, or named
    ``.tmp-<random><suffix>`` by an earlier version, without a PID) is stale
    when it was last modified more than ``max_age`` seconds ago. Other files,
    ``.tmp-*`` files of other programs included, are never stale.

    Parameters
    ----------
    path : str or path-like
    max_age : float, optional
        Seconds (default one hour).
    now : float, optional
        The current time (``time.time()``; for tests).

    Returns
    -------
    bool
    """
    path = os.fspath(path)
    if not is_temporary(path) or not os.path.isfile(path) or os.path.islink(path):
        return False
    owner = temporary_owner(path)
    if owner is not None and owner[1] == _host_tag():
        return not _pid_running(owner[0])
    if owner is None and not _OLD_TMP_NAME.match(os.path.basename(path)):
        return False  # not a name atomic_output gives
    try:
        age = (time.time() if now is None else now) - os.path.getmtime(path)
    except OSError:
        return False
    return age > max_age


def remove_stale_temporaries(directory, *, max_age=STALE_AGE):
    """Remove the temporary files of killed runs from ``directory``.

    Only files named by :func:`atomic_output` (``.tmp-*``) that
    :func:`is_stale_temporary` finds stale are removed; sub-directories are
    not visited. A directory that does not exist holds nothing to remove.

    Parameters
    ----------
    directory : str or path-like
    max_age : float, optional
        See :func:`is_stale_temporary`.

    Returns
    -------
    list of str
        The files removed (full paths, sorted).
    """
    directory = os.fspath(directory)
    try:
        names = sorted(os.listdir(directory))
    except (FileNotFoundError, NotADirectoryError):
        return []
    removed = []
    for name in names:
        path = os.path.join(directory, name)
        if is_stale_temporary(path, max_age=max_age):
            try:
                os.remove(path)
            except FileNotFoundError:  # another run removed it first
                continue
            removed.append(path)
    return removed


def data_files(directory, suffixes):
    """Data files of ``directory`` with one of ``suffixes``, sorted by name.

    Temporary files of :func:`atomic_output` (``.tmp-*``) are never data
    and are left out, as are sub-directories.

    Parameters
    ----------
    directory : str or path-like
    suffixes : tuple of str
        Accepted endings, compared case-insensitively (e.g. ``(".fits",)``).

    Returns
    -------
    list of str
        Full paths.
    """
    directory = os.fspath(directory)
    names = sorted(f for f in os.listdir(directory)
                   if f.lower().endswith(tuple(suffixes)) and not is_temporary(f))
    return [os.path.join(directory, f) for f in names
            if os.path.isfile(os.path.join(directory, f))]


def _same_file(a, b):
    if os.path.realpath(a) == os.path.realpath(b):
        return True
    try:
        return os.path.samefile(a, b)  # hard links
    except OSError:
        return False


def check_output(path, inputs=(), *, overwrite=False, what="output", hint=None):
    """The one overwrite rule of every output of the package.

    An output may never be one of the inputs (the same file once symbolic
    links and relative paths are resolved), even with ``overwrite``; an
    existing file is replaced only with ``overwrite``.

    Parameters
    ----------
    path : str or path-like
        The output.
    inputs : iterable of str or path-like, optional
        The inputs of the command (``None`` entries are skipped).
    overwrite : bool, optional
        Whether an existing file that is not an input may be replaced.
    what : str, optional
        How the output is named in messages (e.g. ``"--out"``).
    hint : str, optional
        How to allow the replacement, in the message; default ``--overwrite``
        when ``what`` is an option (starts with ``--``), else
        ``overwrite=True``.

    Raises
    ------
    OutputExistsError
        ``path`` is one of the inputs, is a directory, or exists and
        ``overwrite`` is False.
    """
    path = os.fspath(path)
    for src in inputs:
        if src is not None and _same_file(path, os.fspath(src)):
            raise OutputExistsError(f"refusing to write {what} {path}: it is one of the inputs "
                                    f"({os.fspath(src)}); give another output file")
    if os.path.isdir(path):
        raise OutputExistsError(f"{what} {path} is a directory; give a file name")
    if os.path.lexists(path) and not overwrite:
        if hint is None:
            hint = "--overwrite" if what.startswith("--") else "overwrite=True"
        raise OutputExistsError(f"{what} {path} exists (use {hint} to replace it)")


def _name_the_output(exc, tmp, path):
    """``exc`` (an OSError about the temporary file) re-worded to name ``path``."""
    name = exc.filename if isinstance(exc.filename, str) else None
    if (name and is_temporary(name)) or (tmp and tmp in str(exc)):
        reason = exc.strerror or str(exc).replace(tmp or name, path)
        return OSError(exc.errno, f"cannot write {path}: {reason}") if exc.errno else \
            OSError(f"cannot write {path}: {reason}")
    return None


@contextlib.contextmanager
def atomic_output(path, *, overwrite=True, inputs=()):
    """Yield a temporary path next to ``path``; rename it to ``path`` on success.

    The file appears complete or not at all. The temporary file (named
    ``.tmp-<pid>-<host>-*``, which directory readers ignore) is removed on any
    exception, KeyboardInterrupt included, and ``path`` is then untouched
    (``bfdrift`` turns SIGTERM into such an exception); one left by a killed
    process is removed by :func:`remove_stale_temporaries`. Permissions
    follow the umask (like a plain ``open``), not mkstemp's 0600.

    Parameters
    ----------
    path : str or path-like
        The output file.
    overwrite : bool, optional
        Replace an existing file (:func:`check_output`).
    inputs : iterable, optional
        Files the output may not replace (:func:`check_output`).

    Yields
    ------
    tmp : str
        The temporary file to write.
    """
    path = os.fspath(path)
    check_output(path, inputs, overwrite=overwrite)
    directory = os.path.dirname(os.path.abspath(path))
    tmp = None
    try:
        os.makedirs(directory, exist_ok=True)
        suffix = os.path.splitext(path)[1] or ".tmp"
        fd, tmp = tempfile.mkstemp(prefix=f"{TMP_PREFIX}{os.getpid()}-{_host_tag()}-",
                                   suffix=suffix, dir=directory)
        os.close(fd)
        yield tmp
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)
        os.replace(tmp, path)
    except OSError as exc:
        renamed = _name_the_output(exc, tmp, path)
        if renamed is None:
            raise
        raise renamed from exc
    finally:
        if tmp is not None and os.path.lexists(tmp):
            os.remove(tmp)


def write_text(path, text):
    """Write ``text`` to ``path`` atomically (:func:`atomic_output`)."""
    with atomic_output(path) as tmp, open(tmp, "w") as fh:
        fh.write(text)


def write_json(path, obj, **dump_kwargs):
    """Write ``obj`` as JSON to ``path`` atomically; ``dump_kwargs`` go to
    :func:`json.dump` (e.g. ``indent=2, default=float``)."""
    with atomic_output(path) as tmp, open(tmp, "w") as fh:
        json.dump(obj, fh, **dump_kwargs)


#: The first bytes of a FITS file (the mandatory first card), and of the compressed
#: files astropy opens (gzip, bzip2, zip).
FITS_MAGIC = b"SIMPLE  ="
_COMPRESSED_MAGIC = (b"\x1f\x8b", b"BZh", b"PK\x03\x04")

#: What astropy appends to its message for a file without the SIMPLE card: an
#: option of ``fits.open``, not of any bfdrift command.
_ASTROPY_HINT = re.compile(r"\s*If this is really a FITS file, try with "
                           r"ignore_missing_simple=True\.?")


def not_fits_reason(path):
    """Why the file at ``path`` is not a FITS file, from its first bytes; None if it may be one.

    A FITS file starts with the card ``SIMPLE  =``; gzip, bzip2 and zip files
    (which astropy decompresses) are left to the reader.

    Parameters
    ----------
    path : str or path-like
        An existing file.

    Returns
    -------
    reason : str or None
        E.g. ``"not a FITS file: it is a text file starting with 'mean var' (a
        FITS file starts with the card 'SIMPLE  =')"``; None when the file
        starts like a FITS (or a compressed) file.

    Raises
    ------
    OSError
        The file cannot be read.
    """
    with open(os.fspath(path), "rb") as fh:
        head = fh.read(2880)
    if head.startswith(FITS_MAGIC) or head.startswith(_COMPRESSED_MAGIC):
        return None
    expected = f"a FITS file starts with the card '{FITS_MAGIC.decode()}'"
    if not head:
        return f"not a FITS file: the file is empty ({expected})"
    try:
        text = head.decode("utf-8")
    except UnicodeDecodeError:
        text = None
    if text is not None and all(c.isprintable() or c in "\t\r\n" for c in text):
        first = next((ln.strip() for ln in text.splitlines() if ln.strip()), "")
        first = first if len(first) <= 40 else first[:37] + "..."
        return f"not a FITS file: it is a text file starting with {first!r} ({expected})"
    return f"not a FITS file: it starts with the bytes {head[:8]!r} ({expected})"


@contextlib.contextmanager
def open_fits(path):
    """``astropy.io.fits.open`` (no memmap) with the package's errors.

    Raises
    ------
    InputNotFoundError
        ``path`` does not exist.
    InputFileError
        ``path`` is not a FITS file (:func:`not_fits_reason`: empty, text,
        another format) or not a readable one (corrupt); the message names
        the file and says which.
    """
    path = os.fspath(path)
    if not os.path.exists(path):
        raise InputNotFoundError(f"{path}: no such file; accepted: a FITS file", path)
    if os.path.isdir(path):
        raise InputFileError(f"{path}: is a directory; accepted: a FITS file", path)
    reason = not_fits_reason(path)
    if reason is not None:
        raise InputFileError(f"{path}: {reason}; accepted: a FITS file", path)
    try:
        hdul = fits.open(path, memmap=False)
    except (OSError, ValueError, TypeError, IndexError) as exc:
        raise InputFileError(f"{path}: not a readable FITS file ({astropy_message(exc)}); "
                             "accepted: a FITS file", path) from exc
    with hdul:
        yield hdul


def astropy_message(exc):
    """The text of an astropy error about a file, without its advice to call
    ``fits.open(..., ignore_missing_simple=True)`` (no option of the package).

    Parameters
    ----------
    exc : Exception

    Returns
    -------
    str
    """
    return _ASTROPY_HINT.sub("", str(exc)).strip()


def hdu_pixels(hdu, path, dtype=np.float64):
    """Pixels of one image HDU as a new array, a truncated file named as such.

    Parameters
    ----------
    hdu : astropy.io.fits HDU
    path : str
        The file (for the message).
    dtype : numpy dtype, optional

    Returns
    -------
    ndarray

    Raises
    ------
    InputFileError
        The file ends before the pixels its header announces ("cannot
        reshape array" in astropy) or they cannot be decoded.
    """
    try:
        return np.array(hdu.data, dtype=dtype)
    except (ValueError, TypeError, OSError, IndexError) as exc:
        hdr = hdu.header
        shape = tuple(hdr.get(f"NAXIS{k}") for k in range(int(hdr.get("NAXIS", 0) or 0), 0, -1))
        raise InputFileError(f"{path}: truncated or corrupt FITS file: HDU {hdu.name or 0!s} "
                             f"announces an image of shape {shape} but its pixels cannot be read "
                             f"({exc}); re-copy or re-write the file", path) from exc


def _number(field):
    try:
        return float(field)
    except ValueError:
        return None


def read_text_rows(path, *, accepted, limit=None):
    """The rows of numbers of a text table, each with its line number.

    Blank lines and lines starting with ``#`` are skipped; fields are
    separated by white space or commas. Lines before the first row of
    numbers none of whose fields is a number are a header and skipped. Any
    other line with a field that is not a number is a malformed row: an
    error naming the line and the field, not a header (a header has no
    numbers).

    Parameters
    ----------
    path : str or path-like
    accepted : str
        What the table may hold, for the messages (e.g. ``'rows of i j value
        sigma'``).
    limit : int, optional
        Stop after this many rows of numbers (e.g. 1 to find the width).

    Returns
    -------
    list of (int, list of float)
        Line number (from 1) and values of each row, in file order.

    Raises
    ------
    InputFileError
        A malformed row, or a file that is not UTF-8 text.
    """
    path = os.fspath(path)
    rows = []
    try:
        with open(path, encoding="utf-8") as fh:
            for n, line in enumerate(fh, 1):
                s = line.strip()
                if not s or s.startswith("#"):
                    continue
                parts = s.replace(",", " ").split()
                vals = [_number(p) for p in parts]
                bad = [k for k, v in enumerate(vals) if v is None]
                if not bad:
                    rows.append((n, vals))
                    if limit is not None and len(rows) >= limit:
                        break
                    continue
                if not rows and len(bad) == len(parts):
                    continue  # a header line: no number in it
                k = bad[0]
                where = ("a line of text among the rows of numbers" if rows else
                         f"{len(parts) - len(bad)} of its {len(parts)} fields are numbers, so it "
                         "is a malformed row, not a header")
                raise InputFileError(f"{path}:{n}: field {k + 1} ({parts[k]!r}) of the row "
                                     f"{s!r} is not a number ({where}); accepted: {accepted}",
                                     path)
    except UnicodeDecodeError:
        raise InputFileError(f"{path}: not a text file (bytes that are not UTF-8); accepted: "
                             f"{accepted}", path) from None
    return rows


def data_path(name):
    """Path of a file bundled in the package's ``data`` directory."""
    return os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "data", name)
