"""The readings' noise when the data do not state it: from each reading against its neighbours.

Without std columns or a declared level, a fit takes a unit current noise (:data:`UNIT_A`) and estimates the level
from its residuals' χ² per degree of freedom, which holds whatever the model misses as well: against that level
every model sits on the floor, and against the unit level a noisy sensor looks like a model error.  A diagnosis
needs a level the model's error does not enter.  Each reading's standardized residual is predicted from its
:data:`NEIGHBOURS` nearest neighbours (one axis, one load group, one approach direction of each coil current;
nearest in bias, set-points and time) by a local linear fit; the model's error, smooth over the operating points,
cancels to first order, and what is left is noise, of variance ``sigma^2 (1 + |w|^2)`` for the prediction's
weights ``w``: the local-linear pseudo-residuals of difference-based variance estimation (Gasser, Sroka and
Jennen-Steinmetz 1986, *Biometrika* 73, 625), in the operating variables.  Repeated set-points give exact
neighbours; an error that varies faster than the neighbours are apart makes the estimate cautious (larger).

The mean square, not a robust scale, is what the held-out scores compare with the floor, so the estimate is a mean
square too (a noise that grows with the current is then right on average); pseudo-residuals beyond :data:`GROSS`
robust scales (a spiking reading and its neighbours') are left out of it.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pandas as pd

from ambfit.data import load_groups
from ambfit.estimation.results import FitResult
from ambfit.rows import approach_direction

UNIT_A = 1e-3
"""The current noise [A] a problem without a current noise level standardizes its residuals by
(:func:`ambfit.estimation.problem.build_problem`)."""

MIN_READINGS = 20
"""Fewer pseudo-residuals than this estimate nothing (:func:`ambfit.diagnose` then says so, and its scores stand
against the unit level)."""

NEIGHBOURS = 12
"""Neighbours each reading is predicted from (a group of readings too small for them and the local linear fit is
skipped)."""

GROSS = 5.0
"""A pseudo-residual beyond this many robust scales (``1.4826 median |e|``, each over its own standard deviation)
holds a gross error and is left out of the mean square."""

FEATURES = ("bias_A", "v_set_um", "w_set_um", "time_s")
"""The operating variables neighbours are near in, each in units of its spread over the data (a column absent or
constant is skipped; the clock makes readings close in time the nearer, so that a drift adds little).  Commanded
values, not readings: neighbours chosen by nearness in noisy readings would be those whose noise is alike, and
their differences too small (among repeated set-points, markedly).  Without set-point columns the positions read
stand in for them (:data:`READ_FEATURES`), to :data:`ambfit.estimation.basis.POSITION_CLUSTER`: readings of one
set-point are then alike whatever their noise."""

READ_FEATURES = ("bias_A", "v_um", "w_um", "time_s")
"""The operating variables when the data hold no (complete) set-point columns."""

DIRECTION_NOISE = 3.0
"""A coil current's approach direction (which groups the readings) turns only on a change of more than this many of
the current's noise levels (the fit's χ² level, model error included; at least the 2 mA of
:func:`ambfit.rows.approach_direction`): a direction that followed the readings' noise would group them by it."""


