"""Plausibility against the bearing description: answers a drawing rules out, with their likely cause.

A fit can converge, be well conditioned and fit its data, and still be wrong by a
factor of a million because the file used mA for A, or by a sign because the load
was given as the force on the bearing instead of the force the bearing supplies.
The bearing description (``Bearing``, DATA-CONTRACT.md section 4) says what a
result may look like:

force constant
    ``k = MU_0 A (2 N)^2 cos(alpha) / 4 * f`` with a lamination factor ``f`` in
    ``K_FACTOR_RANGE``: stacking (0.9-0.98) times the loss to leakage, fringing and
    iron reluctance (Schweitzer & Maslen, *Magnetic Bearings*, 2009, sec. 3.2-3.4,
    pp. 73-84, quote 0.7-1.0 for radial bearings; fringing can lift it a little).
    The paper's rig gives 0.95, the 8-pole FEM bearing 0.89-0.92.
effective gap
    within ``GAP_RANGE`` of the drawn gap: fringing makes it smaller, iron
    reluctance larger, by tens of percent at most (the FEM bearing: 0.92).
effective origin
    within half the drawn gap of the sensor zero.
loads and currents
    within ``LOAD_FACTOR`` of the load capacity and ``CURRENT_FACTOR`` of the coil
    current limit.

Each failed check is a :class:`Flag` naming the quantity, its value, the range the
bearing allows and the likely cause (a unit or sign mistake when the ratio says so,
else a wrong bearing description).  The command line exits 3 on any flag unless
``--accept-implausible``.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pandas as pd

from ambfit.data import file_rows
from ambfit.physics.bearing import AXES, Bearing

K_FACTOR_RANGE = (0.4, 1.15)
"""Lamination factor ``k / (MU_0 A (2N)^2 cos(alpha) / 4)`` a real radial bearing can have."""

K_AXIS_RATIO = 1.25
"""Largest ratio of the two axes' force constants: the bearing description draws both axes alike (the same poles,
turns and iron), so manufacturing and the axes' different effective gaps part them by a few per cent; loads
halved or doubled on one axis (a unit or a lever mistake) part them twofold."""

GAP_RANGE = (0.7, 1.3)
"""Effective gap over the drawn gap."""

ORIGIN_RANGE = 0.5
"""Largest |effective origin| as a fraction of the drawn gap."""

LOAD_FACTOR = 1.5
"""Largest |known load| as a multiple of the bearing's load capacity (one coil at the current limit)."""

CURRENT_FACTOR = 1.2
"""Largest coil current as a multiple of the coil current limit."""


@dataclasses.dataclass(frozen=True)
class Flag:
    """One implausible quantity: what, its value, what the bearing allows, and the likely cause; for a flag on
    the readings also the file, the row (data rows from 1) and the column of the value shown."""

    quantity: str
    value: float
    expected: str
    cause: str
    file: str | None = None
    row: int | None = None
    column: str | None = None

    def __str__(self) -> str:
        where = [w for w in (self.file, None if self.row is None else f"row {self.row} (line {self.row + 1})",
                             None if self.column is None else f"column {self.column!r}") if w is not None]
        text = f"{self.quantity} = {self.value:.4g} is implausible for this bearing ({self.expected}): {self.cause}"
        return ", ".join(where) + ": " + text if where else text

    def to_json(self) -> dict:
        return {k: v for k, v in dataclasses.asdict(self).items() if v is not None or k in ("quantity", "value")}


def _decades(ratio: float) -> int:
    """The nearest power of ten of a positive ratio, when the ratio is within a factor 2 of it (else 0)."""
    if not (ratio > 0 and math.isfinite(ratio)):
        return 0
    n = round(math.log10(ratio))
    return n if n != 0 and abs(math.log10(ratio) - n) < math.log10(2.0) else 0


def _k_cause(factor: float, bearing: Bearing) -> str:
    if factor < 0:
        return ("a negative force constant: the sign of load_N is flipped (it is the force the bearing supplies "
                "to the rotor along +axis, so the rotor weight share is positive on an axis pointing up), or the "
                "top and bottom current columns are swapped")
    n = _decades(factor)
    causes = {-6: "currents given in mA instead of A (k scales as 1/i^2)",
              6: "currents given in kA instead of A, or a bearing description with 1000x too many turns",
              3: "loads given in mN instead of N (k scales with the load)",
              -3: "loads given in kN instead of N, or currents in a unit about 30x too small",
              -12: "positions and gap read in a unit 1e6 too small (metres for µm?)",
              12: "positions and gap read in a unit 1e6 too large"}
    if n in causes:
        return causes[n]
    return (f"the data or the bearing description are inconsistent (check the turns per pole {bearing.turns_per_pole}, "
            f"pole area {bearing.pole_area * 1e6:.4g} mm² and the units of currents and loads)")


