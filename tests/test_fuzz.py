"""Property-based fuzzing of the public entry points (hypothesis; issue 20).

Every generated case must end in one of two ways: a documented package error
(a :class:`~lsst_bfdrift.utils.errors.BfdriftError` or pex_config's
FieldValidationError, whose message names what is wrong), or a valid result
that obeys the package's invariants: conserved flux, no NaN where there was
none, the input untouched, the same result on a rerun, finite maps with
positive areas. These are checks against conservation laws and the inputs
themselves, not against the package's model.

The runs are seeded and derandomized (``tests/conftest.py`` registers the
profiles): the default profile generates about 800 cases in about a minute on
2 cores; ``BFDRIFT_HYPOTHESIS=extended python -m pytest -m slow tests/test_fuzz.py``
generates ten times more.
"""

import os
import warnings

import numpy as np
import pytest
from astropy import units as u
from astropy.io import fits
from astropy.nddata import CCDData
from hypothesis import HealthCheck, event, example, given, settings
from hypothesis import strategies as st

from lsst_bfdrift.cli.main import main
from lsst_bfdrift.correction.task import BrighterFatterDriftConfig, BrighterFatterDriftTask
from lsst_bfdrift.templates.template import load_default_template
from lsst_bfdrift.utils.errors import BfdriftError, FieldValidationError

pytestmark = pytest.mark.slow

ERRORS = (BfdriftError, FieldValidationError)
TEMPLATE = load_default_template()
_TASKS = {}


def _task(method, geometry):
    key = (method, geometry)
    if key not in _TASKS:
        cfg = BrighterFatterDriftConfig(method=method, compute_geometry=geometry, workers=1)
        _TASKS[key] = BrighterFatterDriftTask(config=cfg, template=TEMPLATE)
    return _TASKS[key]


@st.composite
def images(draw, max_side=24):
    """Small images: a sky level, a few bright sources, and special values; some all
    negative or all NaN (no charge at all)."""
    ny = draw(st.integers(1, max_side))
    nx = draw(st.integers(1, max_side))
    sky = draw(st.sampled_from([0.0, 1.0, 300.0, 5e3]))
    seed = draw(st.integers(0, 2**16))
    rng = np.random.default_rng(seed)
    img = rng.poisson(sky, (ny, nx)).astype(np.float64) if sky else np.zeros((ny, nx))
    for _ in range(draw(st.integers(0, 3))):
        y, x = draw(st.integers(0, ny - 1)), draw(st.integers(0, nx - 1))
        img[y, x] = draw(st.sampled_from([1e3, 1e5, 4e5, 6e5, 1e6, -1e4, 1e12, 1e300]))
    for _ in range(draw(st.integers(0, 2))):
        y, x = draw(st.integers(0, ny - 1)), draw(st.integers(0, nx - 1))
        img[y, x] = draw(st.sampled_from([np.nan, np.inf, -np.inf]))
    # issue 44: images with no charge to correct or map (all negative, all NaN)
    fill = draw(st.sampled_from(["as drawn"] * 4 + ["all negative", "all NaN"]))
    if fill == "all negative":
        img = -np.abs(np.nan_to_num(img, nan=1.0, posinf=1e6, neginf=1e6)) - 1.0
    elif fill == "all NaN":
        img = np.full(img.shape, np.nan)
    dtype = draw(st.sampled_from([np.float64, np.float32, np.int32]))
    if dtype is np.int32:
        img = np.nan_to_num(img, nan=0.0, posinf=0.0, neginf=0.0).clip(-2e9, 2e9)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # float32 overflow of 1e300 -> inf
        return img.astype(dtype)


@st.composite
def masks(draw, shape):
    if not draw(st.booleans()):
        return None
    seed = draw(st.integers(0, 2**16))
    return np.random.default_rng(seed).random(shape) < draw(st.sampled_from([0.01, 0.2, 1.0]))


