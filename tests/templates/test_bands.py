"""Tests of lsst_bfdrift.templates.bands: per-band templates and multi-band files."""

import dataclasses

import numpy as np
import pytest
from astropy.io import fits
from numpy.testing import assert_allclose

from lsst_bfdrift.physics.depth import depth_distribution
from lsst_bfdrift.physics.sensor import SensorParameters
from lsst_bfdrift.templates.bands import (MultiBandTemplate, band_key, band_weights,
                                          build_band_templates, combine_templates,
                                          load_templates)
from lsst_bfdrift.templates.template import DistortionTemplate, TemplateSettings, build_template
from lsst_bfdrift.utils.errors import InputError, InputTypeError, TemplateFileError

ARRAYS = ("corner_d", "vedge_d", "hedge_d")


@pytest.fixture(scope="module")
def tiny():
    """Paper sensor, 3 x 3 window, 2 samples per edge, 1e-2 px: under a second per height."""
    params = SensorParameters.paper()
    settings = TemplateSettings(size=3, edge_samples=2, tol=1e-2, workers=1)
    nodes = np.array([params.z_collect, 60.0, params.thickness])
    return params, settings, nodes


@pytest.fixture(scope="module")
def bands_built(tiny):
    params, settings, nodes = tiny
    return build_band_templates(params, ("u", "r", "y", 700.0), settings=settings, nodes=nodes)


@pytest.fixture(scope="module")
def per_height(tiny):
    """Templates built directly at each node above the wells (the reference)."""
    params, settings, nodes = tiny
    return {k: build_template(params, dataclasses.replace(settings,
                                                          conversion_height=float(nodes[k])))
            for k in (1, 2)}


class TestBandTemplates:
    def test_band_template_is_weighted_sum_of_height_templates(self, tiny, bands_built,
                                                               per_height):
        """CORRECTNESS: each band's displacements equal the explicit sum w_k T(z_k).

        The weights are recomputed here by numpy quadrature of the band's
        exponential depth profile against the hat functions of the nodes; the
        templates at each height come from build_template directly; the
        collection height contributes no displacement.
        """
        params, _, nodes = tiny
        dep = np.concatenate([[0.0], np.geomspace(1e-7, params.thickness, 8001)])
        z = params.thickness - dep
        for key in ("u", "r", "y", "700nm"):
            d = depth_distribution(key if len(key) == 1 else 700.0, params.thickness)
            p = (d.coefficients[:, None] / d.absorption[:, None] *
                 np.exp(-dep[None, :] / d.absorption[:, None])).sum(axis=0)
            w = []
            for k in (1, 2):
                hat = np.interp(z, nodes, np.eye(3)[k])
                w.append(np.trapezoid(p * hat, dep))
            for name in ARRAYS:
                ref = sum(wk * getattr(per_height[k], name) for wk, k in zip(w, (1, 2)))
                assert_allclose(getattr(bands_built[key], name), ref, atol=1e-8, rtol=1e-5,
                                err_msg=f"{key} {name}")
            info = bands_built[key].meta["depth"]
            assert_allclose(info["mean_height"], d.mean_height)
            assert info["nodes"] == nodes.tolist()

    def test_u_band_is_the_entrance_window_template(self, bands_built, per_height):
        """CORRECTNESS (physics): u photons convert within nm of the window: its template."""
        for name in ARRAYS:
            assert_allclose(getattr(bands_built["u"], name), getattr(per_height[2], name),
                            atol=1e-6)

    def test_red_band_distorts_less(self, bands_built):
        """CORRECTNESS (physics): deeper conversions drift less: |A00 - 1| smaller in y than u."""
        s = bands_built.summary()
        assert 0 < 1 - s["y"]["A00"] < 1 - s["r"]["A00"] <= 1 - s["u"]["A00"]
        assert s["y"]["converted_fraction"] < 0.7

    def test_galsim_response_scales_base(self, tiny, per_height):
        """CORRECTNESS: 'galsim' response = base x E[tanh(z/12)] (direct quadrature here)."""
        params, settings, _ = tiny
        base = per_height[2]
        mb = build_band_templates(params, ("y",), settings=settings, depth_response="galsim",
                                  base=base)
        dep = np.concatenate([[0.0], np.geomspace(1e-7, params.thickness, 20001)])
        d = depth_distribution("y", params.thickness)
        factor = np.trapezoid(d.pdf(params.thickness - dep) *
                              np.tanh((params.thickness - dep) / 12.0), dep)
        assert_allclose(mb["y"].corner_d, factor * base.corner_d, rtol=1e-5, atol=1e-12)
        assert_allclose(mb["y"].meta["depth"]["factor"], factor, rtol=1e-5)

    def test_band_weights_sum_to_one(self):
        """CONSISTENCY: every band's node weights sum to 1."""
        z, w, _ = band_weights(("g", "z", 950.0), thickness=100.0, z_stop=0.5, nodes=5)
        assert z.size == 5
        for v in w.values():
            assert_allclose(v.sum(), 1.0, rtol=1e-12)


