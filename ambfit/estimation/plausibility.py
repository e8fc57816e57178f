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
    """One implausible quantity: what, its value, what the bearing allows, and the likely cause."""

    quantity: str
    value: float
    expected: str
    cause: str

    def __str__(self) -> str:
        return f"{self.quantity} = {self.value:.4g} is implausible for this bearing ({self.expected}): {self.cause}"

    def to_json(self) -> dict:
        return dataclasses.asdict(self)


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


def check_data(df: pd.DataFrame, bearing: Bearing) -> list[Flag]:
    """Flags for the readings themselves: loads beyond the load capacity, currents beyond the coil limit,
    positions too small to be micrometres."""
    flags = []
    cap = bearing.load_capacity()
    if "load_N" in df.columns:
        load = df["load_N"].to_numpy(float)
        big = np.abs(load) > LOAD_FACTOR * cap
        if big.any():
            r = int(np.nanargmax(np.where(big, np.abs(load), -np.inf)))
            everywhere = big.sum() == np.isfinite(load).sum()
            flags.append(Flag(f"load_N (row {file_rows(df)[r]}, {int(big.sum())} row(s) in all)", float(load[r]),
                              f"|load| up to {LOAD_FACTOR:g} x the load capacity {cap:.3g} N",
                              "every known load is too large: loads in mN or grams instead of N, or a bearing "
                              "description that is not this bearing's" if everywhere else
                              "a typing error in load_N on these rows"))
    limit = CURRENT_FACTOR * bearing.max_current
    for col in ("i_top_A", "i_bottom_A"):
        cur = df[col].to_numpy(float)
        over = cur > limit
        if over.any():
            r = int(np.argmax(cur))
            ratio = cur[r] / bearing.max_current
            flags.append(Flag(f"{col} (row {file_rows(df)[r]}, {int(over.sum())} row(s) in all)", float(cur[r]),
                              f"up to {CURRENT_FACTOR:g} x the coil limit {bearing.max_current:g} A",
                              "currents given in mA instead of A" if ratio > 100 else
                              "a current above the coil limit: a wrong bearing description (max_current_A) or a "
                              "saturated amplifier"))
            break
    pos = np.abs(np.concatenate([df["v_um"].to_numpy(float), df["w_um"].to_numpy(float)]))
    if len(pos) and 0 < np.max(pos) < 1e-3:
        flags.append(Flag("positions [µm]", float(np.max(pos)), "set-points of micrometres to tens of micrometres",
                          "every position is below 0.001 µm: positions given in metres (or mm) instead of µm"))
    return flags