def _check_result(res, data, blocked_extra=None):
    moved = res.flux_moved
    assert moved.shape == data.shape
    assert np.all(np.isfinite(moved))
    total = float(np.abs(moved).sum())
    assert abs(float(moved.sum())) <= 1e-9 * total + 1e-6 * max(1.0, np.sqrt(data.size))
    assert res.flags.shape == data.shape
    out = np.asarray(getattr(res.exposure, "data", res.exposure), dtype=float)
    finite_in = np.isfinite(data.astype(float))
    assert np.all(np.isfinite(out[finite_in]))  # no NaN spread into finite pixels
    if res.area is not None:
        for m in (res.area, res.centroid_x, res.centroid_y, res.e1, res.e2):
            assert np.all(np.isfinite(m))
        assert np.all(res.area > 0)


@settings(suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])
@given(data=st.data(), method=st.sampled_from(["drift", "astier23", "coulton18"]),
       geometry=st.booleans(), kind=st.sampled_from(["array", "masked", "ccddata"]))
def test_task_run(data, method, geometry, kind):
    img = data.draw(images())
    mask = data.draw(masks(img.shape))
    if kind == "masked":
        exp = np.ma.MaskedArray(img, mask=np.zeros(img.shape, bool) if mask is None else mask)
    elif kind == "ccddata":
        unit = data.draw(st.sampled_from([u.electron, u.adu, u.electron / u.s]))
        exp = CCDData(img.astype(float), unit=unit, mask=mask,
                      meta={"GAIN": data.draw(st.sampled_from([1.5, 0.0, "abc", True]))})
    else:
        exp = img
    before = np.array(img, copy=True)
    task = _task(method, geometry)
    try:
        res = task.run(exp)
    except ERRORS as exc:
        assert str(exc)
        event(f"refused: {type(exc).__name__}")
        return
    event("result")
    assert np.array_equal(img, before, equal_nan=True)  # input untouched
    _check_result(res, img)
    again = task.run(exp)
    assert np.array_equal(res.flux_moved, again.flux_moved)


@settings(suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])
@given(data=st.data(), linear=st.booleans())
def test_moment_maps(data, linear):
    from lsst_bfdrift.geometry.linear import linear_moment_maps
    from lsst_bfdrift.geometry.superpose import moment_maps
    img = data.draw(images()).astype(float)
    mask = data.draw(masks(img.shape))
    f = linear_moment_maps if linear else moment_maps
    try:
        maps = f(TEMPLATE, img, mask=mask)
    except ERRORS as exc:
        assert str(exc)
        event(f"refused: {type(exc).__name__}")
        return
    event("result")
    for m in (maps.area, maps.dx, maps.dy, maps.e1, maps.e2):
        assert np.all(np.isfinite(m))
    assert np.all(maps.area > 0)


@settings(suppress_health_check=[HealthCheck.too_slow])
@given(data=st.data())
def test_solvers(data):
    from lsst_bfdrift.correction.solvers import correct_half_shift, correct_image
    img = data.draw(images(max_side=16)).astype(float)
    blocked = ~np.isfinite(img)
    f = data.draw(st.sampled_from([correct_image, correct_half_shift]))
    try:
        flux = f(np.where(blocked, 0.0, img), TEMPLATE, blocked=blocked)[0]
    except ERRORS as exc:
        assert str(exc)
        event(f"refused: {type(exc).__name__}")
        return
    event("result")
    good = ~blocked
    assert np.all(np.isfinite(flux[good]))
    assert abs(float(flux[good].sum()) - float(img[good].sum())) <= \
        1e-9 * float(np.abs(img[good]).sum()) + 1e-6


@settings(suppress_health_check=[HealthCheck.too_slow])
@given(seed=st.integers(0, 2**16), ny=st.integers(2, 40), nx=st.integers(2, 40),
       level=st.sampled_from([-5.0, 0.0, 1.0, 1e3, 1e5]), max_lag=st.integers(-1, 12),
       nan=st.booleans())
def test_pair_covariances(seed, ny, nx, level, max_lag, nan):
    from lsst_bfdrift.ptc.covariances import pair_covariances
    rng = np.random.default_rng(seed)
    a = level + rng.normal(0, 1 + np.sqrt(abs(level)), (ny, nx))
    b = level + rng.normal(0, 1 + np.sqrt(abs(level)), (ny, nx))
    if nan:
        a[0, 0] = np.nan
    try:
        pc = pair_covariances(a, b, max_lag=max_lag, min_pixels=4)
    except ERRORS as exc:
        assert str(exc)
        event(f"refused: {type(exc).__name__}")
        return
    event("result")
    assert np.all(np.isfinite(pc.cov)) and pc.mu > 0


