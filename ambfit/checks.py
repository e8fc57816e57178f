"""Range checks of a contract table: values no reading can have, whatever the bearing.

:mod:`ambfit.data` runs them on every file it reads (each problem names file, row, column and value, through
its problem sink); what a particular bearing rules out (currents beyond its coil limit, loads beyond what it can
lift) is judged by :mod:`ambfit.estimation.plausibility`.
"""

from __future__ import annotations

import pandas as pd

CURRENTS = ("bias_A", "i_top_A", "i_bottom_A")
STD_COLUMNS = ("i_top_std_A", "i_bottom_std_A", "v_std_um", "w_std_um")

MAX_CURRENT_A = 1e4
"""Currents at least this large [A] are input errors, not readings (squared they overflow the force law);
smaller ones beyond the bearing's coil limit are judged by :mod:`ambfit.estimation.plausibility`."""

ZERO_CURRENT_NOISE_A = 3e-3
"""A measured coil current slightly below 0 is a zero current read through its sensor's noise: accepted down to
-5 times the row's std column, or -3 mA without one (a 0.6 mA sensor at 5 sigma).  Biases must not be negative."""


def ranges(df: pd.DataFrame, problems, max_position_um: float):
    """The values no reading can have, reported to ``problems`` (:class:`ambfit.data._Problems`: ``rows(mask,
    reason, column, values)``): negative or absurd currents, coil currents that contradict the known load, zero
    or negative standard errors, positions as large as the gap."""
    for col in [c for c in CURRENTS if c in df.columns]:
        floor = 0.0
        if col != "bias_A":
            std = f"{col[:-2]}_std_A"
            floor = (-5.0 * df[std].fillna(ZERO_CURRENT_NOISE_A / 5.0).clip(lower=0.0) if std in df.columns
                     else -ZERO_CURRENT_NOISE_A)
        problems.rows(df[col] < floor, "negative current; coil currents and biases cannot be negative (a coil "
                      "current within its noise of 0 is accepted)", col, df[col])
    for col in [c for c in CURRENTS if c in df.columns]:
        problems.rows(df[col] >= MAX_CURRENT_A, f"not a coil current (at least {MAX_CURRENT_A:g} A); currents must "
                      "be in amperes", col, df[col])
    if "i_top_A" in df.columns and "i_bottom_A" in df.columns:
        problems.rows((df["i_top_A"] == 0) & (df["i_bottom_A"] == 0),
                      "both coil currents are 0: the bearing carries no force at this reading (amplifier off or a "
                      "missing value written as 0?); remove the row", "i_top_A", df["i_top_A"])
        if "load_N" in df.columns:
            _one_coil_off(df, problems)
    for col in [c for c in STD_COLUMNS if c in df.columns]:
        problems.rows(df[col] <= 0, "a standard error must be positive (leave the cell empty when it is not known)",
                      col, df[col])
    for col in [c for c in ("v_um", "w_um", "v_set_um", "w_set_um") if c in df.columns]:
        problems.rows(df[col].abs() >= max_position_um,
                      f"position as large as the air gap (>= {max_position_um:g} µm); positions must be in "
                      "micrometres from the sensor zero: was another unit used?", col, df[col])


def _one_coil_off(df: pd.DataFrame, problems) -> None:
    """A coil at 0 A (within its noise) pulls nothing: the other coil alone pulls the rotor towards its own side,
    so the bearing cannot supply a known load along the off coil's direction (Eq. 4 with one current 0 has one
    sign).  Such a reading is no equilibrium at its load; a fit of it is dragged towards closed gaps."""
    load = df["load_N"]
    for off, on, sign, towards in (("i_top_A", "i_bottom_A", 1, "-axis"), ("i_bottom_A", "i_top_A", -1, "+axis")):
        bad = (df[off] <= 0) & (df[on] > 0) & (sign * load > 0)
        problems.rows(bad, f"this coil's current is 0 while the known load_N is {'positive' if sign > 0 else 'negative'}:"
                      f" with it off, the {on[2:-2]} coil can only pull the rotor towards {towards}, so the reading is "
                      f"no equilibrium at its load (a missing current written as 0, or a load of the wrong sign?); "
                      "fix or remove the row (a coil at 0 A is fine where the load is unknown or of the other sign, "
                      "but then the reading says nothing about this coil's side)", off, df[off])