@dataclasses.dataclass(frozen=True)
class NoiseEstimate:
    """The current noise estimated from neighbouring readings.

    Attributes
    ----------
    sigma_i : float
        Standard deviation of each coil current reading [A] (beside the position noise the fit was given; with none,
        the positions' noise is folded into it).
    readings : int
        Readings it rests on (their pseudo-residuals).
    left_out : int
        Readings without a pseudo-residual in the estimate: holding a gross error, or in a group too small.
    fit_estimate : float
        The ideal law's level from its residuals' χ² per degree of freedom [A], model error included.
    model : str
        The model whose residuals the readings were taken in.
    features : str
        What the neighbours are near in.
    settled : bool
        With a position noise known: whether refits at the level found settled on it (:attr:`refits` of them).
    refits : int
        Refits at the level found.
    gaps : str
        Why the data's own current std columns were not used, when they are there but incomplete.
    """

    sigma_i: float
    readings: int
    left_out: int
    fit_estimate: float
    model: str = "ideal"
    features: str = "bias, set-points and time"
    settled: bool = True
    refits: int = 0
    gaps: str = ""

    def describe(self) -> str:
        return (f"current {self.sigma_i * 1e3:.3g} mA, the floor's level, from {self.readings} readings against "
                f"their neighbours in {self.features}, in the residuals of {self.model} (the law that fits them best; "
                f"the ideal law's χ²/dof gives {self.fit_estimate * 1e3:.3g} mA, its error included"
                + ("" if self.settled else f"; beside the position noise not settled after {self.refits} refits: "
                   "the level may be high") + ")" + (f" {self.gaps}" if self.gaps else ""))

    def to_json(self) -> dict:
        return {"current_mA": self.sigma_i * 1e3, "readings": self.readings, "readings_left_out": self.left_out,
                "fit_chi2_estimate_mA": self.fit_estimate * 1e3, "model": self.model, "features": self.features,
                "settled": self.settled, "refits": self.refits,
                "method": f"local-linear pseudo-residuals: each reading's standardized residual against its "
                          f"{NEIGHBOURS} nearest neighbours' (one axis, load group and approach direction; nearest "
                          f"in {self.features}), over its standard deviation; their mean square"}


@dataclasses.dataclass(frozen=True)
class Unestimated:
    """Too few readings have neighbours enough for an estimate: the diagnosis' scores stand against the unit level."""

    def describe(self) -> str:
        return (f"too few readings have neighbours enough to estimate the current noise apart from the model's error: "
                f"the scores stand against the unit {UNIT_A * 1e3:g} mA (declare the noise, or give std columns)")

    def to_json(self) -> dict:
        return {"skipped": "too few readings have neighbours enough to estimate it", "unit_mA": UNIT_A * 1e3}


UNESTIMATED = Unestimated()
"""What :func:`ambfit.diagnose` records when too few readings have neighbours enough for an estimate."""


def _operating_points(df: pd.DataFrame) -> tuple[np.ndarray, str]:
    """The readings in :data:`FEATURES` (or :data:`READ_FEATURES`), each in units of its spread: array[n, d], and
    what they are."""
    from ambfit.estimation.basis import POSITION_CLUSTER

    commanded = all(c in df and pd.to_numeric(df[c], errors="coerce").notna().all() for c in ("v_set_um", "w_set_um"))
    step = POSITION_CLUSTER * 1e6
    names = {"bias_A": "bias", "v_set_um": "set-points", "w_set_um": "set-points", "time_s": "time",
             "v_um": f"positions read (to {step:g} µm)", "w_um": f"positions read (to {step:g} µm)"}
    cols, used = [], []
    for name in FEATURES if commanded else READ_FEATURES:
        if name in df:
            x = pd.to_numeric(df[name], errors="coerce").to_numpy(float)
            if name in ("v_um", "w_um"):
                x = np.round(x / step) * step
            spread = np.nanstd(x) if np.isfinite(x).any() else 0.0
            if np.isfinite(x).all() and spread > 0:
                cols.append((x - np.mean(x)) / spread)
                used.append(names[name])
    if not cols:
        # one operating point throughout: the readings' order stands in (neighbours taken close in time)
        return np.arange(len(df), dtype=float)[:, None] / max(len(df), 1), "the order of the readings"
    used = list(dict.fromkeys(used))
    return np.column_stack(cols), ", ".join(used[:-1]) + (" and " if len(used) > 1 else "") + used[-1]