@settings(suppress_health_check=[HealthCheck.too_slow])
@given(mu=st.lists(st.floats(1.0, 1e5), max_size=14),
       bad=st.lists(st.sampled_from([float("nan"), -5.0, 0.0, 1e12]), max_size=2),
       scale=st.sampled_from([0.0, 1.0, 0.5]), seed=st.integers(0, 2**16))
@example(mu=[1.0, 1.0, 1.0, 2.0, 3.0], bad=[], scale=0.0, seed=0)  # found: numpy RankWarning
def test_ptc_fits(mu, bad, scale, seed):
    from lsst_bfdrift.ptc.covariances import fit_ptc_exponential
    mu = np.asarray(mu + bad, float)
    noise = 1 + 0.01 * np.random.default_rng(seed).standard_normal(mu.size)
    var = (scale * mu + 1e-7 * mu**2 + 10.0) * noise
    try:
        fit = fit_ptc_exponential(mu, var)
    except ERRORS as exc:
        assert str(exc)
        event(f"refused: {type(exc).__name__}")
        return
    event("result")
    assert np.isfinite(fit["gain"]) and fit["gain"] > 0
    assert np.isfinite(fit["gain_err"]) and fit["gain_err"] > 0  # never a zero error


_TEXT = st.text(alphabet=st.sampled_from(list("0123456789 .-+eE,#\tabcnaif\n")), max_size=200)


@settings(suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture])
@given(text=_TEXT, which=st.sampled_from(["acoeff", "ptc", "diagnose"]))
def test_text_readers(tmp_path, text, which):
    from lsst_bfdrift.ptc.acoeffs import read_acoeff_table
    from lsst_bfdrift.diagnosis.effects_fit import load_input
    from lsst_bfdrift.ptc.covariances import read_ptc_text
    path = tmp_path / f"in_{abs(hash(text)) % 10**8}.txt"
    path.write_text(text)
    f = {"acoeff": read_acoeff_table, "ptc": read_ptc_text,
         "diagnose": lambda p: load_input(str(p))}[which]
    try:
        f(path)
    except ERRORS as exc:
        assert str(path) in str(exc) or path.name in str(exc), str(exc)


@settings(suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture],
          max_examples=40)
@given(cut=st.integers(0, 60000), flip=st.integers(0, 60000), byte=st.integers(0, 255))
def test_template_loader_on_damaged_files(tmp_path, cut, flip, byte):
    from lsst_bfdrift.templates.template import DistortionTemplate
    from lsst_bfdrift.utils.io import data_path
    with open(data_path("default_template.fits"), "rb") as fh:
        raw = bytearray(fh.read())
    if flip < len(raw):
        raw[flip] = byte
    raw = raw[:max(cut, 0)] if cut < len(raw) else raw
    path = tmp_path / f"t_{cut}_{flip}_{byte}.fits"
    path.write_bytes(bytes(raw))
    try:
        t = DistortionTemplate.load(path)
    except ERRORS as exc:
        assert path.name in str(exc), str(exc)
        event("refused")
        return
    event("loaded")
    assert np.all(np.isfinite(t.corner_d))  # a change the checksums do not see: still valid


#: ECSV units of a-matrix columns: the per-electron factor of each, None where the
#: unit is not per electron and must be refused (issue 44 item 2).
_ACOEFF_UNITS = {None: 1.0, "1 / electron": 1.0, "0.001 / electron": 1e-3,
                 "1000 / electron": 1e3, "1 / adu": None, "pix": None, "electron": None}


