"""Tables of measured area coefficients a_ij: reading, orientation, the sum rule.

Measured area coefficients a_ij (per electron; Astier et al. 2019) are the
relative area change of the pixel at lag (i, j) = (serial, parallel) per
electron collected in the aggressor pixel, a_ij = d ln A_ij / dQ. This module

* holds them with their errors (:class:`AcoeffTable`) and reads tables of
  them (:func:`read_acoeff_table`, :func:`acoeff_square`),
* establishes which file axis is parallel from the data
  (:func:`assign_axes`: the larger nearest neighbour is the parallel one,
  because the clock barriers are weaker than the channel stops) and whether
  a00 was set by the area sum rule (:func:`sum_rule_check`).

The model's a_ij and its fit to a table are in
:mod:`lsst_bfdrift.calibration.acoeff_model`.

Arrays of coefficients are indexed ``a[i, j]`` with i the serial lag and j
the parallel lag, 0 <= i, j <= L (the model is symmetric in the sign of each).
"""

import math

import numpy as np

from lsst_bfdrift.templates.refine import lag_multiplicity
from lsst_bfdrift.utils.errors import InputError
from lsst_bfdrift.utils.io import read_text_rows

__all__ = ["AcoeffTable", "read_acoeff_table", "assign_axes", "sum_rule_check",
           "lag_radius", "acoeff_square", "check_consistency",
           "near_field_response", "MAX_TABLE_LAG"]

#: Largest lag an a_ij table may hold (measured tables reach ~20; a larger
#: lag is a typo, and the square arrays grow as its square).
MAX_TABLE_LAG = 64


def lag_radius(max_lag):
    """Array r[i, j] = sqrt(i^2 + j^2) for 0 <= i, j <= max_lag."""
    i, j = np.meshgrid(np.arange(max_lag + 1), np.arange(max_lag + 1), indexing="ij")
    return np.hypot(i, j)


class AcoeffTable:
    """Measured a_ij (per e) with 1-sigma errors, indexed [serial, parallel].

    Attributes
    ----------
    a, sigma : ndarray, shape (L + 1, L + 1)
        Coefficients and errors (per e).
    max_lag : int
    source : str
        Where the table came from.
    axis_note : str
        How the axis assignment was established.
    exclude_a00 : bool
        True when a00 must be left out of chi2 (set by the sum rule).
    """

    def __init__(self, a, sigma, *, source="", axis_note="", exclude_a00=False):
        a = np.array(a, dtype=np.float64)
        sigma = np.array(sigma, dtype=np.float64)
        if a.ndim != 2 or a.shape[0] != a.shape[1]:
            raise InputError(f"a_ij must be a square 2-d array, got shape {a.shape}")
        if sigma.shape != a.shape:
            raise InputError(f"errors have shape {sigma.shape}, coefficients {a.shape}")
        if not np.all(np.isfinite(a)):
            raise InputError("a_ij table holds non-finite coefficients")
        if not np.all(np.isfinite(sigma)) or np.any(sigma <= 0):
            raise InputError("a_ij errors must be finite and positive (found NaN, inf, zero "
                             "or negative errors)")
        self.a, self.sigma = a, sigma
        self.max_lag = a.shape[0] - 1
        self.source, self.axis_note, self.exclude_a00 = source, axis_note, bool(exclude_a00)

    def mask(self):
        """Boolean array of the lags that enter chi2."""
        m = np.ones(self.a.shape, dtype=bool)
        if self.exclude_a00:
            m[0, 0] = False
        return m

    def transposed(self):
        """The table with the two axes exchanged."""
        return AcoeffTable(self.a.T, self.sigma.T, source=self.source,
                           axis_note=self.axis_note, exclude_a00=self.exclude_a00)

    def truncated(self, max_lag):
        """The table restricted to lags <= ``max_lag``."""
        k = int(max_lag) + 1
        return AcoeffTable(self.a[:k, :k], self.sigma[:k, :k], source=self.source,
                           axis_note=self.axis_note, exclude_a00=self.exclude_a00)