def pseudo_residuals(df: pd.DataFrame, z: np.ndarray, turn: float = 2e-3) -> np.ndarray:
    """Each reading's residual ``z`` less the local linear prediction from its :data:`NEIGHBOURS` nearest neighbours
    among the readings of its axis, load group and approach direction of both coil currents (turning on changes above
    ``turn`` [A]), over the standard deviation that leaves to unit noise (``sqrt(1 + |w|^2)``): array[n], NaN where a
    reading's group is too small or a residual is not finite."""
    return _pseudo_residuals(_operating_points(df)[0], _groups(df, turn), z)


def _groups(df: pd.DataFrame, turn: float) -> np.ndarray:
    """Each reading's group: its axis, load group and the approach direction of both coil currents (turning on
    changes above ``turn`` [A])."""
    key = load_groups(df).astype(str)
    for coil in ("i_top_A", "i_bottom_A"):
        key = key + "|" + pd.Series(approach_direction(df, coil, threshold=turn), index=df.index).astype(str)
    return pd.factorize(key)[0]


def _pseudo_residuals(points: np.ndarray, codes: np.ndarray, z: np.ndarray) -> np.ndarray:
    """:func:`pseudo_residuals` from the readings' operating points and groups."""
    from scipy.spatial import cKDTree

    out = np.full(len(z), np.nan)
    k = NEIGHBOURS
    finite = np.isfinite(z)
    for c in np.unique(codes):
        rows = np.nonzero((codes == c) & finite)[0]
        if len(rows) < max(k, points.shape[1] + 2) + 1:
            continue
        _, near = cKDTree(points[rows]).query(points[rows], k=k + 1)
        found = rows[near]
        # the reading itself is left out wherever the search put it (readings at one point tie)
        own = found == rows[:, None]
        drop = np.where(own.any(axis=1), np.argmax(own, axis=1), k)
        nb = np.where(np.arange(k)[None, :] < drop[:, None], found[:, :k], found[:, 1:])
        # the local linear fit's value at each reading: an intercept and slopes in the operating variables
        design = np.concatenate([np.ones((len(rows), k, 1)), points[nb] - points[rows][:, None, :]], axis=2)
        w = np.linalg.pinv(design)[:, 0, :]
        out[rows] = (z[rows] - np.einsum("mk,mk->m", w, z[nb])) / np.sqrt(1.0 + np.einsum("mk,mk->m", w, w))
    return out


def from_neighbours(df: pd.DataFrame, fit: FitResult, *, level: float = UNIT_A, ideal: FitResult | None = None,
                    turn: float | None = None) -> NoiseEstimate | None:
    """The current noise of ``df`` from its readings against their neighbours (module docstring), given ``fit``, a
    fit of every row at the current noise ``level`` [A] (the unit :data:`UNIT_A`, as a fit without a noise level
    makes): ``level`` times the pseudo-residuals' root mean square, which holds exactly when the fit was given no
    position noise (else the level is the fixed point of declaring it and estimating again).  ``ideal``: the ideal
    law's fit at the unit level, for :attr:`NoiseEstimate.fit_estimate` (default ``fit``).  ``turn`` [A]: the change
    of a coil current that turns its approach direction (default :data:`DIRECTION_NOISE` of ``fit``'s χ² level).  None
    when fewer than :data:`MIN_READINGS` readings have a pseudo-residual."""
    n = len(df)
    df = df.reset_index(drop=True)
    z = np.array(fit.residuals, dtype=float)[:n]
    turn = max(2e-3, DIRECTION_NOISE * level * float(np.sqrt(fit.reduced_chi2))) if turn is None else turn
    (points, features), codes = _operating_points(df), _groups(df, turn)
    gross = _gross(_pseudo_residuals(points, codes, z))
    # a gross error moves its neighbours' pseudo-residuals too: the readings found are taken out of every
    # neighbourhood and the rest predicted again
    z[gross] = np.nan
    e = _pseudo_residuals(points, codes, z)
    e[_gross(e)] = np.nan
    e = e[np.isfinite(e)]
    if len(e) < MIN_READINGS:
        return None
    chi2 = (ideal or fit).reduced_chi2
    return NoiseEstimate(sigma_i=level * float(np.sqrt(np.mean(e**2))), readings=len(e), left_out=int(n - len(e)),
                         fit_estimate=UNIT_A * float(np.sqrt(chi2)), model=getattr(fit, "model", "ideal"),
                         features=features)