@st.composite
def acoeff_tables(draw):
    """a-matrix tables as a user writes them (issue 44): text (a header or not) or ECSV
    with units, short tables (a00 alone, a row left out) and malformed rows.

    Returns (text, suffix, expected): ``expected`` the a_ij per electron a reader must
    return, None when it must refuse the table.
    """
    L = draw(st.integers(0, 3))
    i, j = np.meshgrid(np.arange(L + 1), np.arange(L + 1), indexing="ij")
    a = draw(st.sampled_from([1e-7, 3e-8])) / (1.0 + i**2 + 2.0 * j**2) * (1.0 + j)
    a[0, 0] = -draw(st.sampled_from([1.3e-6, 4e-7]))
    sig = np.full(a.shape, 1e-8)
    ecsv = draw(st.booleans())
    unit = draw(st.sampled_from(sorted(_ACOEFF_UNITS, key=str))) if ecsv else None
    factor = _ACOEFF_UNITS[unit]
    rows = [(int(x), int(y)) for x, y in zip(i.ravel(), j.ravel())]
    defect = draw(st.sampled_from(["none", "none", "short", "malformed"]))
    if defect == "short":
        del rows[draw(st.integers(0, len(rows) - 1))]
    scale = 1.0 if factor is None else factor
    if ecsv:
        import io
        from astropy.table import Table
        t = Table({"i": [r[0] for r in rows], "j": [r[1] for r in rows],
                   "a": [a[r] / scale for r in rows], "a_err": [sig[r] / scale for r in rows]})
        if unit is not None:
            t["a"].unit = t["a_err"].unit = u.Unit(unit)
        buf = io.StringIO()
        t.write(buf, format="ascii.ecsv")
        lines = buf.getvalue().splitlines()
    else:
        lines = (["i j a sigma"] if draw(st.booleans()) else []) + [
            f"{x} {y} {float(a[x, y])!r} {float(sig[x, y])!r}" for x, y in rows]
    data = [k for k, line in enumerate(lines) if line and line[0].isdigit()]
    if defect == "malformed" and data:
        k = draw(st.sampled_from(data))
        fields = lines[k].split()
        fields[draw(st.integers(0, len(fields) - 1))] = draw(
            st.sampled_from(["x", "1e-7x", "--", "0x10"]))
        lines[k] = " ".join(fields)
    refused = defect != "none" or factor is None or not rows
    return "\n".join(lines) + "\n", "ecsv" if ecsv else "txt", None if refused else a


@settings(suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture],
          max_examples=60)
@given(table=acoeff_tables())
def test_amatrix_readers_agree(tmp_path, table):
    """calibrate's and diagnose's readers take an a-matrix table alike: both refuse it,
    naming the file, or both return its a_ij per electron (units converted)."""
    from lsst_bfdrift.diagnosis.effects_fit import load_input
    from lsst_bfdrift.ptc.inputs import read_calibration_input
    text, suffix, expected = table
    path = tmp_path / f"t_{abs(hash(text)) % 10**8}.{suffix}"
    path.write_text(text)
    got = []
    for read in (lambda p: read_calibration_input(p).acoeff_table(), lambda p: load_input(p)):
        try:
            t = read(str(path))
        except ERRORS as exc:
            assert str(path) in str(exc), str(exc)
            got.append(None)
            continue
        got.append((t.a, t.sigma))
    assert path.read_text() == text  # the input untouched
    if expected is None:
        assert got == [None, None]
        event("refused")
        return
    event(f"read, lags 0..{expected.shape[0] - 1}")
    for a, sigma in got:
        np.testing.assert_allclose(a, expected, rtol=1e-12)
        np.testing.assert_allclose(sigma, 1e-8, rtol=1e-12)


@st.composite
def flat_sets(draw):
    """Flat sets as a user may bring them (issue 44): pairs at 3 to 7 levels, a pair
    perhaps a file and its copy, levels at EXPTIME zero or negative, a pair of
    constant (saturated) images."""
    n = draw(st.integers(3, 7))
    return {"n": n, "seed": draw(st.integers(0, 2**16)),
            "copy": draw(st.one_of(st.none(), st.integers(0, n - 1))),
            "zero": draw(st.lists(st.integers(0, n - 1), max_size=2, unique=True)),
            "exptime0": draw(st.sampled_from([0.0, -1.0])),
            "constant": draw(st.one_of(st.none(), st.integers(0, n - 1)))}