class TestMultiBandFile:
    def test_round_trip(self, bands_built, tmp_path):
        """CONSISTENCY: save/load keeps every band's arrays, meta and the band list."""
        path = tmp_path / "bands.fits"
        bands_built.save(path)
        back = load_templates(path)
        assert back.bands == ("u", "r", "y", "700nm")
        for key in back.bands:
            for name in ARRAYS:
                assert_allclose(getattr(back[key], name), getattr(bands_built[key], name),
                                rtol=0, atol=0)
            assert back[key].meta["depth"] == bands_built[key].meta["depth"]
        one = DistortionTemplate.load(path, band="Y")
        assert_allclose(one.corner_d, bands_built["y"].corner_d, rtol=0, atol=0)
        nm = DistortionTemplate.load(path, band=700.0)
        assert_allclose(nm.corner_d, bands_built["700nm"].corner_d, rtol=0, atol=0)
        with fits.open(path) as h:
            assert h[0].header["BFBANDS"] == "u,r,y,700nm"
            assert h["TEMPLATE_R"].header["BFBAND"] == "r"

    def test_single_band_file_serves_every_band(self, per_height, tmp_path):
        path = tmp_path / "one.fits"
        per_height[2].save(path)
        mb = load_templates(path)
        assert mb.bands == () and mb.single is not None
        assert_allclose(mb.select("z").corner_d, per_height[2].corner_d)
        assert_allclose(mb.select(None).corner_d, per_height[2].corner_d)
        with pytest.raises(TemplateFileError, match="single-band template file"):
            DistortionTemplate.load(path, band="r")

    def test_multi_band_file_needs_a_band(self, bands_built, tmp_path):
        path = tmp_path / "bands.fits"
        bands_built.save(path)
        with pytest.raises(TemplateFileError, match="multi-band template file"):
            DistortionTemplate.load(path)
        with pytest.raises(TemplateFileError, match="no template for band 'g'"):
            DistortionTemplate.load(path, band="g")

    def test_tampered_band_marker(self, bands_built, tmp_path):
        path = tmp_path / "bands.fits"
        bands_built.save(path)
        with fits.open(path, mode="update") as h:
            h["TEMPLATE_R"].header["BFBAND"] = "g"
            h["TEMPLATE_R"].add_checksum()
        with pytest.raises(TemplateFileError, match="not marked as band 'r'"):
            load_templates(path)


class TestSelect:
    def test_select_errors_name_the_problem(self, bands_built):
        with pytest.raises(InputError, match=r"gives no band.*u, r, y, 700nm"):
            bands_built.select(None, where="FILTER/BAND")
        with pytest.raises(InputError, match=r"no template for band 'g' \(from the exposure\)"):
            bands_built.select("g")
        with pytest.raises(InputError, match="unknown band"):
            bands_built.select("q")
        assert bands_built.select("r_57") is bands_built["r"]
        assert bands_built.select(700.0) is bands_built["700nm"]

    def test_band_key(self):
        assert band_key("LSST_i") == "i"
        assert band_key("700 nm") == "700nm"
        assert band_key(0.7e3) == "700nm"
        with pytest.raises(InputTypeError, match="band name or a wavelength"):
            band_key([1])


class TestBadInput:
    def test_build_refuses(self, tiny, per_height):
        params, settings, nodes = tiny
        with pytest.raises(InputError, match="conversion_height must be None"):
            build_band_templates(params, ("r",), settings=dataclasses.replace(
                settings, conversion_height=50.0))
        with pytest.raises(InputError, match="depth_response must be one of"):
            build_band_templates(params, ("r",), settings=settings, depth_response="exact")
        with pytest.raises(InputError, match="base is the template"):
            build_band_templates(params, ("r",), settings=settings, base=per_height[2])
        with pytest.raises(InputError, match="unknown band 'w'"):
            build_band_templates(params, ("w",), settings=settings, nodes=nodes)
        with pytest.raises(InputError, match="outside the silicon absorption table"):
            build_band_templates(params, (2000.0,), settings=settings, nodes=nodes)
        with pytest.raises(InputError, match="given once each"):
            build_band_templates(params, ("r", "R"), settings=settings, nodes=nodes)
        with pytest.raises(InputError, match="from the collection height"):
            build_band_templates(params, ("r",), settings=settings, nodes=[0.0, 50.0, 100.0])

    def test_combine_and_container_refuse(self, per_height, tiny):
        params, settings, _ = tiny
        other = build_template(params, dataclasses.replace(settings, size=5))
        with pytest.raises(InputError, match="differ in size"):
            combine_templates([per_height[1], other], [0.5, 0.5])
        with pytest.raises(InputError, match="at least one template"):
            combine_templates([None], [1.0])
        with pytest.raises(InputTypeError, match="not a DistortionTemplate"):
            MultiBandTemplate({"r": "file.fits"})
        with pytest.raises(InputError, match="at least one band"):
            MultiBandTemplate({})
