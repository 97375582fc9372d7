"""Export to GalSim sensor files, checked by GalSim itself (independent reader)."""

import galsim
import numpy as np
import pytest
from numpy.testing import assert_allclose

from lsst_bfdrift.physics.sensor import SensorParameters
from lsst_bfdrift.templates.galsim_export import export_galsim_sensor
from lsst_bfdrift.templates.galsim_io import import_galsim_sensor, read_galsim_sensor
from lsst_bfdrift.templates.template import TemplateSettings, build_template


def galsim_areas(name, charge, half, n=31):
    """GalSim's pixel areas of a stamp holding ``charge`` in one pixel."""
    img = galsim.ImageD(n, n, scale=0.2)
    img.setCenter(0, 0)
    img[0, 0] = charge
    a = galsim.SiliconSensor(name, diffusion_factor=0.0, qdist=half).calculate_pixel_areas(img)
    c = n // 2
    return a.array[c - half:c + half + 1, c - half:c + half + 1]


@pytest.fixture(scope="module")
def tan_template():
    """A template sampled at GalSim's own (tan) fractions: nothing to interpolate."""
    return build_template(SensorParameters(), TemplateSettings(size=9, edge_samples=6, tol=1e-5,
                                                               spacing="tan", workers=2))


def test_round_trip_and_galsim_areas(tan_template, tmp_path):
    """The exported files read back to the template's displacements, and
    galsim.SiliconSensor draws from them the template's own pixel areas."""
    t = tan_template
    cfg, dat = export_galsim_sensor(t, tmp_path / "sensor")
    back = read_galsim_sensor(str(tmp_path / "sensor"))
    assert_allclose(back.fractions, t.fractions, atol=1e-14)
    for name in ("corner_d", "vedge_d", "hedge_d"):
        assert_allclose(getattr(back, name), getattr(t, name), rtol=0, atol=1e-9)
    ga = galsim_areas(str(tmp_path / "sensor"), t.charge, t.center)
    assert_allclose(ga, t.moments().area, rtol=0, atol=1e-8)
    # GalSim's linear response: a half charge gives the template's areas at half charge
    assert_allclose(galsim_areas(str(tmp_path / "sensor"), t.charge / 2, t.center),
                    t.moments(charge=t.charge / 2).area, rtol=0, atol=1e-8)
    with open(cfg) as fh:
        text = fh.read()
    assert "NumVertices = 6" in text and f"CollectedCharge_0_0 = {t.charge}" in text


def test_galsim_sensor_survives_import_and_export(tmp_path):
    """GalSim's ITL file imported (per-pixel table kept) and exported again:
    GalSim draws the same areas from the copy as from its own file."""
    tpl = import_galsim_sensor("lsst_itl_50_8", match="none")
    export_galsim_sensor(tpl, tmp_path / "itl_copy")
    assert_allclose(galsim_areas(str(tmp_path / "itl_copy"), tpl.charge, 4),
                    galsim_areas("lsst_itl_50_8", tpl.charge, 4), rtol=0, atol=1e-7)


def test_resampled_edges_keep_the_areas(tmp_path):
    """Uniform samples interpolated to GalSim's tan fractions: areas kept to
    the interpolation error (1e-5 of a pixel at 1e4 e, 4 samples per edge)."""
    t = build_template(SensorParameters(), TemplateSettings(size=7, edge_samples=4, tol=1e-5,
                                                            workers=2))
    export_galsim_sensor(t, tmp_path / "u", num_vertices=8)
    ga = galsim_areas(str(tmp_path / "u"), t.charge, t.center)
    a = t.moments().area
    assert np.abs(ga - a).max() < 0.01 * np.abs(a - 1).max()


def test_refusals(tan_template, tmp_path):
    prefix = tmp_path / "s"
    export_galsim_sensor(tan_template, prefix)
    before = (tmp_path / "s.dat").read_bytes()
    with pytest.raises(FileExistsError, match=r"s\.cfg exists"):
        export_galsim_sensor(tan_template, prefix)
    assert (tmp_path / "s.dat").read_bytes() == before
    export_galsim_sensor(tan_template, prefix, overwrite=True)
    with pytest.raises(TypeError, match="DistortionTemplate"):
        export_galsim_sensor("template.fits", tmp_path / "x")
    with pytest.raises(ValueError, match="num_vertices"):
        export_galsim_sensor(tan_template, tmp_path / "y", num_vertices=0)