def acoeff_square(path, i, j, a, s):
    """Checked square arrays a[i, j], sigma[i, j] from row values."""
    i = np.asarray(i, dtype=float)
    j = np.asarray(j, dtype=float)
    a = np.asarray(a, dtype=float)
    s = np.asarray(s, dtype=float)
    if i.size == 0:
        raise InputError(f"{path}: no a_ij rows found; accepted: rows of i j value sigma")
    lags = np.column_stack([i, j])
    badlag = ~np.isfinite(lags).all(axis=1) | np.any(lags != np.round(lags), axis=1) | np.any(
        lags < 0, axis=1)
    if badlag.any():
        bad = [(float(x), float(y)) for x, y in lags[badlag][:3]]
        raise InputError(f"{path}: lags must be non-negative integers (i serial, j parallel); "
                         f"found {bad}")
    if not np.all(np.isfinite(a)):
        k = int(np.flatnonzero(~np.isfinite(a))[0])
        raise InputError(f"{path}: coefficient at lag ({int(i[k])}, {int(j[k])}) is {a[k]}; "
                         "accepted: finite a_ij (per electron)")
    badsig = ~(np.isfinite(s) & (s > 0))
    if badsig.any():
        ks = np.flatnonzero(badsig)[:3]
        found = ", ".join(f"({int(i[k])}, {int(j[k])}): {s[k]:g}" for k in ks)
        raise InputError(f"{path}: {int(badsig.sum())} a_ij error(s) not positive and finite "
                         f"(lag: error {found}); accepted: positive 1-sigma errors per electron")
    if max(i.max(), j.max()) > MAX_TABLE_LAG:
        k = int(np.argmax(np.maximum(i, j)))
        raise InputError(f"{path}: lag ({int(i[k])}, {int(j[k])}) is beyond {MAX_TABLE_LAG}; "
                         f"accepted: lags 0..{MAX_TABLE_LAG} (measured tables reach ~20)")
    ii, jj = i.astype(int), j.astype(int)
    if not np.any((ii == 0) & (jj == 0)):
        raise InputError(f"{path}: no a00 (lag 0, 0) row; the table must include a00, measured "
                         "or set by the area sum rule")
    L = int(max(ii.max(), jj.max()))
    A = np.full((L + 1, L + 1), np.nan)
    S = np.full((L + 1, L + 1), np.nan)
    for x, y, v, e in zip(ii, jj, a, s):
        if not np.isnan(A[x, y]):
            raise InputError(f"{path}: lag ({x}, {y}) appears twice; each lag once")
        A[x, y], S[x, y] = v, e
    if np.isnan(A).any():
        miss = [tuple(m) for m in np.argwhere(np.isnan(A))[:3].tolist()]
        raise InputError(f"{path}: incomplete table, missing lags e.g. {miss}; accepted: every "
                         f"lag 0 <= i, j <= {L} once")
    return A, S


def _text_rows(path):
    accepted = "rows of i j value sigma (a first line of column names allowed)"
    rows = read_text_rows(path, accepted=accepted)
    for n, vals in rows:
        if len(vals) != 4:
            raise InputError(f"{path}:{n}: {len(vals)} columns; accepted: 4 (i j value "
                             "sigma)")
    d = np.array([vals for _, vals in rows], dtype=float).reshape(-1, 4)
    return d[:, 0], d[:, 1], d[:, 2], d[:, 3]


def read_acoeff_table(path, *, orient=True):
    """Read a text table ``i j value sigma`` (one lag per row, header allowed).

    Parameters
    ----------
    path : str
        File name. Rows hold integer lags i, j >= 0, the coefficient (per e)
        and its 1-sigma error; lines without any number before the first row
        are a header, any other line with a field that is not a number is an
        error naming the line (:func:`~lsst_bfdrift.utils.io.read_text_rows`).
        A table of a00 alone is accepted (nothing to orient, no sum rule).
    orient : bool, optional
        Establish the axis assignment from the data (:func:`assign_axes`)
        and detect a sum-rule a00 (:func:`sum_rule_check`).

    Returns
    -------
    AcoeffTable
        Indexed [serial, parallel] when ``orient`` is true, else in the file's
        (i, j) order.
    """
    a, s = acoeff_square(path, *_text_rows(path))
    table = AcoeffTable(a, s, source=str(path))
    if orient:
        table = assign_axes(table)
        ok, note = sum_rule_check(table)
        table.exclude_a00 = ok
        table.axis_note += "; " + note
    return table


