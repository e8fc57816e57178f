"""The bearing description: what a user knows of a bearing from its drawings and datasheets.

One immutable :class:`Bearing` holds the facts every other part reads (pole angle,
turns, pole face, nominal gap, back-up clearance, current limit, polarity, iron
path, calibration tolerances, the lamination's B-H curve).  The force model, the
effects, the virtual rig, the design and the diagnosis take it from here; no other
module types these numbers.  :data:`PAPER_BEARING` is the seed paper's rig and the
default everywhere.  Files follow ``DATA-CONTRACT.md`` section 4 (TOML, read by
:meth:`Bearing.from_toml`).

Conventions (contract section 1 and 4): ``turns_per_pole`` is ``N`` of one pole
coil, a horseshoe carries ``2 N``; the ideal horseshoe circuit (two gaps in series,
iron ignored) gives the gap flux density ``B = MU_0 (2 N) i / (2 g)`` and Eq. 3's
constant ``k = 0.25 MU_0 A (2 N)^2 cos(alpha) * lamination`` [N m^2/A^2]
(Schweitzer & Maslen (eds.), *Magnetic Bearings*, Springer 2009, eq. 4.13, p. 85).
"""

from __future__ import annotations

import dataclasses
import difflib
import math
import sys
import tomllib
from pathlib import Path

MU_0 = 4e-7 * math.pi
"""Magnetic permeability of vacuum (air) [H/m]."""

AXES = ("v", "w")
"""Axis names in index order: rows with ``axis == AXES[j]`` use parameter ``j``."""

POLARITIES = ("NNSS", "NSNS")


class BearingError(ValueError):
    """A bearing description that cannot be used; the message names the file and key."""


TOLERANCE_DISTRIBUTIONS = ("uniform", "normal")
"""How a bearing description's calibration tolerances are read (:attr:`Bearing.tolerance_distribution`)."""


