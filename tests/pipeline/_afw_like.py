"""A stand-in with the shape of an afw Exposure (afw is not installable from
the package registry): ``.image.array``, ``.mask.array`` with a plane
dictionary, ``.variance.array``, ``getMetadata()`` and ``clone()``."""

import copy

import numpy as np

__all__ = ["FakeExposure"]


class _Image:
    def __init__(self, array):
        self.array = array


class _Mask(_Image):
    def __init__(self, array, planes):
        super().__init__(array)
        self._planes = dict(planes)

    def getMaskPlaneDict(self):  # noqa: N802 (afw name)
        return dict(self._planes)

    def addMaskPlane(self, name):  # noqa: N802 (afw name)
        if name not in self._planes:
            self._planes[name] = max(self._planes.values(), default=-1) + 1
        return self._planes[name]

    def getPlaneBitMask(self, names):  # noqa: N802 (afw name)
        names = [names] if isinstance(names, str) else names
        return int(sum(1 << self._planes[n] for n in names))


class FakeExposure:
    def __init__(self, image, *, planes, variance=None, metadata=None):
        self.image = _Image(np.asarray(image, np.float32))
        self.mask = _Mask(np.zeros(self.image.array.shape, np.int32), planes)
        var = self.image.array.copy() if variance is None else variance
        self.variance = _Image(np.asarray(var, np.float32))
        self._metadata = dict(metadata or {"BUNIT": "electron"})

    def getMetadata(self):  # noqa: N802 (afw name)
        return self._metadata

    def clone(self):
        return copy.deepcopy(self)