def _write_flat_set(directory, spec):
    rng = np.random.default_rng(spec["seed"])
    pairs = []
    for k in range(spec["n"]):
        t = spec["exptime0"] if k in spec["zero"] else float(2**k)  # levels follow EXPTIME
        pair = []
        for half in "ab":
            path = os.path.join(directory, f"flat_{k}{half}.fits")
            if half == "b" and k == spec["copy"]:
                with open(pair[0], "rb") as src, open(path, "wb") as dst:
                    dst.write(src.read())
            else:
                img = (np.full((32, 32), 65535.0) if k == spec["constant"]
                       else rng.poisson(500.0 * 2**k, (32, 32)))
                fits.PrimaryHDU(img.astype(np.float32),
                                header=fits.Header({"EXPTIME": t, "BUNIT": "adu"})).writeto(path)
            pair.append(path)
        pairs.append(pair)
    return pairs


@settings(suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture],
          max_examples=25)
@given(spec=flat_sets())
def test_flat_reader_on_copied_and_zero_exposure_files(tmp_path, spec):
    """Every file the reader leaves out is named with its reason (a copy as one
    exposure twice, EXPTIME <= 0 as not a flat, constant images as such), no pair of
    two exposures is dropped as past a turn-off, and the files are untouched; or a
    refusal names the files."""
    import hashlib
    import tempfile

    from lsst_bfdrift.ptc.inputs import read_calibration_input
    d = tempfile.mkdtemp(dir=tmp_path)
    pairs = _write_flat_set(d, spec)
    paths = [p for pair in pairs for p in pair]

    def digest():
        out = []
        for p in paths:
            with open(p, "rb") as fh:
                out.append(hashlib.sha256(fh.read()).hexdigest())
        return out
    before = digest()
    try:
        data = read_calibration_input(paths, max_lag=1, min_pixels=200, min_levels=2)
    except ERRORS as exc:
        assert d in str(exc) or any(p in str(exc) for p in paths), str(exc)
        event("refused")
        return
    finally:
        assert digest() == before
    event(f"{data.n_levels} levels")
    reasons = {tuple(p["files"]): p["reason"] for p in data.pairs_dropped}
    used = [tuple(p["files"]) for p in data.pairs_used]
    for k, pair in enumerate(pairs):
        if k in spec["zero"]:
            assert all("is not positive (a bias or dark" in reasons[(f,)] for f in pair)
        elif k == spec["constant"]:
            assert "both images are constant" in reasons[tuple(pair)]
        elif k == spec["copy"]:
            assert reasons[tuple(pair)].startswith("the two images are one exposure")
        else:  # two exposures below any saturation: used
            assert tuple(pair) in used, reasons
    assert data.n_levels == len(used)


_VALUES = st.sampled_from(["0", "-1", "nan", "inf", "2.5", "1e40", "abc"])


@st.composite
def cli_args(draw):
    """A command with its required arguments and a few options of random values."""
    command = draw(st.sampled_from(["template summary", "ptc", "diagnose", "maps", "correct",
                                    "calibrate"]))
    argv = command.split()
    files = {"template summary": [], "ptc": ["IN", "IN"], "diagnose": ["TXT"],
             "maps": ["IN"], "correct": ["IN", "OUT"], "calibrate": ["TXT", "--out", "OUT"]}
    argv += files[command]
    options = {"ptc": ["--max-lag"], "diagnose": ["--max-lag"], "calibrate": ["--max-lag"],
               "maps": ["--gain", "--samples"], "correct": ["--gain", "--saturation"],
               "template summary": []}[command]
    for opt in draw(st.lists(st.sampled_from(options), max_size=2, unique=True)) \
            if options else []:
        argv += [opt, draw(_VALUES)]
    if command == "correct" and draw(st.booleans()):
        argv += ["--method", draw(st.sampled_from(["drift", "astier23", "magic"]))]
    for flag in draw(st.lists(st.sampled_from(["--json", "--quiet", "--overwrite"]),
                              max_size=2, unique=True)):
        if command != "template summary" or flag == "--json":
            argv.append(flag)
    return argv


@settings(suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture],
          max_examples=80)
@given(argv=cli_args(), text=_TEXT)
def test_cli_never_tracebacks(tmp_path, capsys, argv, text):
    rng = np.random.default_rng(1)
    img = tmp_path / "IN"
    if not img.exists():
        fits.PrimaryHDU(rng.poisson(500.0, (24, 24)).astype(np.float32)).writeto(img)
    (tmp_path / "TXT").write_text(text)
    argv = [str(tmp_path / a) if a in ("IN", "OUT", "TXT") else a for a in argv]
    try:
        code = main(argv)
    except SystemExit as exc:  # argparse usage errors
        assert exc.code in (0, 2)
        event(f"usage exit {exc.code}")
        return
    finally:
        capsys.readouterr()
    assert code in (0, 1, 2, 3, 4)
    event(f"{argv[0]} exit {code}")
    assert not [p for p in os.listdir(tmp_path) if p.startswith(".tmp-")]