def check_result(values: dict[str, float], bearing: Bearing) -> list[Flag]:
    """Flags for fitted parameters (SI units, internal names ``g_v0``, ``v0``, ``k_v``, ...)."""
    flags = []
    k_geom = bearing.force_constant(1.0)
    lo, hi = K_FACTOR_RANGE
    g_lo, g_hi = GAP_RANGE
    nominal = bearing.nominal_gap
    kv, kw = values.get("k_v"), values.get("k_w")
    if kv is not None and kw is not None and math.isfinite(kv) and math.isfinite(kw) and kv > 0 and kw > 0 \
            and not 1 / K_AXIS_RATIO <= kv / kw <= K_AXIS_RATIO:
        flags.append(Flag("k_v / k_w", kv / kw, f"within {1 / K_AXIS_RATIO:.2f}-{K_AXIS_RATIO:.2f} on a bearing drawn "
                          "alike on both axes", "the known loads of one axis in another unit or scale (a lever arm, "
                          "grams, a halved or doubled load), or a current channel of one axis mis-scaled"))
    for ax in AXES:
        k = values.get(f"k_{ax}")
        if k is not None and math.isfinite(k):
            f = k / k_geom
            if not lo <= f <= hi:
                flags.append(Flag(f"k_{ax}", k, f"{lo * k_geom:.3g} to {hi * k_geom:.3g} N·m²/A², lamination factor "
                                  f"{lo}-{hi}; this is {f:.3g}", _k_cause(f, bearing)))
        g = values.get(f"g_{ax}0")
        if g is not None and math.isfinite(g) and not g_lo * nominal <= g <= g_hi * nominal:
            flags.append(Flag(f"g_{ax}0 [µm]", g * 1e6, f"{g_lo:g}-{g_hi:g} x the drawn {nominal * 1e6:.4g} µm; "
                              f"this is {g / nominal:.2f} x", _gap_cause(g / nominal)))
        x0 = values.get(f"{ax}0")
        if x0 is not None and math.isfinite(x0) and abs(x0) > ORIGIN_RANGE * nominal:
            flags.append(Flag(f"{ax}0 [µm]", x0 * 1e6, f"within ±{ORIGIN_RANGE * nominal * 1e6:.4g} µm (half the "
                              "drawn gap) of the sensor zero", "a position sensor offset or unit error, or too few "
                              "positions to separate origin from gap"))
    return flags


def _gap_cause(ratio: float) -> str:
    if ratio <= 0:
        return "a closed pole gap: the fit is not physical (too little data or a sign error in the positions)"
    if _decades(ratio) != 0:
        return f"the position unit is off by 10^{_decades(ratio)} (µm expected)"
    return ("not an effect a real bearing has: positions in the wrong unit, noise larger than the perturbation "
            "(too small a bias step or too few readings), or the bearing description (nominal_gap_um) is not this "
            "bearing's")


TINY_POSITION_UM = 0.01
"""Largest |position| [µm] of a file whose positions are all this small: a perturbation protocol moves the rotor by
micrometres (and sensor noise alone is ~0.1 µm), so positions in metres (or mm) typed into a µm column."""

SMALL_POSITION_UM = 1.0
"""Largest |position| [µm] of a file whose rotor clearly moved (its positions spread over many times their noise,
or its set-points are not all zero) yet never by a micrometre: no perturbation protocol moves that little, so
positions in mm typed into a µm column (a thousand times too small)."""

MOVED_NOISE = 20.0
"""A spread of the positions beyond this many of their standard deviations (``v_std_um``) is a rotor that moved."""

SPAN_FACTOR = 1.5
"""Largest spread of one position column over the file, as a multiple of twice the back-up clearance (the rotor
cannot move further, whatever the sensor's zero)."""

CURRENT_STD_FACTOR = 0.1
"""Largest current standard error as a fraction of the coil current limit (a DAQ averages to mA or better)."""


