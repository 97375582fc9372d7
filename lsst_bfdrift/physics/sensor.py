"""Sensor model: the LSST pixel array assembled from field terms.

Geometry (see ``docs/conventions.rst``): pixel (i, j) covers
``i p <= x < (i + 1) p`` and ``j p <= y < (j + 1) p``; column boundary ``b``
is the line x = b p, row boundary ``b`` the line y = b p. Channel stops lie on
every column boundary, clock barriers on every row boundary, all in the gate
plane z = ``barrier_height``. Dipole strengths are given in units of the
paper's xi0, whose SI value (in e = e um / um) is the parameter ``xi0``.
"""

import dataclasses
import json
import math
from dataclasses import dataclass, field

import numpy as np
from astropy import constants as const
from astropy import units as u

from lsst_bfdrift.physics.fields import (BackdropField, HalfPeriodicDipoleGrid, LineDipole,
                                         PeriodicDipoleGrid, PointDipoles, TruncatedLineDipole)
from lsst_bfdrift.utils.errors import InputError, InputKeyError, InputTypeError

__all__ = ["SensorParameters", "SensorModel", "strict_from_dict"]

# Unit of each float parameter, for astropy Quantity input.
_UNITS = {
    "pixel_pitch": u.um, "thickness": u.um, "v_bss": u.V, "front_potential": u.V,
    "acceptor_density": u.cm**-3, "clock_separation": u.um, "barrier_height": u.um,
    "channel_depth": u.um, "collection_height": u.um, "guard_ring_offset": u.um,
}


def _as_float(name, value):
    if isinstance(value, u.Quantity):
        if name in _UNITS:
            value = value.to_value(_UNITS[name])
        elif name == "xi0":
            if value.unit.physical_type == "electrical charge":
                value = (value / const.e.si).decompose().value
            else:
                value = value.to_value(u.electron)
        else:
            raise InputTypeError(f"parameter {name!r} takes no units")
    try:
        value = float(value)
    except (TypeError, ValueError):
        raise InputTypeError(f"parameter {name!r} must be a number, got {value!r}") from None
    if not math.isfinite(value):
        raise InputError(f"parameter {name!r} must be finite, got {value!r}")
    return value


def strict_from_dict(cls, mapping, what):
    """Build dataclass ``cls`` from ``mapping``, naming any unknown keys.

    ``what`` is the phrase used in the error, e.g. "sensor parameter".
    """
    names = {f.name for f in dataclasses.fields(cls)}
    unknown = sorted(set(mapping) - names)
    if unknown:
        raise InputKeyError(f"unknown {what}(s): {', '.join(unknown)}; "
                       f"known: {', '.join(sorted(names))}")
    return cls(**dict(mapping))


def _pairs(name, value, width):
    """Normalise an override list to a tuple of float tuples."""
    if value is None:
        return ()
    if isinstance(value, dict):
        value = [(k,) + (tuple(v) if isinstance(v, (list, tuple)) else (v,))
                 for k, v in value.items()]
    out = []
    for item in value:
        item = tuple(item)
        if len(item) != width:
            raise InputError(f"each entry of {name} must have {width} numbers, got {item!r}")
        out.append(tuple(_as_float(name, v) for v in item))
    return tuple(out)


#: Rasmussen 2015's nominal values of the parameters that the default
#: calibration changes (:meth:`SensorParameters.paper`).
_PAPER = {"xi0": 1000.0, "channel_depth": 2.0, "clock_separation": 3.0, "v_bss": -50.0,
          "collection_height": None}