def assign_axes(table):
    """Orient a table as [serial, parallel] from the data itself.

    The clock barriers between rows are weaker than the channel stops, so a
    collected charge pushes the row boundaries further: the parallel nearest
    neighbour has the larger coefficient (the paper's A01 > A10; every
    measured LSST sensor). The axis of the larger of the file's a[0, 1] and
    a[1, 0] is taken as parallel; the significance of the difference is
    reported in ``axis_note``.

    Parameters
    ----------
    table : AcoeffTable
        In the file's (i, j) order.

    Returns
    -------
    AcoeffTable
        [serial, parallel] order; a table of a00 alone as it is (no nearest
        neighbours to orient it by, said in ``axis_note``).
    """
    if table.max_lag == 0:
        return AcoeffTable(table.a, table.sigma, source=table.source,
                           axis_note="a00 only: no nearest neighbours, nothing to orient",
                           exclude_a00=table.exclude_a00)
    a01, a10 = table.a[0, 1], table.a[1, 0]
    s = math.hypot(table.sigma[0, 1], table.sigma[1, 0])
    z = abs(a01 - a10) / s
    if a01 >= a10:
        out = AcoeffTable(table.a, table.sigma, source=table.source,
                          exclude_a00=table.exclude_a00)
        which = "file (i, j) = (serial, parallel): a[0,1] > a[1,0]"
    else:
        out = table.transposed()
        which = "file (i, j) = (parallel, serial): a[1,0] > a[0,1], axes swapped"
    out.axis_note = (f"{which} by {z:.1f} sigma ({max(a01, a10):.3g} vs {min(a01, a10):.3g}; "
                     "the larger nearest neighbour is the parallel one)")
    return out


def sum_rule_check(table, *, nsigma=1.0):
    """Whether a00 equals minus the sum of all other lags (area sum rule).

    Sums a_ij over all signed lags except (0, 0) (weights 2 on the axes, 4
    off them) and compares with -a00. When they agree to better than
    ``nsigma`` times the error of a00 *divided by 10*, a00 was evidently set
    by the rule, not measured, and must stay out of chi2.

    Returns
    -------
    (bool, str)
        The verdict and a sentence with the numbers; a table of a00 alone
        has no other lag to sum: a00 is taken as measured.
    """
    a = table.a
    if table.max_lag == 0:
        return False, (f"a00 = {a[0, 0]:.4g} alone: no other lag to check the sum rule "
                       "with; a00 taken as measured, kept")
    w = np.full(a.shape, 4.0)
    w[0, :] = 2.0
    w[:, 0] = 2.0
    w[0, 0] = 0.0
    s = float(np.sum(w * a))
    gap = a[0, 0] + s
    ok = abs(gap) < nsigma * table.sigma[0, 0] / 10.0
    note = (f"a00 = {a[0, 0]:.4g}, minus the sum of the other lags = {-s:.4g} (gap {gap:.2g}, "
            f"a00 error {table.sigma[0, 0]:.2g}): "
            + ("a00 set by the sum rule, left out of chi2" if ok else "a00 measured, kept"))
    return ok, note