@dataclasses.dataclass(frozen=True)
class Bearing:
    """An 8-pole heteropolar radial bearing as drawn (SI units).

    Attributes
    ----------
    name : str
    pole_angle : float
        ``alpha``, pole axis to horseshoe axis [rad] (the paper's 22.5 deg).
    turns_per_pole : float
        Turns ``N`` of one pole coil; a horseshoe has ``2 N``.
    pole_area : float
        One pole face, width x stack length [m^2].
    pole_width : float
        Pole face width [m] (the fringing estimate needs width and length; the length is
        ``pole_area / pole_width``).
    nominal_gap : float
        Radial air gap as drawn [m].
    backup_clearance : float
        Radial distance rotor to back-up bearing with the rotor centred [m].
    max_current : float
        Coil current limit [A].
    polarity : str
        Pole polarities around the stator, ``"NNSS"`` or ``"NSNS"``.
    iron_path : float
        Mean iron path of one horseshoe circuit [m] (the paper's ``b_th``).
    lamination : float
        Nominal lamination (stacking) coefficient in Eq. 3 [-].
    position_gain_tolerance, current_gain_tolerance : float
        Relative calibration tolerances of the position sensors and current channels (0.0025 and 0.001).
    current_offset_tolerance : float
        Calibration tolerance of each current channel's zero [A] (1 mA).
    load_scale_tolerance : float
        Relative tolerance of the known loads (masses, gravity, lever; 0.001).
    tolerance_distribution : str
        How a tolerance ``a`` is read (the GUM, JCGM 100 4.3.7): ``"uniform"``, the error lies within ±a, all values
        alike (standard uncertainty ``a / sqrt(3)``, the reading of a data-sheet limit); ``"normal"``, ``a`` is
        itself a standard uncertainty (a calibration certificate's).
    bore_diameter : float
        Stator bore [m].
    rotor_mass : float
        Share of the rotor's weight this bearing carries [kg] (the virtual rig's static load, carried by
        axes at ±45° from vertical; 1 kg on the paper's rig, an assumption: the paper does not print it).
    b_curve, h_curve : tuple of float
        Lamination B-H curve, B [T] ascending from 0 or above, H [A/m] not falling; empty when unknown.  A table
        that starts above B = 0 (a data sheet's from 0.1 T) is completed with the origin, where soft iron has
        H = 0; H > 0 at B = 0 is kept (the curve, odd in B, then steps at zero flux).
    extra_keys : tuple of str
        Keys of the file that ambfit does not use (the contract allows more keys; a key that looks
        like a misspelt known one is an error instead).

    Examples
    --------
    >>> b = PAPER_BEARING
    >>> round(b.force_constant() * 1e6, 4)     # k of Eq. 3 [N m^2/A^2] x 1e6
    3.4452
    >>> round(b.flux_density(3.0, b.nominal_gap), 2)   # ideal-circuit B at 3 A, centred [T]
    1.19
    """

    name: str = "paper rig"
    pole_angle: float = math.radians(22.5)
    turns_per_pole: float = 240.0
    pole_area: float = 54.2e-6
    pole_width: float = 5.0e-3
    nominal_gap: float = 762e-6
    backup_clearance: float = 60e-6
    max_current: float = 3.0
    polarity: str = "NNSS"
    iron_path: float = 0.08
    lamination: float = 0.95
    position_gain_tolerance: float = 0.0025
    current_gain_tolerance: float = 0.001
    current_offset_tolerance: float = 1e-3
    load_scale_tolerance: float = 0.001
    tolerance_distribution: str = "uniform"
    bore_diameter: float = 35e-3
    rotor_mass: float = 1.0
    b_curve: tuple = ()
    h_curve: tuple = ()
    extra_keys: tuple = ()

    def __post_init__(self):
        if self.polarity not in POLARITIES:
            raise BearingError(f"polarity must be one of {', '.join(POLARITIES)}, got {self.polarity!r}")
        for name in ("pole_angle", "turns_per_pole", "pole_area", "pole_width", "nominal_gap", "max_current",
                     "iron_path", "lamination"):
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and math.isfinite(value) and value > 0):
                raise BearingError(f"{name} must be a positive number, got {value!r}")
        if not (isinstance(self.rotor_mass, (int, float)) and math.isfinite(self.rotor_mass) and self.rotor_mass >= 0):
            raise BearingError(f"rotor_mass must be a number >= 0 [kg], got {self.rotor_mass!r}")
        if not self.pole_angle < math.pi / 2:   # each pole of a pair leans off the axis by less than a right angle
            raise BearingError(f"pole_angle_deg must lie between 0 and 90 (each pole's angle from its axis: 22.5 on "
                               f"an 8-pole bearing), got {math.degrees(self.pole_angle):g}")
        if not self.lamination <= 1:
            raise BearingError(f"lamination (the iron's stacking factor) must lie in (0, 1], got {self.lamination!r}")
        if self.tolerance_distribution not in TOLERANCE_DISTRIBUTIONS:
            raise BearingError(f"tolerance_distribution must be one of {', '.join(TOLERANCE_DISTRIBUTIONS)}, got "
                               f"{self.tolerance_distribution!r}")
        if not (isinstance(self.current_offset_tolerance, (int, float)) and 0 <= self.current_offset_tolerance
                <= self.max_current):
            raise BearingError(f"current_offset_tolerance_mA must lie between 0 and the current limit, got "
                               f"{self.current_offset_tolerance * 1e3!r}")
        for name in ("position_gain_tolerance", "current_gain_tolerance", "load_scale_tolerance"):
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and math.isfinite(value) and 0 <= value < 1):
                raise BearingError(f"{name} must be a fraction in [0, 1) (0.001 is 0.1 %), got {value!r}")
        if len(self.b_curve) or len(self.h_curve):
            b, h = _completed_bh(self.b_curve, self.h_curve, names=("b_curve", "h_curve"))
            object.__setattr__(self, "b_curve", b)
            object.__setattr__(self, "h_curve", h)

    # --- derived quantities -------------------------------------------------------------------------------

    @property
    def cos_alpha(self) -> float:
        return math.cos(self.pole_angle)

    @property
    def sin_alpha(self) -> float:
        return math.sin(self.pole_angle)

    @property
    def horseshoe_turns(self) -> float:
        """Turns of one horseshoe's coils in series, ``2 N``."""
        return 2.0 * self.turns_per_pole

    @property
    def pole_length(self) -> float:
        """Axial stack length of a pole face [m]."""
        return self.pole_area / self.pole_width

    def force_constant(self, lamination: float | None = None) -> float:
        """Eq. 3's ``k = 0.25 MU_0 A (2 N)^2 cos(alpha) * lamination`` [N m^2/A^2] (default: the nominal lamination)."""
        lam = self.lamination if lamination is None else lamination
        return 0.25 * MU_0 * self.pole_area * self.horseshoe_turns**2 * self.cos_alpha * lam

    def flux_density(self, i, g):
        """Ideal-circuit gap flux density ``MU_0 (2 N) i / (2 g)`` [T] for current ``i`` [A] and gap ``g`` [m].

        Works on floats, numpy and JAX arrays alike.
        """
        return MU_0 * self.horseshoe_turns * i / (2.0 * g)

    def load_capacity(self, current: float | None = None) -> float:
        """Force of one coil at ``current`` (default the current limit), rotor centred at the nominal gap [N]."""
        i = self.max_current if current is None else current
        return self.force_constant() * i**2 / self.nominal_gap**2

    def with_(self, **changes) -> Bearing:
        """A copy with some facts changed (SI units)."""
        return dataclasses.replace(self, **changes)

    # --- files --------------------------------------------------------------------------------------------

    def to_dict(self) -> dict:
        """The description in the contract's keys (section 4, units as in their names): what a model file
        records so that a reader can judge it against the bearing it was fitted with (:meth:`from_dict` reads
        it back)."""
        out = {"name": self.name, "pole_angle_deg": math.degrees(self.pole_angle),
               "turns_per_pole": self.turns_per_pole, "pole_area_mm2": self.pole_area * 1e6,
               "pole_width_mm": self.pole_width * 1e3, "nominal_gap_um": self.nominal_gap * 1e6,
               "backup_clearance_um": self.backup_clearance * 1e6, "max_current_A": self.max_current,
               "polarity": self.polarity, "iron_path_mm": self.iron_path * 1e3, "lamination": self.lamination,
               "position_gain_tolerance": self.position_gain_tolerance,
               "current_gain_tolerance": self.current_gain_tolerance,
               "current_offset_tolerance_mA": self.current_offset_tolerance * 1e3,
               "load_scale_tolerance": self.load_scale_tolerance, "tolerance_distribution": self.tolerance_distribution,
               "bore_diameter_mm": self.bore_diameter * 1e3,
               "rotor_mass_kg": self.rotor_mass}
        if self.b_curve:
            out["material"] = {"B_T": list(self.b_curve), "H_A_per_m": list(self.h_curve)}
        return out

    @classmethod
    def from_toml(cls, path: str | Path) -> Bearing:
        """Read a bearing description (contract section 4); missing keys take the paper rig's values.

        Raises
        ------
        BearingError
            Unreadable file, unknown key or a value of the wrong kind; the message names the file and key.
        """
        path = Path(path)
        try:
            with open(path, "rb") as f:
                d = tomllib.load(f)
        except IsADirectoryError:
            raise BearingError(f"{path}: is a directory, not a bearing description (TOML)") from None
        except OSError as exc:
            raise BearingError(f"{path}: cannot read the bearing description ({exc.strerror})") from None
        except tomllib.TOMLDecodeError as exc:
            raise BearingError(f"{path}: not valid TOML ({exc})") from None
        except RecursionError:
            raise BearingError(f"{path}: not a bearing description (its tables or arrays nest too deeply to "
                               "read)") from None
        except ValueError as exc:              # an integer beyond sys.get_int_max_str_digits
            raise BearingError(f"{path}: not a bearing description ({exc.args[0].split(';')[0]})") from None
        except UnicodeDecodeError:             # a binary file: TOML is UTF-8 text
            raise BearingError(f"{path}: not a TOML file (binary content, not UTF-8 text)") from None
        return cls.from_dict(d, source=str(path))

    @classmethod
    def from_dict(cls, d: dict, *, source: str = "bearing description") -> Bearing:
        """A bearing from the contract's keys (units as in their names)."""
        d = dict(d)
        scale = {"pole_angle_deg": ("pole_angle", math.radians), "turns_per_pole": ("turns_per_pole", float),
                 "pole_area_mm2": ("pole_area", lambda v: v * 1e-6),
                 "pole_width_mm": ("pole_width", lambda v: v * 1e-3),
                 "nominal_gap_um": ("nominal_gap", lambda v: v * 1e-6),
                 "backup_clearance_um": ("backup_clearance", lambda v: v * 1e-6),
                 "max_current_A": ("max_current", float), "iron_path_mm": ("iron_path", lambda v: v * 1e-3),
                 "lamination": ("lamination", float), "position_gain_tolerance": ("position_gain_tolerance", float),
                 "current_gain_tolerance": ("current_gain_tolerance", float),
                 "current_offset_tolerance_mA": ("current_offset_tolerance", lambda v: v * 1e-3),
                 "load_scale_tolerance": ("load_scale_tolerance", float),
                 "bore_diameter_mm": ("bore_diameter", lambda v: v * 1e-3),
                 "rotor_mass_kg": ("rotor_mass", float)}
        kw = {}
        if "name" in d:
            kw["name"] = str(d.pop("name"))
        if "polarity" in d:
            kw["polarity"] = str(d.pop("polarity")).upper()
        if "tolerance_distribution" in d:
            kw["tolerance_distribution"] = str(d.pop("tolerance_distribution")).lower()
        material = d.pop("material", None)
        extra = []
        for key in list(d):
            if key not in scale:
                near = difflib.get_close_matches(key, [*scale, "name", "polarity", "material", "tolerance_distribution"],
                                                 n=1, cutoff=0.75)
                if near:
                    raise BearingError(f"{source}: unknown key {key!r}; did you mean {near[0]!r}? "
                                       f"(keys carry their unit: {', '.join(sorted(scale))})")
                extra.append(key)   # the contract allows more keys
                continue
            field, conv = scale[key]
            value = d.pop(key)
            if isinstance(value, bool) or not isinstance(value, (int, float)):
                raise BearingError(f"{source}: {key} must be a number, got {short_repr(value)}")
            try:
                kw[field] = float(conv(value))
            except OverflowError:            # an integer beyond any float (a 400-digit number)
                raise BearingError(f"{source}: {key} = {short_repr(value)} is beyond any physical value") from None
        if "pole_area" in kw and "pole_width" not in kw:
            kw["pole_width"] = math.sqrt(kw["pole_area"])   # no width given: a square face
        if material is not None:
            kw.update(_material(material, source))
        kw["extra_keys"] = tuple(extra)
        try:
            return cls(**kw)
        except BearingError as exc:
            raise BearingError(f"{source}: {exc}") from None