@dataclass(frozen=True)
class SensorParameters:
    """Parameters of the electrostatic sensor model.

    The defaults describe the sensor of the bundled default template: an
    LSST ITL sensor, Rasmussen 2015's structure calibrated to its measured
    a-matrix (``benchmarks/calibration/calibrate_default.py``: the charge dipole, the
    backside bias and the clock-pair separation). :meth:`paper` gives the
    paper's nominal values.

    Every float accepts an astropy Quantity with compatible units; plain
    numbers are taken in the units below.

    Parameters
    ----------
    pixel_pitch : float
        Pixel pitch p (um).
    thickness : float
        Silicon thickness t_Si (um).
    v_bss : float
        Backside bias V_BSS (V).
    front_potential : float
        Effective potential of the gate plane (V); dV = front_potential - v_bss.
    acceptor_density : float
        Bulk acceptor density N_a (cm^-3).
    xi0 : float
        SI value of the paper's dipole unit xi0, in e (= e um / um).
    xi_cs : float
        Channel-stop dipole along +z, in xi0 (paper: -14.3).
    xi_ck : float
        Magnitude of each of the two opposite in-plane clock dipoles straddling
        a row boundary, in xi0; positive values make a barrier (paper: 5).
    clock_separation : float
        Distance between the two clock dipoles of a barrier (um).
    barrier_height : float
        z of the barrier dipole plane (um).
    channel_depth : float
        Buried channel depth d_ch (um): collected charge Q gives a dipole
        p = -2 Q d_ch k at the pixel centre.
    collection_height : float or None
        Height (um) at which drift lines end and the landing pixel is read;
        None means ``channel_depth``.
    backside_images : bool
        Add one image of every barrier term across the backside plane.
    charge_cloud : float
        Lateral rms extent (um) of the collected charge in its potential
        well; 0 makes each pixel's charge one point dipole, otherwise it is
        spread over a 3 x 3 Gauss-Hermite grid of dipoles (exact for the
        cloud's moments up to fifth order), whose outer dipoles (sqrt(3) rms
        from the centre) must lie inside the pixel.
    charge_variance_parallel : float
        Extra variance (um^2) of the collected charge along the columns (y,
        the parallel transfer direction): the cloud's rms extents are
        ``charge_cloud`` along x and sqrt(charge_cloud^2 +
        charge_variance_parallel) along y. A packet held under its collecting
        phases can be longer along the column than across it, between the
        channel stops. A variance, not an extent, so that the a_ij move
        linearly with it from 0 (a fit can start there). The same rule
        (one dipole along x without ``charge_cloud``), inside the pixel.
    charge_images : int
        Number of images of collected-charge dipoles, nearest first
        (z = 2t, -2t, 4t, ...).
    bloom_stop : float or None
        Row boundary index of the bloom-stop (midline) implant, or None.
    xi_bs : float or None
        Bloom-stop dipole along +z in xi0; None means equal to ``xi_cs``.
    edge : float or None
        Column boundary index of the last channel stop at a sensor edge; the
        channel-stop grid exists only on the ``edge_side`` side of it.
    edge_side : int
        +1: the array lies at x >= edge; -1: at x <= edge.
    xi_guard : float
        Guard-ring dipole (in-plane, along +x pointing into the array for
        ``edge_side=+1``), in xi0. Only with ``edge``.
    guard_ring_offset : float
        Distance of the guard-ring dipole outside the last channel stop (um).
    column_overrides : sequence of (boundary, delta_xi)
        Extra channel-stop strength (xi0, along z) on given column boundaries.
    row_overrides : sequence of (boundary, delta_xi)
        Extra clock-barrier strength (xi0) on given row boundaries.
    row_shifts : sequence of (boundary, shift)
        Lithographic displacement (um, along y) of a row boundary's clock pair.
    truncations : sequence of (boundary, y_end, extends, delta_xi)
        Truncated extra channel-stop dipole on a column boundary, from row
        coordinate ``y_end`` (pixel units) towards ``extends`` (+1 or -1).
    """

    pixel_pitch: float = 10.0
    thickness: float = 100.0
    v_bss: float = -69.93
    front_potential: float = 0.0
    acceptor_density: float = 1e12
    xi0: float = 2952.0
    xi_cs: float = -14.3
    xi_ck: float = 5.0
    clock_separation: float = 0.1
    barrier_height: float = 0.0
    channel_depth: float = 0.368
    collection_height: float = 0.5
    backside_images: bool = True
    charge_images: int = 1
    charge_cloud: float = 0.0
    charge_variance_parallel: float = 0.0
    bloom_stop: float = None
    xi_bs: float = None
    edge: float = None
    edge_side: int = 1
    xi_guard: float = 0.0
    guard_ring_offset: float = 1.0
    column_overrides: tuple = field(default=())
    row_overrides: tuple = field(default=())
    row_shifts: tuple = field(default=())
    truncations: tuple = field(default=())

    def __post_init__(self):
        setf = object.__setattr__
        for f in dataclasses.fields(self):
            v = getattr(self, f.name)
            if f.name in ("backside_images",):
                if not isinstance(v, (bool, np.bool_)):
                    raise InputTypeError(f"parameter {f.name!r} must be True or False, got {v!r}")
                setf(self, f.name, bool(v))
            elif f.name in ("charge_images", "edge_side"):
                if isinstance(v, bool) or int(v) != v:
                    raise InputTypeError(f"parameter {f.name!r} must be an integer, got {v!r}")
                setf(self, f.name, int(v))
            elif f.name in ("column_overrides", "row_overrides", "row_shifts"):
                setf(self, f.name, _pairs(f.name, v, 2))
            elif f.name == "truncations":
                setf(self, f.name, _pairs(f.name, v, 4))
            elif v is None and f.name in ("collection_height", "bloom_stop", "xi_bs", "edge"):
                pass
            else:
                setf(self, f.name, _as_float(f.name, v))
        self._validate()

    def _validate(self):
        for name in ("pixel_pitch", "thickness", "channel_depth", "xi0", "clock_separation"):
            if getattr(self, name) <= 0:
                raise InputError(f"parameter {name!r} must be positive, got {getattr(self, name)}")
        if self.acceptor_density < 0:
            raise InputError(f"parameter 'acceptor_density' must be >= 0, got "
                             f"{self.acceptor_density}")
        if not self.charge_cloud >= 0:
            raise InputError(f"parameter 'charge_cloud' must be >= 0 um, got {self.charge_cloud}")
        if not self.charge_variance_parallel >= 0:
            raise InputError(f"parameter 'charge_variance_parallel' must be >= 0 um^2, got "
                             f"{self.charge_variance_parallel}")
        reach = math.sqrt(3.0) * self.cloud_extent_y  # the larger extent
        if reach >= self.pixel_pitch / 2:
            raise InputError(f"the charge cloud's outer dipoles (sqrt(3) x its rms extent, "
                             f"{reach:.3g} um) must lie inside the pixel (half pitch "
                             f"{self.pixel_pitch / 2:.3g} um)")
        if self.charge_images < 0:
            raise InputError(f"parameter 'charge_images' must be >= 0, got {self.charge_images}")
        if self.edge_side not in (1, -1):
            raise InputError(f"parameter 'edge_side' must be +1 or -1, got {self.edge_side}")
        zc = self.z_collect
        if not (self.barrier_height < zc < self.thickness):
            raise InputError(f"collection height {zc} um must lie between the barrier plane "
                             f"({self.barrier_height} um) and the backside ({self.thickness} um)")
        if self.clock_separation >= self.pixel_pitch:
            raise InputError("clock_separation must be smaller than pixel_pitch")
        for b, y_end, ext, dxi in self.truncations:
            if ext not in (1.0, -1.0):
                raise InputError(f"truncation 'extends' must be +1 or -1, got {ext}")
        # Building the backdrop checks full depletion.
        self.backdrop()

    @property
    def cloud_extent_y(self):
        """The charge cloud's rms extent along y (um)."""
        return math.sqrt(self.charge_cloud ** 2 + self.charge_variance_parallel)

    @property
    def z_collect(self):
        """Height (um) where drift lines end."""
        return self.channel_depth if self.collection_height is None else self.collection_height

    @classmethod
    def from_dict(cls, mapping):
        """Build from a mapping, rejecting unknown keys by name."""
        return strict_from_dict(cls, mapping, "sensor parameter")

    @classmethod
    def paper(cls, **changes):
        """Rasmussen 2015's model structure and nominal values (section 3),
        before any calibration: xi0 = 1000 e, channel depth 2 um, clock pair
        3 um apart, V_BSS = -50 V, drift lines ending at the channel depth."""
        return cls(**{**_PAPER, **changes})

    def to_dict(self):
        """Plain-Python dictionary (JSON serialisable)."""
        out = {}
        for f in dataclasses.fields(self):
            v = getattr(self, f.name)
            out[f.name] = [list(t) for t in v] if isinstance(v, tuple) else v
        return out

    def to_json(self):
        """JSON string of :meth:`to_dict`, keys sorted."""
        return json.dumps(self.to_dict(), sort_keys=True)

    def replace(self, **changes):
        """Copy with some parameters changed."""
        return dataclasses.replace(self, **changes)

    def backdrop(self):
        """The backdrop field term."""
        return BackdropField(self.v_bss, self.acceptor_density, self.thickness,
                             front_potential=self.front_potential)