SCATTER_OFF = 0.25
"""The readings scatter unlike their stated noise when their pseudo-residuals' root mean square is further than
this (relative) from 1, and further than 6 standard errors of independent ones (``1 / sqrt(2 m)`` for ``m``;
neighbouring pseudo-residuals share readings, so the true standard error is larger)."""


@dataclasses.dataclass(frozen=True)
class Scatter:
    """How the residuals of data with a stated noise (std columns, or declared) scatter between neighbouring
    readings, against that noise: 1 when the noise is as stated and the model's error is smooth between them.

    Attributes
    ----------
    ratio : float
        The pseudo-residuals' root mean square (:func:`pseudo_residuals`).
    readings : int
        How many readings it rests on.
    model : str
        The model whose residuals they were (the one that fits every row best).
    positions_unstated : bool
        The data state no position noise (it is taken as 0): what the positions' noise adds shows here.
    declared : bool
        The current noise was declared (it overrides the std columns).
    """

    ratio: float
    readings: int
    model: str
    positions_unstated: bool = False
    declared: bool = False

    @property
    def off(self) -> bool:
        """Whether the scatter is clearly unlike the stated noise (:data:`SCATTER_OFF`)."""
        return bool(abs(self.ratio - 1.0) > max(SCATTER_OFF, 6.0 / np.sqrt(2.0 * max(self.readings, 1))))

    def describe(self) -> str:
        stated = "the declared level says" if self.declared else "the std columns say"
        head = (f"between neighbouring readings the residuals (of {self.model}, the law that fits them best) scatter "
                f"{self.ratio:.2f} times their stated noise ({self.readings} readings): ")
        if self.ratio > 1.0:
            return head + (
                ("the positions' noise, taken as 0 without position std columns, adds to the currents' (declare it "
                 "with --position-noise-um); or " if self.positions_unstated else "either ")
                + f"the noise is larger than {stated} (a DAQ's averaging error is not a reading's noise), or an "
                "effect changes from one reading to its neighbours (a history the operating point does not fix); "
                "with the noise understated every model falls short of the floor")
        hidden = float(np.sqrt(max(1.0 - self.ratio**2, 0.0)))
        return head + (f"either the noise is smaller than {stated}, or noise shared by neighbouring readings (a slow "
                       "wander, filtering, averaging over one another) cancels in their differences; an error of up "
                       f"to {hidden:.2f} of the stated noise would go unseen")

    def to_json(self) -> dict:
        return {"ratio": float(self.ratio), "readings": int(self.readings), "model": self.model, "off": self.off,
                "positions_unstated": self.positions_unstated, "declared": self.declared}


def scatter(df: pd.DataFrame, fit: FitResult, current: float, positions_unstated: bool = False,
            declared: bool = False) -> Scatter | None:
    """:class:`Scatter` of ``fit``'s residuals (a fit at the data's stated noise, ``current`` [A] typical of the
    coil currents'); None when fewer than :data:`MIN_READINGS` readings have a pseudo-residual."""
    found = from_neighbours(df, fit, level=1.0, turn=max(2e-3, DIRECTION_NOISE * current))
    return None if found is None else Scatter(ratio=found.sigma_i, readings=found.readings, model=found.model,
                                              positions_unstated=positions_unstated, declared=declared)


def _gross(e: np.ndarray) -> np.ndarray:
    """Where a pseudo-residual exceeds :data:`GROSS` robust scales of them all."""
    from ambfit.estimation.robust import robust_scale

    finite = np.isfinite(e)
    scale = robust_scale(e[finite], known_noise=False) if finite.any() else 0.0
    return finite & (np.abs(np.where(finite, e, 0.0)) > GROSS * scale) if scale > 0 else np.zeros(len(e), bool)