def short_repr(value) -> str:
    """``repr(value)`` cut to 60 characters (a 5000-digit number or a long list stays readable)."""
    try:
        text = repr(value)
    except ValueError:                        # an integer too long for repr (sys.get_int_max_str_digits)
        return f"an integer of more than {sys.get_int_max_str_digits()} digits"
    return text if len(text) <= 60 else text[:57] + "..."


def _material(material, source: str) -> dict:
    try:
        b, h = material["B_T"], material["H_A_per_m"]
    except (KeyError, TypeError):
        raise BearingError(f"{source}: [material] needs numeric lists B_T and H_A_per_m") from None
    try:
        b, h = _completed_bh(b, h)
    except BearingError as exc:
        raise BearingError(f"{source}: [material] {exc}") from None
    return {"b_curve": b, "h_curve": h}


def _completed_bh(b, h, names=("B_T", "H_A_per_m")) -> tuple[tuple, tuple]:
    """A lamination's B-H table as the magnetic circuit uses it (odd in B, a monotone cubic through the table), as
    tuples of floats: B ascending from 0 or above, H not falling.  A table that starts above B = 0 (a data sheet's
    from 0.1 T) is completed with the origin, where soft iron has H = 0; one that gives H > 0 at B = 0 is kept (the
    odd curve then steps by twice that H at zero flux).  ``names``: the two lists' names in messages."""
    nb, nh = names
    try:
        b, h = tuple(float(v) for v in b), tuple(float(v) for v in h)
    except (TypeError, ValueError, OverflowError):
        raise BearingError(f"{nb} and {nh} must be lists of numbers") from None
    if not all(map(math.isfinite, b + h)):
        raise BearingError(f"{nb} and {nh} must be finite numbers")
    if len(b) != len(h) or len(b) < 2:
        raise BearingError(f"{nb} and {nh} must have the same length, at least 2, got {len(b)} and {len(h)}")
    bad = next((k for k in range(1, len(b)) if not b[k] > b[k - 1]), None)
    if bad is not None:
        raise BearingError(f"{nb} must ascend, got {b[bad - 1]!r} then {b[bad]!r} T")
    if b[0] < 0 or h[0] < 0:
        raise BearingError(f"the B-H curve is given for B >= 0 (it is extended to negative B as an odd function), "
                           f"got B = {b[0]!r} T, H = {h[0]!r} A/m first")
    bad = next((k for k in range(1, len(h)) if h[k] < h[k - 1]), None)
    if bad is not None:
        raise BearingError(f"{nh} must not fall as {nb} rises (soft iron's B-H curve is monotone), got "
                           f"H = {h[bad - 1]!r} then {h[bad]!r} A/m at B = {b[bad - 1]!r}, {b[bad]!r} T")
    if b[0] > 0:
        if h[0] <= 0:
            raise BearingError(f"the B-H table starts at B = {b[0]!r} T with H = {h[0]!r} A/m: give H > 0 there, or "
                               "the curve from B = 0")
        b, h = (0.0,) + b, (0.0,) + h
    return b, h


def _paper_bearing() -> Bearing:
    # The paper prints the load capacity (53.4 N at the 3.0 A saturation current, rotor centred), not the
    # winding: the pole face is the one that gives that capacity with 2 x 240 turns and lamination 0.95.
    k = 53.4 * Bearing.nominal_gap**2 / Bearing.max_current**2
    unit = Bearing().with_(pole_area=1.0).force_constant()
    return Bearing(pole_area=k / unit)


PAPER_BEARING = _paper_bearing()
"""The seed paper's rig (its "Test Apparatus" section): 35 mm bore, 762 µm nominal radial gap,
poles at 22.5 deg, a 60 µm back-up clearance (the ±20 µm pairs are "one third" of it), 3.0 A
saturation current and 53.4 N load capacity there, i.e. ``k`` = 3.445e-6 N m²/A².  Turns and
pole face are not printed; 2 x 240 turns per horseshoe on a 5 mm x 10.84 mm face with a 0.95
lamination coefficient give that ``k`` and about 1.2 T at 3.0 A.  The 80 mm iron path is an
assumption (stator yoke plus rotor path of a 35 mm bore)."""