@st.composite
def spot_series(draw):
    """Small spot series: a grid of Gaussian spots (some near an edge) at a few exposure
    times, with noise, special values, saturated or dark frames, and bad times."""
    n = draw(st.sampled_from([3, 4, 4, 4, 2]))
    side = draw(st.integers(100, 130))
    grid = draw(st.sampled_from([3] * 5 + [1]))
    sigma = draw(st.sampled_from([0.7, 1.5, 2.0]))
    seed = draw(st.integers(0, 2**16))
    rng = np.random.default_rng(seed)
    jj, ii = np.mgrid[:side, :side]
    margin = draw(st.sampled_from([0.23] * 5 + [0.02])) * side  # some at an edge
    pos = np.linspace(margin, side - 1 - margin, grid) + rng.uniform(-0.5, 0.5, grid)
    levels = rng.choice([1e4, 3e4, 3e5, 3e6, 0.0], n, p=[0.1, 0.35, 0.35, 0.15, 0.05])
    imgs = []
    for level in levels:
        img = np.zeros((side, side))
        for x in pos:
            for y in pos:
                img += level * np.exp(-0.5 * ((ii - x) ** 2 + (jj - y) ** 2) / sigma ** 2) / (
                    2 * np.pi * sigma ** 2)
        img = rng.poisson(img + 20.0).astype(float) + rng.normal(0.0, 5.0, img.shape)
        if draw(st.integers(0, 3)) == 0:
            y, x = draw(st.integers(0, side - 1)), draw(st.integers(0, side - 1))
            img[y, x] = draw(st.sampled_from([np.nan, np.inf, -1e6, 1e12]))
        imgs.append(img)
    times = draw(st.sampled_from(["levels"] * 6 + ["equal", "one bad"]))
    exptimes = [max(float(v), 1.0) / 1e5 for v in levels]
    if times == "equal":
        exptimes = [1.0] * n
    elif times == "one bad":
        exptimes[0] = draw(st.sampled_from([0.0, -1.0, np.nan]))
    saturation = draw(st.sampled_from([None] * 5 + [5e4, 1e3]))
    return imgs, exptimes, saturation


@settings(suppress_health_check=[HealthCheck.too_slow], max_examples=20, deadline=None)
@given(spec=spot_series())
def test_spot_series_measurement(spec):
    """The spot measurement (find, measure, fit) on generated series: a documented refusal,
    or rows whose used ones have finite, positive fluxes and finite moments with
    errors, and finite slopes; the inputs untouched and the rerun identical."""
    from lsst_bfdrift.catalogs.spot_series import SpotSeries

    imgs, exptimes, saturation = spec
    before = [np.array(i, copy=True) for i in imgs]
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            series = SpotSeries(imgs, exptimes=exptimes, saturation=saturation)
            fit = series.fit()
    except ERRORS as exc:
        assert str(exc)
        event(f"refused: {type(exc).__name__}")
        series = None
    for a, b in zip(imgs, before):
        assert np.array_equal(a, b, equal_nan=True)  # inputs untouched, either way
    if series is None:
        return
    event("measured")
    cat = series.catalog
    use = np.asarray(cat["use"], bool)
    assert use.any()
    flux = np.asarray(getattr(cat["flux"], "value", cat["flux"]), float)[use]
    assert np.all(np.isfinite(flux)) and np.all(flux > 0)
    for q in ("size", "e1", "e2"):
        assert np.all(np.isfinite(np.asarray(cat[q], float)[use]))
        assert np.all(np.asarray(cat[f"{q}_err"], float)[use] > 0)
        assert np.isfinite(fit[q]["slope"]) and fit[q]["slope_err"] > 0
    again = SpotSeries(imgs, exptimes=exptimes, saturation=saturation).fit()
    assert again["e1"]["slope"] == fit["e1"]["slope"]