def near_field_response(a, sigma=None, *, from_sum_rule=False):
    """The net area response of the 3 x 3 block around a charge, S1 (per e).

    S1 = a00 + 2 (a01 + a10) + 4 a11: the relative area change, summed over
    the aggressor and its eight neighbours, per electron in the aggressor.
    By area conservation it is minus the response of every pixel beyond them.
    The stars' size-flux slope left by a correction follows it
    (``benchmarks/calibration/flats_links.py``: on GalSim's stars the size
    slope left moves by 0.7-1.0 % of the uncorrected slope per 1 % of S1),
    and an a-matrix measures it poorly: a difference of large terms of
    opposite sign.

    Parameters
    ----------
    a : array_like, shape (L + 1, L + 1), L >= 1
        a_ij (per e), [serial, parallel].
    sigma : array_like, optional
        Their 1-sigma errors (independent); NaN or inf where unmeasured.
    from_sum_rule : bool, optional
        a00 was set by the area sum rule (:attr:`AcoeffTable.exclude_a00`):
        S1 is then minus the response of every lag beyond the block, with
        those lags' errors (a00's own error says nothing of S1).

    Returns
    -------
    s1 : float
        Per e.
    error : float or None
        1-sigma error of ``s1`` from ``sigma`` (None without it, NaN when a
        lag of the block is unmeasured).

    Raises
    ------
    InputError
        Fewer than two lags per axis.

    Examples
    --------
    >>> a = [[-2.0e-6, 3.0e-7], [1.0e-7, 5.0e-8]]
    >>> s1, err = near_field_response(a, [[1e-7, 1e-8], [1e-8, 1e-8]])
    >>> print(f"{s1:.2e} {err:.2e}")
    -1.00e-06 1.11e-07
    """
    a = np.asarray(a, dtype=np.float64)
    if a.ndim != 2 or min(a.shape) < 2:
        raise InputError(f"the near-field response needs lags 0-1 on both axes, got a_ij of "
                         f"shape {a.shape}")
    if from_sum_rule:
        w = lag_multiplicity(a.shape[0] - 1)
        w[:2, :2] = 0.0
        sign = -1.0
    else:
        w = np.zeros(a.shape)
        w[:2, :2] = lag_multiplicity(1)
        sign = 1.0
    s1 = sign * float(np.sum(w * a))
    if sigma is None:
        return s1, None
    s = np.asarray(sigma, dtype=np.float64)
    return s1, float(np.sqrt(np.sum((w * s)[w > 0] ** 2)))


def check_consistency(table, *, nsigma=5.0, zero_ring=2.0):
    """Refuse an a-matrix that is inconsistent in itself, naming the check that failed.

    Checks:

    * **a00 shrinks its pixel**: a measured a00 must be negative (a pixel
      loses area to the charge it holds); one above ``nsigma`` errors is a
      sign error or another quantity.
    * **The area sum rule, when the lags are complete**: pixel areas sum to a
      constant, so the sum of a_ij over all lags (2 on the axes, 4 off them,
      a00 once) is zero. When a00 is measured and every lag of the table's
      outermost ring is within ``zero_ring`` errors of zero (the table
      reaches the lags where the effect has faded), a sum more than
      ``nsigma`` errors from zero says a00, or the errors, are wrong.

    Parameters
    ----------
    table : AcoeffTable
    nsigma : float, optional
    zero_ring : float, optional

    Returns
    -------
    list of str
        The checks made and their figures (for reports).

    Raises
    ------
    InputError
        A failed check, named, with its figures.
    """
    a, s = table.a, table.sigma
    m = table.mask()
    src = table.source or "the a-matrix"
    done = []
    if not table.exclude_a00 and m[0, 0]:
        if a[0, 0] > nsigma * s[0, 0]:
            raise InputError(f"{src}: a00 = {a[0, 0]:+.3g} per e ({a[0, 0] / s[0, 0]:+.1f} "
                             "sigma above zero): a pixel grows with its own charge; the check "
                             "'a00 shrinks its pixel' failed (a sign error, or a table of "
                             "another quantity?)")
        done.append(f"a00 shrinks its pixel: a00 = {a[0, 0]:.3g}")
    L = table.max_lag
    ring = m.copy()
    ring[:L, :L] = False
    complete = L >= 3 and ring.any() and bool(np.all(np.abs(a[ring]) <= zero_ring * s[ring]))
    if complete and not table.exclude_a00 and m[0, 0]:
        w = lag_multiplicity(L)
        total = float(np.sum((w * a)[m]))
        err = float(np.sqrt(np.sum(((w * s)[m]) ** 2)))
        if abs(total) > nsigma * err:
            raise InputError(
                f"{src}: the area sum rule fails: the a_ij sum to {total:+.3g} +- {err:.2g} per "
                f"e ({total / err:+.1f} sigma) over lags 0..{L}, whose outermost lags are zero "
                f"within {zero_ring:g} errors (the table is complete); the check 'sum rule "
                "when the lags are complete' failed: a00 or the errors are wrong")
        done.append(f"sum rule (lags complete): {total:+.3g} +- {err:.2g} per e")
    elif complete:
        done.append("sum rule: a00 not measured, not checked")
    else:
        done.append(f"sum rule: not checked (the lags at {L} are not yet zero within their "
                    "errors: the table stops short of the effect's reach)")
    return done