def check_data(df: pd.DataFrame, bearing: Bearing, source: str | None = None) -> list[Flag]:
    """Flags for the readings themselves, judged against the bearing description: loads beyond what the bearing
    can lift (``LOAD_FACTOR`` x its load capacity ``k (i_max / g)^2``), currents beyond its coil limit, positions
    too small to be micrometres or spread beyond the back-up clearance, current errors as large as currents.
    Each names the file (``source``), the row and column of the worst value and the likely unit mistake."""
    rows = file_rows(df)
    flags = []

    def flag(column, mask, values, expected, cause, key=None):
        """A flag on ``column``, showing the value of the masked row with the largest |key| (default |value|)."""
        r = int(np.nanargmax(np.where(mask, np.abs(values if key is None else key), -np.inf)))
        flags.append(Flag(f"{column} ({int(mask.sum())} row(s) in all)", float(values[r]), expected, cause,
                          source, int(rows[r]), column))

    cap = bearing.load_capacity()
    if "load_N" in df.columns:
        load = df["load_N"].to_numpy(float)
        big = np.abs(load) > LOAD_FACTOR * cap
        if big.any():
            ratio = np.nanmax(np.abs(load[big])) / cap
            everywhere = big.sum() == np.isfinite(load).sum()
            flag("load_N", big, load, f"|load| up to {LOAD_FACTOR:g} x the load capacity {cap:.3g} N "
                 f"(one coil at {bearing.max_current:g} A); this is {ratio:.3g} x", _load_cause(ratio, everywhere))
    limit = CURRENT_FACTOR * bearing.max_current
    for col in ("i_top_A", "i_bottom_A", "bias_A"):
        if col in df.columns:
            cur = df[col].to_numpy(float)
            over = cur > limit
            if over.any():
                ratio = np.nanmax(cur) / bearing.max_current
                flag(col, over, cur, f"up to {CURRENT_FACTOR:g} x the coil limit {bearing.max_current:g} A; this is "
                     f"{ratio:.3g} x", "currents given in mA instead of A" if ratio > 100 else
                     "a current above the coil limit: a wrong bearing description (max_current_A) or a saturated "
                     "amplifier")
    for col in ("i_top_std_A", "i_bottom_std_A"):
        if col in df.columns:
            std = df[col].to_numpy(float)
            big = std > CURRENT_STD_FACTOR * bearing.max_current
            if big.any():
                flag(col, big, std, f"below {CURRENT_STD_FACTOR:g} x the coil limit {bearing.max_current:g} A",
                     "current standard errors given in mA instead of A")
    moved = any(col in df.columns and np.nanmax(np.abs(df[col].to_numpy(float)), initial=0.0) > 0
                for col in ("v_set_um", "w_set_um"))
    for col in ("v_um", "w_um", "v_set_um", "w_set_um"):
        if col not in df.columns:
            continue
        x = df[col].to_numpy(float)
        largest = np.nanmax(np.abs(x), initial=0.0)
        if largest < TINY_POSITION_UM and (largest > 0 or (moved and col in ("v_um", "w_um"))):
            flag(col, np.isfinite(x), x, f"set-points of micrometres to tens of micrometres; every |{col}| is below "
                 f"{TINY_POSITION_UM:g} µm", "positions given in metres (or mm) instead of µm")
        elif TINY_POSITION_UM <= largest < SMALL_POSITION_UM and _moved(df, col, x, moved):
            flag(col, np.isfinite(x), x, f"positions of micrometres to tens of micrometres; the rotor moved, yet every "
                 f"|{col}| is below {SMALL_POSITION_UM:g} µm", "positions given in mm instead of µm (1000 times "
                 "too small)")
        span, room = np.nanmax(x, initial=0.0) - np.nanmin(x, initial=0.0), 2 * bearing.backup_clearance * 1e6
        if span > SPAN_FACTOR * room:
            flag(col, np.isfinite(x), x, f"a spread of at most twice the back-up clearance "
                 f"{bearing.backup_clearance * 1e6:.4g} µm (x {SPAN_FACTOR:g}); these spread over {span:.4g} µm "
                 "(the value shown: the furthest from their median)", "positions in a unit smaller than µm (e.g. "
                 "0.1 µm counts), or a bearing description with another back-up clearance (backup_clearance_um)",
                 key=x - np.nanmedian(x))
    return flags


def _moved(df: pd.DataFrame, col: str, x: np.ndarray, set_points: bool) -> bool:
    """Whether position column ``col`` shows a rotor that moved: set-points not all zero, or a spread beyond
    :data:`MOVED_NOISE` standard deviations of its std column (a rotor held still spreads over a few)."""
    if set_points:
        return True
    std = f"{col[0]}_std_um"
    if std not in df.columns:
        return False
    s = np.nanmedian(df[std].to_numpy(float))
    return bool(np.isfinite(s) and s > 0 and np.nanmax(x) - np.nanmin(x) > MOVED_NOISE * s)


def _load_cause(ratio: float, everywhere: bool) -> str:
    if not everywhere:
        return "a typing error in load_N on these rows (or a unit mistake on them only)"
    n = _decades(ratio) or int(math.floor(math.log10(ratio)))
    beyond = f"; {n} orders of magnitude beyond what the bearing can lift" if n >= 1 else ""
    return (f"every known load is too large: loads given in mN, or masses in grams, instead of N{beyond}; or a "
            "bearing description that is not this bearing's")