class SensorModel:
    """Superposition of field terms describing a pixel array.

    Parameters
    ----------
    params : SensorParameters, optional
        Model parameters; defaults to the paper's fiducial geometry.
    charge : dict or None, optional
        Collected charge ``{(i, j): Q}`` in electrons per pixel.
    terms : list of FieldTerm, optional
        Extra terms to add (e.g. a :class:`~lsst_bfdrift.physics.fields.TabulatedBackdrop`
        together with ``replace_backdrop=True``).
    replace_backdrop : bool, optional
        Drop the parametric backdrop (use one passed in ``terms``).
    """

    def __init__(self, params=None, *, charge=None, terms=(), replace_backdrop=False):
        self.params = SensorParameters() if params is None else params
        if not isinstance(self.params, SensorParameters):
            raise InputTypeError("params must be a SensorParameters instance")
        self.charge = {} if charge is None else _check_charge(charge)
        self.extra_terms = list(terms)
        self.replace_backdrop = bool(replace_backdrop)
        self.terms = self._build_terms()

    # -- assembly ---------------------------------------------------------
    def barrier_terms(self):
        """Channel stops, clock barriers and fixed-pattern features (no images)."""
        P = self.params
        p, xi0, h = P.pixel_pitch, P.xi0, P.barrier_height
        terms = []
        m_cs = P.xi_cs * xi0
        if P.edge is None:
            terms.append(PeriodicDipoleGrid("y", p, 0.0, height=h, m_z=m_cs))
        else:
            x_edge = P.edge * p
            terms.append(HalfPeriodicDipoleGrid("y", p, x_edge, side=P.edge_side, height=h,
                                                m_z=m_cs))
            if P.xi_guard != 0.0:
                x_g = x_edge - P.edge_side * P.guard_ring_offset
                terms.append(LineDipole("y", x_g, height=h,
                                        m_perp=P.edge_side * P.xi_guard * xi0))
        half = 0.5 * P.clock_separation
        m_ck = P.xi_ck * xi0
        terms.append(PeriodicDipoleGrid("x", p, half, height=h, m_perp=m_ck))
        terms.append(PeriodicDipoleGrid("x", p, -half, height=h, m_perp=-m_ck))
        if P.bloom_stop is not None:
            xi_bs = P.xi_cs if P.xi_bs is None else P.xi_bs
            terms.append(LineDipole("x", P.bloom_stop * p, height=h, m_z=xi_bs * xi0))
        for b, dxi in P.column_overrides:
            terms.append(LineDipole("y", b * p, height=h, m_z=dxi * xi0))
        for b, dxi in P.row_overrides:
            terms.append(LineDipole("x", b * p + half, height=h, m_perp=dxi * xi0))
            terms.append(LineDipole("x", b * p - half, height=h, m_perp=-dxi * xi0))
        for b, shift in P.row_shifts:
            # move the pair: remove at nominal place, add at shifted place
            for sgn in (1, -1):
                terms.append(LineDipole("x", b * p + sgn * half, height=h, m_perp=-sgn * m_ck))
                terms.append(LineDipole("x", b * p + sgn * half + shift, height=h,
                                        m_perp=sgn * m_ck))
        for b, y_end, ext, dxi in P.truncations:
            terms.append(TruncatedLineDipole("y", b * p, y_end * p, extends=int(ext), height=h,
                                             m_z=dxi * xi0))
        return terms

    def charge_terms(self):
        """Point dipoles of the collected charge and their images."""
        if not self.charge:
            return []
        P = self.params
        ij = np.array(list(self.charge.keys()), dtype=float).reshape(-1, 2)
        q = np.array(list(self.charge.values()), dtype=float)
        keep = q != 0
        if not np.any(keep):
            return []
        x = (ij[keep, 0] + 0.5) * P.pixel_pitch
        y = (ij[keep, 1] + 0.5) * P.pixel_pitch
        pz = -2.0 * q[keep] * P.channel_depth
        sx, sy = P.charge_cloud, P.cloud_extent_y
        if sx > 0 or sy > 0:
            # 3-point Gauss-Hermite rule per axis with spread: offsets 0,
            # +-sqrt(3) s, weights 2/3, 1/6, 1/6 (one point on an axis without)
            rule = np.array([0.0, -1.0, 1.0]) * math.sqrt(3.0), np.array([4.0, 1.0, 1.0]) / 6.0
            ux, wx = (rule[0] * sx, rule[1]) if sx > 0 else (np.zeros(1), np.ones(1))
            uy, wy = (rule[0] * sy, rule[1]) if sy > 0 else (np.zeros(1), np.ones(1))
            ox, oy = np.meshgrid(ux, uy, indexing="ij")
            wxy = np.outer(wx, wy).ravel()
            x = (x[:, None] + ox.ravel()[None, :]).ravel()
            y = (y[:, None] + oy.ravel()[None, :]).ravel()
            pz = (pz[:, None] * wxy[None, :]).ravel()
        base = PointDipoles(x, y, pz, height=P.barrier_height)
        terms = [base]
        t = P.thickness
        for k in range(P.charge_images):
            n = k // 2 + 1
            z_img = 2 * n * t if k % 2 == 0 else -2 * n * t
            terms.append(PointDipoles(x, y, pz, height=P.barrier_height + z_img))
        return terms

    def _build_terms(self):
        P = self.params
        terms = [] if self.replace_backdrop else [P.backdrop()]
        barriers = self.barrier_terms()
        terms += barriers
        if P.backside_images:
            for b in barriers:
                img = b.mirrored(P.thickness)
                # A periodic grid's field decays as exp(-2 pi |dz| / p); its image
                # lies >= t above the silicon, where that is below exp(-2 pi t / p)
                # (~1e-27 for LSST), and the term's cutoff zeroes it anyway.
                if isinstance(img, PeriodicDipoleGrid) and \
                        P.thickness - P.barrier_height > img.cutoff * img.pitch:
                    continue
                terms.append(img)
        terms += self.charge_terms()
        terms += self.extra_terms
        return terms

    def with_charge(self, charge):
        """Copy of this model holding collected ``charge`` ``{(i, j): Q}`` (e)."""
        return SensorModel(self.params, charge=charge, terms=self.extra_terms,
                           replace_backdrop=self.replace_backdrop)

    @property
    def mirror_symmetric(self):
        """True when the model is symmetric under x -> -x and y -> -y about the
        centre of pixel (0, 0): no sensor edge, bloom stop, per-boundary
        override, shift or truncation, no extra terms, and charge in pixel
        (0, 0) alone (the periodic channel stops and clock barriers, the
        backdrop and the charge's images are symmetric)."""
        P = self.params
        return (P.edge is None and P.bloom_stop is None and not P.column_overrides
                and not P.row_overrides and not P.row_shifts and not P.truncations
                and not self.extra_terms and set(self.charge) <= {(0, 0)})

    # -- evaluation -------------------------------------------------------
    def field(self, x, y, z):
        """Total field (ex, ey, ez) in V/um at points (x, y, z) in um."""
        x, y, z = np.broadcast_arrays(np.asarray(x, float), np.asarray(y, float),
                                      np.asarray(z, float))
        ex = np.zeros(x.shape)
        ey = np.zeros(x.shape)
        ez = np.zeros(x.shape)
        for t in self.terms:
            fx, fy, fz = t.field(x, y, z)
            ex += fx
            ey += fy
            ez += fz
        return ex, ey, ez

    def pixel_of(self, x, y):
        """Nominal pixel indices (i, j) of lateral positions (um)."""
        p = self.params.pixel_pitch
        return np.floor(np.asarray(x) / p).astype(int), np.floor(np.asarray(y) / p).astype(int)

    def __repr__(self):
        return f"SensorModel({self.params!r}, charge={len(self.charge)} pixels)"


def _check_charge(charge):
    out = {}
    for key, q in dict(charge).items():
        key = tuple(int(k) for k in key)
        if len(key) != 2:
            raise InputError(f"charge keys must be (i, j) pixel indices, got {key!r}")
        q = float(q)
        if not math.isfinite(q):
            raise InputError(f"collected charge must be finite, got {q!r} at pixel {key}")
        out[key] = q
    return out
