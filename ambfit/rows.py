"""What each reading's history and companions are: its run of readings, the direction and path by which its coil
currents were reached, the other axis' currents read at the same moment, and the rows as the model's readings.

The order of rows within each experiment and axis is the order in which the readings were taken (contract
section 1).
"""

from __future__ import annotations

import numpy as np
import pandas as pd

from ambfit.data import Dataset, group_labels, joint_codes


def runs(df: pd.DataFrame, sets: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Each axis' runs of readings, one coil history each: ``(order, first)``, the row numbers run by run and
    whether each of them starts its run.

    A run is one experiment's readings of an axis in file order; when the experiments were read one after another
    on one clock (:func:`clock`), the bearing stayed energised between them, and each axis' timed experiments form
    one run, in the order of that clock (an untimed experiment stays a run of its own).  ``sets``: as for
    :func:`clock`.
    """
    n = len(df)
    sets = np.zeros(n, dtype=np.int64) if sets is None else np.asarray(sets)
    labels = group_labels(df["experiment"]).to_numpy() if "experiment" in df.columns else np.zeros(n)
    exp = joint_codes(sets, labels, own_missing=True)
    # one history per set and axis where its experiments share a clock
    history = np.where(_shared_clock(df, sets, labels), -1, exp)
    code = joint_codes(sets, history, df["axis"].to_numpy(), own_missing=True)
    # each run's rows together, by experiment (in the order of the shared clock), then in file order
    order = np.lexsort((np.arange(n), exp, code))
    c = code[order]
    return order, np.r_[True, c[1:] != c[:-1]] if len(c) else np.zeros(0, bool)


def approach_direction(df: pd.DataFrame, column: str, threshold: float = 2e-3,
                       sets: np.ndarray | None = None) -> np.ndarray:
    """Direction (+1 rising, -1 falling) from which each reading's coil current was reached.

    Derived from the order of rows: within each run (:func:`runs`), the sign of the change from the previous
    reading; a change below ``threshold`` [A] keeps the previous direction; a run's first reading counts as rising
    (from zero current).  ``sets``: as for :func:`clock`.
    """
    n = len(df)
    if n == 0:
        return np.zeros(0)
    order, first = runs(df, sets)
    i = df[column].to_numpy(float)[order]
    step = np.diff(i, prepend=np.nan)
    with np.errstate(invalid="ignore"):
        d = np.where(first, 1.0, np.where(np.abs(step) >= threshold, np.sign(step), np.nan))
    # a small change keeps the previous direction: carry the last set value forward (each group starts with one)
    last = np.where(np.isnan(d), 0, np.arange(n))
    np.maximum.accumulate(last, out=last)
    out = np.empty(n)
    out[order] = d[last]
    return out


def play_states(df: pd.DataFrame, column: str, widths) -> np.ndarray:
    """Where each reading's coil current sits in the dead band of a play operator of each half-width: array[n, w],
    ``(i - p) / width`` in [-1, 1] (+1: the current has risen at least ``width`` since it last turned).

    The play's output ``p = clip(p_prev, i - width, i + width)`` follows the current through each run's readings
    in order (:func:`runs`), from zero current before the first reading.  A sum of plays of several
    widths is the Prandtl-Ishlinskii model of hysteresis with memory (Mayergoyz, *Mathematical Models of
    Hysteresis*, 1991, ch. 1); the narrowest play's state is the approach direction (:func:`approach_direction`).
    """
    widths = np.asarray(widths, dtype=float)
    out = np.zeros((len(df), len(widths)))
    if len(df) == 0:
        return out
    order, first = runs(df)
    i = df[column].to_numpy(float)[order]
    p = np.zeros(len(widths))
    for r, (now, new) in enumerate(zip(i, first)):       # a recursion: each output needs the one before
        if new:
            p = np.zeros(len(widths))
        p = np.clip(p, now - widths, now + widths)
        out[order[r]] = (now - p) / widths
    return out


def fading_states(df: pd.DataFrame, column: str, memories, widths) -> np.ndarray:
    """How far each reading's coil current sits from a fading memory of its recent course: array[n, m * w],
    ``clip((i - q) / width, -1, 1)`` for each memory (outer) and half-width (inner).

    ``q`` follows the current through each run's readings in order (:func:`runs`), ``q = a q_prev + (1 - a) i``
    with ``a = exp(-1 / memory)`` (``memory`` in readings), from zero current before the run's first reading, as the
    plays start: the coils were energised from zero, and a memory not yet relaxed by the first reading lags it as
    after a rise.  Where a play (:func:`play_states`) forgets nothing until the current turns by its width, this
    forgets the past at a fixed rate: the lag of a magnetisation that relaxes towards the current (eddy currents in
    solid iron, magnetic after-effect; Bertotti, *Hysteresis in Magnetism*, Academic Press, 1998), linear in
    ``i - q`` for a wide width and a direction for a narrow one.
    """
    memories, widths = np.asarray(memories, dtype=float), np.asarray(widths, dtype=float)
    out = np.zeros((len(df), len(memories) * len(widths)))
    if len(df) == 0:
        return out
    order, first = runs(df)
    i = df[column].to_numpy(float)[order]
    a = np.exp(-1.0 / memories)
    q = np.zeros(len(memories))
    for r, (now, new) in enumerate(zip(i, first)):       # a recursion: each output needs the one before
        if new:
            q = np.zeros(len(memories))
        q = a * q + (1.0 - a) * now
        out[order[r]] = np.clip((now - q)[:, None] / widths[None, :], -1.0, 1.0).reshape(-1)
    return out


def other_axis_currents(df: pd.DataFrame) -> tuple[np.ndarray, np.ndarray]:
    """The other axis' ``(i_top_A, i_bottom_A)`` read at the same moment as each row (NaN where none).

    Rows of both axes taken at one moment share ``time_s`` (and ``experiment``, contract section 1);
    without a ``time_s`` column every entry is NaN.
    """
    n = len(df)
    nan = np.full(n, np.nan)
    if "time_s" not in df.columns:
        return nan, nan.copy()
    exp = group_labels(df["experiment"]).to_numpy() if "experiment" in df.columns else np.full(n, "")
    t = df["time_s"].to_numpy(float)
    ax = (df["axis"] == "w").to_numpy().astype(int)
    timed = ~np.isnan(t)
    # each moment (experiment, time) numbered; the first row of each moment and axis is the one read
    moment = np.full(n, -1)
    if timed.any():
        moments = pd.DataFrame({"e": exp[timed], "t": t[timed]}).groupby(["e", "t"], sort=False, dropna=False)
        moment[timed] = moments.ngroup()
    first = np.full((moment.max(initial=-1) + 2, 2), -1)   # (a last row of -1s for the untimed rows)
    rows = np.nonzero(timed)[0][::-1]                  # in reverse, so that the first row of each is kept
    first[moment[rows], ax[rows]] = rows
    partner = first[moment, 1 - ax]
    it, ib = df["i_top_A"].to_numpy(float), df["i_bottom_A"].to_numpy(float)
    return np.where(partner >= 0, it[partner], np.nan), np.where(partner >= 0, ib[partner], np.nan)


def clock(df: pd.DataFrame, sets: np.ndarray | None = None) -> np.ndarray | None:
    """Each row's time [s] from the start of its clock; ``None`` without a ``time_s`` column.

    One clock holds within an experiment (contract section 1).  When each experiment, in the order the file
    lists them, starts after the one before it ends, they were read one after another on one clock, and the
    whole file counts from its first reading (a drift runs on across experiments); otherwise each experiment's
    clock restarted, and each counts from its own first reading.  Either way nothing depends on where a clock's
    zero is.  ``sets`` (each row's data set, one set's rows together) decides this for each data set of a
    joined table on its own, as for that table alone.
    """
    if "time_s" not in df.columns:
        return None
    t = df["time_s"].to_numpy(float)
    n = len(t)
    sets = np.zeros(n, dtype=np.int64) if sets is None else np.asarray(sets)
    code = joint_codes(sets, group_labels(df["experiment"]).to_numpy() if "experiment" in df.columns else np.zeros(n))
    one_clock, lo = _one_clock(t, sets, code)
    first = np.full(len(one_clock), np.inf)
    np.fmin.at(first, sets, t)
    lo, first = np.where(np.isfinite(lo), lo, np.nan), np.where(np.isfinite(first), first, np.nan)
    return t - np.where(one_clock[sets], first[sets], lo[code])


def _one_clock(t: np.ndarray, sets: np.ndarray, code: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per data set, whether its experiments (``code``: each set's experiments numbered in the order the file
    lists them, -1 for rows of none) were read one after another on one clock: each timed one starts after the one
    before it ends (:func:`clock`); and each experiment's first time (inf for one untimed, and in the last place for
    rows of none, which start no clock of their own)."""
    count = int(code.max(initial=-1)) + 1
    lo, hi = np.full(count + 1, np.inf), np.full(count + 1, -np.inf)   # (a last one for rows of no experiment)
    np.fmin.at(lo, code, t)
    np.fmax.at(hi, code, t)
    lo[-1], hi[-1] = np.inf, -np.inf
    owner = np.zeros(count + 1, dtype=np.int64)
    owner[code] = sets
    timed = np.nonzero(np.isfinite(lo))[0]         # experiments with a reading's time
    after = owner[timed[1:]] == owner[timed[:-1]]
    restarted = after & ~(lo[timed[1:]] >= hi[timed[:-1]])
    one_clock = np.ones(int(sets.max(initial=-1)) + 1, dtype=bool)
    one_clock[owner[timed[1:]][restarted]] = False
    return one_clock, lo


def _shared_clock(df: pd.DataFrame, sets: np.ndarray, labels: np.ndarray) -> np.ndarray:
    """Per row, whether its experiment (``labels``) is timed and shares one clock with the other experiments of its
    data set (:func:`clock`)."""
    if "time_s" not in df.columns or len(df) == 0:
        return np.zeros(len(df), bool)
    code = joint_codes(sets, labels)
    one_clock, lo = _one_clock(df["time_s"].to_numpy(float), sets, code)
    return one_clock[sets] & np.isfinite(lo[code])


STEADY_K = 0.01
"""A temperature column that varies by less than this [K] over the rows measures no thermal state (a bearing
thermometer resolves 0.01-0.1 K; a drift of the library's 0.1-2 µm/K needs more than this to show)."""


def thermometer(df: pd.DataFrame) -> np.ndarray | None:
    """Each row's temperature [°C], or ``None`` when the rows have no thermometer: no ``temperature_C`` column, or
    one that does not change (by less than :data:`STEADY_K`: a logged room or set-point temperature).  A drift is
    then followed in time (:class:`ambfit.physics.effects.ThermalDrift`), not pinned to a constant."""
    if "temperature_C" not in df.columns:
        return None
    t = df["temperature_C"].to_numpy(float)
    known = t[np.isfinite(t)]
    return t if known.size and np.ptp(known) >= STEADY_K else None


def readings(data: Dataset | pd.DataFrame, sets: np.ndarray | None = None):
    """The rows as :class:`ambfit.physics.model.Readings` in SI units; time counts from the start of the rows'
    clock (:func:`clock`), wherever the clock's zero is.  ``sets``: as for :func:`clock` (the clocks and coil
    histories of a joined table's data sets, each decided as for that table alone)."""
    from ambfit.physics.model import Readings

    df = data.frame if isinstance(data, Dataset) else data
    ax = (df["axis"] == "w").to_numpy().astype(int)
    v = df["v_um"].to_numpy(float) * 1e-6
    w = df["w_um"].to_numpy(float) * 1e-6
    return Readings.build(
        axis=ax, i_top=df["i_top_A"].to_numpy(float), i_bottom=df["i_bottom_A"].to_numpy(float),
        x=np.where(ax == 0, v, w), y=np.where(ax == 0, w, v), bias=df["bias_A"].to_numpy(float),
        time=clock(df, sets),
        temperature=thermometer(df),
        dir_top=approach_direction(df, "i_top_A", sets=sets), dir_bottom=approach_direction(df, "i_bottom_A", sets=sets),
        **dict(zip(("i_top_other", "i_bottom_other"), other_axis_currents(df))),
    )
