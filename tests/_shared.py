"""Data made once per test session and shared by the pytest-xdist workers.

Seeded simulations that several test modules use (GalSim star fields, flat
pairs) are computed by the first worker that needs them, pickled into the
session's directory (``BFDRIFT_TEST_SHARED``, set by ``tests/conftest.py`` on
the controlling process and inherited by the workers) and read by the others:
the same arrays every worker would have drawn from the same seeds, made once.
Without the variable (a single process, or the module imported outside
pytest) the data are simply made.
"""

import os
import pickle
import time

__all__ = ["SHARED_ENV", "shared"]

#: Environment variable naming the session's directory of shared data.
SHARED_ENV = "BFDRIFT_TEST_SHARED"

#: Seconds a worker waits for another one making the same data before it makes
#: them itself (a worker that died leaves its lock behind).
WAIT_LIMIT = 900.0


def shared(name, make):
    """``make()``, computed once per test session across workers.

    Parameters
    ----------
    name : str
        File name (unique per data set: include every argument of ``make``).
    make : callable
        Makes the data (picklable) from fixed seeds.

    Returns
    -------
    object
        What ``make()`` returned, here or in another worker.
    """
    directory = os.environ.get(SHARED_ENV)
    if not directory or not os.path.isdir(directory):
        return make()
    path = os.path.join(directory, f"{name}.pkl")
    lock = path + ".lock"
    start = time.monotonic()
    while True:
        if os.path.exists(path):
            with open(path, "rb") as f:
                return pickle.load(f)
        try:
            fd = os.open(lock, os.O_CREAT | os.O_EXCL | os.O_WRONLY)
        except FileExistsError:  # another worker is making them
            if time.monotonic() - start > WAIT_LIMIT:
                return make()
            time.sleep(0.2)
            continue
        os.close(fd)
        try:
            out = make()
            tmp = f"{path}.{os.getpid()}.tmp"
            with open(tmp, "wb") as f:
                pickle.dump(out, f, protocol=pickle.HIGHEST_PROTOCOL)
            os.replace(tmp, path)  # readers see the whole file or none
        finally:
            if not os.path.exists(path):  # make() failed: let another worker try
                os.remove(lock)
        return out
