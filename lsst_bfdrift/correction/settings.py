"""The recommended settings of the drift correction, in one place.

:func:`~lsst_bfdrift.correction.solvers.correct_image`, the Task's config
(:class:`~lsst_bfdrift.correction.task.BrighterFatterDriftConfig`) and the
``bfdrift`` command take their defaults from :data:`RECOMMENDED`; change a
default here and all three follow. The figures behind each choice are in
the performance section of the validation page (``docs/benchmarks.rst``).
"""

import dataclasses

import numpy as np

__all__ = ["SolverSettings", "RECOMMENDED", "REFERENCE"]


@dataclasses.dataclass(frozen=True)
class SolverSettings:
    """Settings of the drift solver.

    Attributes
    ----------
    order : int
        Terms of the time-history series (2 = half the final shift).
    density : {'fv4', 'cubic4', 'mean2'}
        Flux density at the pixel edges: four-point finite-volume
        reconstruction from the pixel averages (``fv4``), four-point
        interpolation along the normal (``cubic4``) or the mean of the two
        pixels beside the edge (``mean2``).
    max_iter : int
        Largest number of fixed-point iterations.
    rtol : float
        Convergence, when ``noise_tol`` is None: max abs(I - R(F)) <= rtol *
        max abs(I).
    noise_tol : float or None
        Convergence: abs(I - R(F)) <= noise_tol * sqrt(I) in every pixel (a
        fraction of the Poisson noise, e).
    start : {'series', 'image'}
        First guess: the third-order inverse series (three operator calls,
        iterated only where an a-priori bound requires), or the recorded image.
    fft_precision : {'float32', 'float64'}
        Precision of the FFT convolutions (float32: half the time and memory).
    strip : int or None
        Rows per block of the solvers (bounded memory); None: the whole image.
    sparse : bool
        With ``start='series'``: the second- and third-order terms only in
        windows around the sources that need them (bounded error, dense
        fallback).
    workers : int
        FFT threads.
    """

    order: int = 3
    density: str = "fv4"
    max_iter: int = 10
    rtol: float = 1e-7
    noise_tol: float | None = 0.05
    start: str = "series"
    fft_precision: str = "float32"
    strip: int | None = 512
    sparse: bool = True
    workers: int = 2

    @property
    def dtype(self):
        """The numpy dtype of ``fft_precision``."""
        return np.float32 if self.fft_precision == "float32" else np.float64

    def solver_kwargs(self, **overrides):
        """Keyword arguments of :func:`~lsst_bfdrift.correction.solvers.correct_image`
        (``dtype`` for ``fft_precision``), with ``overrides`` applied."""
        kw = dataclasses.asdict(self)
        kw["dtype"] = self.dtype
        del kw["fft_precision"]
        kw.update(overrides)
        return kw


#: The settings every entry point uses unless told otherwise.
RECOMMENDED = SolverSettings()

#: Settings of a reference solution: double precision, the whole image at
#: once, the dense series iterated from the recorded image to ``rtol``
#: (tests and the diagnosis' forward models, where speed does not matter).
REFERENCE = SolverSettings(density="cubic4", noise_tol=None, start="image",
                           fft_precision="float64", strip=None, sparse=False, workers=1)
