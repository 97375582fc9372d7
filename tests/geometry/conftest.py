"""Fixtures and fields shared by the geometry tests."""

import numpy as np
import pytest


@pytest.fixture(scope="module")
def default_template():
    from lsst_bfdrift.templates.template import load_default_template
    return load_default_template()


def star_field(n, peak_flux, rng, *, sky=1000.0, faint=((0.25, 0.75, 20, 1.2),
                                                       (0.75, 0.25, 5, 2.0))):
    """Poisson sky, one star of ``peak_flux`` e (sigma 1.5 px) at the centre and
    fainter ones: ``faint`` rows are (x / n, y / n, peak_flux divisor, sigma px)."""
    q = rng.poisson(sky, (n, n)).astype(float)
    yy, xx = np.mgrid[0:n, 0:n]
    stars = [(n / 2 + 0.3, n / 2 - 0.2, peak_flux, 1.5)]
    stars += [(fx * n, fy * n + (0.5 if k else 0.0), peak_flux / d, s)
              for k, (fx, fy, d, s) in enumerate(faint)]
    for (x, y, f, s) in stars:
        q += f * np.exp(-0.5 * ((xx - x)**2 + (yy - y)**2) / s**2) / (2 * np.pi * s**2)
    return q
