"""A campaign: identification in windows of time, the drift of gap and origin, and change points.

A lab that logs one machine for days or weeks wants to know whether the bearing's effective
gap and origin stay put.  :func:`analyse` cuts the contract table into windows (rolling
windows of ``time_s``, :func:`windows`, or one per experiment, :func:`by_experiment`), fits
each with ambfit's least squares (:func:`ambfit.estimation.fit.fit`), and studies each
parameter's series of estimates ``y_j ± s_j`` at the windows' times ``t_j``:

Drift (:func:`drift`)
    The weighted least-squares line ``y = a + b t`` (weights ``1 / s_j^2``).  The slope's standard error
    is ``sqrt((X^T W X)^-1)_bb``; when the scatter about the line exceeds the error bars (reduced
    ``χ² > 1``) it is multiplied by ``sqrt(χ²/dof)`` (the Birge ratio; Birge, Phys. Rev. 40, 207, 1932; the
    scale factor S of the Particle Data Group's averages) and the result says so.

Change points (:func:`change_points`)
    The model with one step, ``y_j = a + b t_j + δ [j >= τ] + ε_j`` with ``ε_j ~ N(0, s_j^2)``, against the
    model without it.  For each candidate boundary ``τ`` (between consecutive experiments, or windows when the
    data name none) the jump ``δ̂_τ`` is fitted jointly with the drift, so the drift is removed without the jump
    leaking into it, and ``z_τ = δ̂_τ / se(δ̂_τ)``; ``max_τ z_τ^2`` is the likelihood-ratio statistic for one
    change point in a simple linear regression with known variances (Kim & Siegmund, Biometrika 76, 409,
    1989).  Its p-value is bounded by Bonferroni over the ``m`` candidates, ``p <= m P(χ²_1 >= max z²)``
    (conservative; Worsley, Biometrika 69, 297, 1982, gives a sharper bound for change points), or
    found by simulating the no-jump model (``method="simulation"``).  A step is flagged when ``p <= alpha``
    (1 %).  Further steps are searched one at a time with the flagged ones in the model (Bai, Econometric
    Theory 13, 315, 1997: estimating multiple breaks one at a time).  The windows' error bars are taken as
    known; when the model under test (drift, flagged steps and the candidate) scatters beyond them by more
    than chance (χ² p-value below 1 %), its errors are scaled by its Birge ratio and the p-value uses
    Student's t, as a t-test takes its variance from the full model.  (Scaling whenever χ²/dof > 1 would act
    on noise: a χ² of 8 degrees of freedom exceeds its mean by half in one case of seven.  A second jump not
    yet in the model inflates the scale and can mask the first: two jumps of similar size in one campaign
    are the test's weak case.)  The drift is a straight line: one that bends (exponential warm-up) leaves a
    curvature that the search reads as a step (``benchmarks/campaign.py``: most campaigns with an 8 h warm-up
    get a flag on v0); check the drift's χ²/dof and look at the series before reading a flag as a jump.

The drift is then reported from the model with the flagged steps in it.

Jumps against a drift measured elsewhere (:func:`differences`)
    With few windows (the paper's Table 1 has three experiments) a drift and a step cannot both be fitted.
    A drift measured inside the experiments (where no re-levitation happens) is then removed from each
    difference of neighbours, its error included: ``z = (y_j - y_{j-1} - b Δt) / sqrt(s_j² + s_{j-1}² +
    Δt² s_b²)``, Bonferroni over the boundaries.  :func:`paper_origins` applies it to the paper's Tables 1
    and 2; :func:`change_points` also takes such a drift (``drift=``, a Gaussian constraint on the slope).

Windows are independent estimates only when they share no readings: with overlapping
rolling windows (``step_s < width_s``) the tests use a subset that does not overlap, and say so.

Example
-------
>>> import numpy as np
>>> t = np.arange(8.0)
>>> s = Series("v0", t, 1e-6 * (0.2 * t + 3.0 * (t >= 4)), np.full(8, 0.1e-6), labels=tuple("ABCDEFGH"),
...            time_unit="h", seconds_per_unit=3600.0)
>>> cp = change_points(s)
>>> [f.at for f in cp.flagged], round(drift(s, steps=cp.steps).per_hour()[0] * 1e6, 3)
(['E'], 0.2)
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence

import numpy as np
import pandas as pd

from ambfit.data import DataError, Dataset
from ambfit.physics.bearing import PAPER_BEARING, Bearing
from ambfit.rig.campaign import HOUR

PARAMS = ("g_v0", "v0", "g_w0", "w0")
"""The parameters whose drift and jumps a campaign studies (internal names, SI)."""

ALPHA = 0.01
"""False-alarm probability of the change-point test per parameter and campaign (Bonferroni bound)."""

SCATTER_P = 0.01
"""The change-point test scales the error bars when the scatter about its model has a χ² p-value below this: the
windows' errors are trusted unless they are clearly too small (scaled and judged by Student's t with a few degrees
of freedom, a 7-sigma jump can drop below a Bonferroni bound; a pre-test at 5 % did so in 4 % of the benchmark's
campaigns)."""



class CampaignError(ValueError):
    """A series too short for the requested analysis (too few identified windows)."""


# --- windows ---------------------------------------------------------------------------------------------------

@dataclasses.dataclass(frozen=True)
class Window:
    """One window of a campaign: its readings and, once identified, its fit.

    Attributes
    ----------
    label : str
        ``W1``, ``W2``, ... (rolling windows) or the experiment's label.
    start_s, end_s : float
        The window's span [s]: ``[start, end)`` for a rolling window, first and last reading for an experiment.
    centre_s : float
        Mean time of its readings [s]: where the estimate of a linearly drifting parameter applies.
    n_rows : int
    experiments : tuple of str
        The experiments its readings belong to (empty when the data name none).
    fit : FitResult or None
    problem : str
        Why the window is not identified ("" when it is).
    """

    label: str
    start_s: float
    end_s: float
    centre_s: float
    n_rows: int
    experiments: tuple = ()
    frame: pd.DataFrame | None = dataclasses.field(default=None, repr=False, compare=False)
    fit: object = dataclasses.field(default=None, repr=False, compare=False)
    problem: str = "not fitted"

    @property
    def identified(self) -> bool:
        return self.fit is not None and not self.problem

    @property
    def group(self) -> str:
        """The experiment label(s) of its readings (joined with ``+``), the unit change points sit between."""
        return "+".join(self.experiments)

    def estimate(self, name: str) -> tuple[float, float]:
        """``(value, std)`` of ``name`` [SI]; NaN when not identified or not estimated in this window."""
        if not self.identified or name not in self.fit.names:
            return math.nan, math.nan
        return self.fit.value(name), self.fit.error(name)

    def to_json(self) -> dict:
        out = {"label": self.label, "start_s": self.start_s, "end_s": self.end_s, "centre_s": self.centre_s,
               "n_rows": self.n_rows, "experiments": list(self.experiments), "identified": self.identified,
               "problem": self.problem or None}
        if self.fit is not None:
            out |= {"params": self.fit.contract_params(), "reduced_chi2": self.fit.reduced_chi2,
                    "dof": self.fit.dof, "health": self.fit.health()}
        return out


def _frame(data) -> tuple[pd.DataFrame, str]:
    if isinstance(data, Dataset):
        return data.frame, data.source
    return data, "<data>"


def check_time(frame: pd.DataFrame, source: str = "<data>", column: str | None = "experiment") -> None:
    """Raise :class:`ambfit.data.DataError` (naming file, column, row) unless every row has a time and the
    experiments follow one another in time (a campaign's clock, not one restarting per experiment)."""
    if "time_s" not in frame.columns:
        raise DataError("missing column 'time_s': a campaign needs the time of every reading [s] (from one clock "
                        f"over the whole campaign); the file has {list(frame.columns)}", file=source, column="time_s")
    t = pd.to_numeric(frame["time_s"], errors="coerce").to_numpy(float)
    if not np.all(np.isfinite(t)):
        r = int(np.argmax(~np.isfinite(t)))
        raise DataError("empty or non-numeric time: every reading of a campaign needs its time_s", file=source,
                        row=r + 1, column="time_s", value=frame["time_s"].iloc[r])
    if column is None or column not in frame.columns:
        return
    spans = frame.assign(_t=t).groupby(frame[column].astype(str), sort=False)["_t"].agg(["min", "max"])
    spans = spans.sort_values("min")
    overlap = spans["min"].to_numpy()[1:] < spans["max"].to_numpy()[:-1]
    if overlap.any():
        j = int(np.argmax(overlap))
        a, b = spans.index[j], spans.index[j + 1]
        raise DataError(f"the times of {column} {a!r} ({spans['min'].iloc[j]:g}-{spans['max'].iloc[j]:g} s) and "
                        f"{b!r} ({spans['min'].iloc[j + 1]:g}-{spans['max'].iloc[j + 1]:g} s) overlap: time_s must "
                        "run on one clock over the whole campaign (seconds since its start), not restart with "
                        "each experiment", file=source, column="time_s")


def _window(label, sub: pd.DataFrame, start, end, column) -> Window:
    t = sub["time_s"].to_numpy(float)
    exps = tuple(dict.fromkeys(sub[column].astype(str))) if column in sub.columns else ()
    return Window(label=label, start_s=float(start), end_s=float(end), centre_s=float(t.mean()), n_rows=len(sub),
                  experiments=exps, frame=sub)


def windows(data, width_s: float, step_s: float | None = None, *, column: str = "experiment") -> list[Window]:
    """Rolling windows ``[t0 + k step, t0 + k step + width)`` of ``time_s`` [s] from the first reading ``t0``.

    Windows without readings are left out (there is nothing to report); windows with too few readings to
    identify are kept and :func:`identify` says why.  ``step_s`` defaults to ``width_s`` (windows that
    share no reading, what the drift and change-point tests need).
    """
    frame, source = _frame(data)
    check_time(frame, source, column)
    if not (np.isfinite(width_s) and width_s > 0):
        raise ValueError(f"the window width must be a positive number of seconds, got {width_s!r}")
    step = width_s if step_s is None else float(step_s)
    if not (np.isfinite(step) and step > 0):
        raise ValueError(f"the window step must be a positive number of seconds, got {step_s!r}")
    t = frame["time_s"].to_numpy(float)
    t0, out = float(t.min()), []
    for k in range(int(np.floor((t.max() - t0) / step)) + 1):
        lo = t0 + k * step
        sel = (t >= lo) & (t < lo + width_s)
        if sel.any():
            out.append(_window(f"W{k + 1}", frame[sel], lo, lo + width_s, column))
    return out


def by_experiment(data, column: str = "experiment") -> list[Window]:
    """One window per value of ``column`` (default ``experiment``), in the order of their first reading."""
    frame, source = _frame(data)
    if column not in frame.columns:
        raise DataError(f"missing column {column!r} to split the campaign by (or cut rolling windows of time_s "
                        f"instead: width_s, --window); the file has {list(frame.columns)}", file=source, column=column)
    check_time(frame, source, column)
    out = []
    for key, sub in frame.groupby(frame[column].astype(str), sort=False):
        t = sub["time_s"].to_numpy(float)
        out.append(_window(key, sub, t.min(), t.max(), column))
    return sorted(out, key=lambda w: w.start_s)


def identify(wins: Sequence[Window], *, bearing: Bearing = PAPER_BEARING, progress=None, **fit_kw) -> list[Window]:
    """Fit every window by least squares (:func:`ambfit.estimation.fit.fit`, keywords passed on).

    A window is identified when its fit converged, is well conditioned and plausible for ``bearing``; else
    ``problem`` holds the fit's own cause-and-fix text.  ``progress(what, done, total)`` is called per window.
    """
    from ambfit.estimation.fit import FitError, fit

    out = []
    for j, w in enumerate(wins, 1):
        try:
            res = fit(w.frame, bearing=bearing, throw=False, **fit_kw)
            bad = [text for name, ok, text in res.checks()
                   if name in ("converged", "well_conditioned", "plausible") and ok is False]
            problem = "; ".join(bad)
        except FitError as exc:
            res, problem = None, str(exc)
        out.append(dataclasses.replace(w, fit=res, problem=problem))
        if progress is not None:
            progress("windows", j, len(wins))
    return out


def independent(wins: Sequence[Window]) -> list[int]:
    """Indices of windows that share no readings: greedily, each starting at or after the last one's end."""
    keep, end = [], -math.inf
    for j, w in enumerate(wins):
        if w.start_s >= end:
            keep.append(j)
            end = w.end_s if w.end_s > w.start_s else w.start_s + 1e-9
    return keep


# --- series, lines and steps ------------------------------------------------------------------------------------

@dataclasses.dataclass(frozen=True)
class Series:
    """One parameter's estimates over time: ``y ± s`` [SI] at times ``t`` [``time_unit``].

    ``groups`` (experiment labels) mark where a change point may sit: between points of different groups
    (every boundary when no groups are given).  ``seconds_per_unit`` converts rates to per hour (None when
    the time is a count, e.g. iterations).
    """

    name: str
    t: np.ndarray
    y: np.ndarray
    s: np.ndarray
    labels: tuple = ()
    groups: tuple = ()
    time_unit: str = "s"
    seconds_per_unit: float | None = 1.0
    display: tuple = ("µm", 1e6)

    def __post_init__(self):
        n = len(self.t)
        if not (len(self.y) == len(self.s) == n):
            raise ValueError(f"t, y and s must have equal lengths, got {n}, {len(self.y)}, {len(self.s)}")
        if not np.all(np.asarray(self.s) > 0):
            raise ValueError(f"{self.name}: every standard error must be positive")
        if not self.labels:
            object.__setattr__(self, "labels", tuple(str(j + 1) for j in range(n)))

    def __len__(self) -> int:
        return len(self.t)

    @classmethod
    def from_windows(cls, wins: Sequence[Window], name: str) -> Series:
        """The identified windows' estimates of ``name`` (time: window centre [s])."""
        pts = [(w.centre_s, *w.estimate(name), w.label, w.group) for w in wins]
        pts = [p for p in pts if np.isfinite(p[1]) and np.isfinite(p[2]) and p[2] > 0]
        t, y, s, labels, groups = (list(c) for c in zip(*pts)) if pts else ([], [], [], [], [])
        unit = ("µm", 1e6) if name in PARAMS else ("N·m²/A²", 1.0)
        return cls(name, np.asarray(t, float), np.asarray(y, float), np.asarray(s, float), tuple(labels),
                   tuple(groups) if all(groups) else (), display=unit)

    def candidates(self) -> list[int]:
        """Indices ``τ`` (from 1) where a step may start: a new group begins (or every point without groups)."""
        if not self.groups:
            return list(range(1, len(self)))
        return [j for j in range(1, len(self)) if self.groups[j] != self.groups[j - 1]]

    def where(self, tau: int) -> str:
        """The label of the first point after a step at ``tau`` (its experiment when windows carry one)."""
        if self.groups and self.groups[tau] != self.labels[tau]:
            return f"{self.labels[tau]} ({self.groups[tau]})"
        return str(self.labels[tau])


@dataclasses.dataclass(frozen=True)
class _Line:
    """Weighted least squares ``y = a + b (t - t_ref) + sum_k d_k [j >= tau_k]`` (coefficients SI; ``b`` is
    ``coef[1]`` unless the slope is fixed; the steps start at ``first_step``)."""

    coef: np.ndarray
    cov: np.ndarray
    chi2: float
    dof: int
    first_step: int

    def step(self, k: int) -> tuple[float, float]:
        j = self.first_step + k
        return float(self.coef[j]), float(np.sqrt(abs(self.cov[j, j])))

    @property
    def birge(self) -> float:
        """``sqrt(χ²/dof)``; NaN without degrees of freedom."""
        return math.sqrt(self.chi2 / self.dof) if self.dof > 0 else math.nan


def _slope_prior(slope):
    """``"fit"`` -> None (free), ``"none"`` -> (0, 0), a :class:`Drift` or ``(slope, std)`` -> that pair."""
    if isinstance(slope, str):
        if slope not in ("fit", "none"):
            raise ValueError(f"drift must be 'fit', 'none', a Drift or (slope, std), got {slope!r}")
        return None if slope == "fit" else (0.0, 0.0)
    if isinstance(slope, Drift):
        return slope.slope, slope.std
    b, sb = slope
    return float(b), float(sb)


def _design(series: Series, steps: Sequence[int], prior) -> tuple[np.ndarray, np.ndarray, int]:
    """The whitened design matrix, right-hand side (a prior on the slope as one more row) and the first step's
    column; ``t_ref`` is the weighted mean time."""
    n = len(series)
    t = np.asarray(series.t, float)
    w = 1.0 / np.asarray(series.s, float)
    t_ref = float(np.sum(w**2 * t) / np.sum(w**2))
    u = t - t_ref
    y = np.asarray(series.y, float)
    cols = [np.ones(n)]
    free = prior is None or prior[1] > 0
    if free:
        cols.append(u)
    else:                                   # a slope known exactly: removed from the data
        y = y - prior[0] * u
    cols += [(np.arange(n) >= tau).astype(float) for tau in steps]
    x = np.column_stack(cols)
    a, r = x * w[:, None], y * w
    if prior is not None and prior[1] > 0:
        row = np.zeros(x.shape[1])
        row[1] = 1.0 / prior[1]
        a, r = np.vstack([a, row]), np.append(r, prior[0] / prior[1])
    return a, r, 1 + free


def _line(series: Series, steps: Sequence[int] = (), prior=None) -> _Line:
    a, r, first = _design(series, steps, prior)
    scale = np.linalg.norm(a, axis=0)
    scale = np.where(scale > 0, scale, 1.0)
    sv = np.linalg.svd(a / scale, compute_uv=False)
    if sv[-1] <= 1e-10 * sv[0]:
        raise CampaignError(f"{series.name}: the drift and the steps at {[series.where(s) for s in steps]} cannot "
                            f"be told apart with {len(series)} windows")
    cov = np.linalg.inv((a / scale).T @ (a / scale)) / np.outer(scale, scale)
    coef = cov @ a.T @ r
    res = r - a @ coef
    return _Line(coef=coef, cov=cov, chi2=float(res @ res), dof=len(r) - a.shape[1], first_step=first)


def _key(unit: str) -> str:
    """A display unit as an ASCII JSON key part: ``µm`` -> ``um``, ``N·m²/A²`` -> ``Nm2_per_A2``."""
    return unit.replace("µ", "u").replace("·", "").replace("²", "2").replace("/", "_per_")


# --- drift ------------------------------------------------------------------------------------------------------

@dataclasses.dataclass(frozen=True)
class Drift:
    """A parameter's drift: the slope of its weighted least-squares line over time.

    Attributes
    ----------
    name : str
    slope, std : float
        Slope [SI per ``time_unit``] and its standard error (scaled by ``birge`` when ``inflated``).
    stated_std : float
        The slope's standard error from the windows' error bars alone.
    reduced_chi2 : float
        Scatter about the line over its error bars (NaN without degrees of freedom).
    dof, n : int
    inflated : bool
        The error bars did not cover the scatter (reduced χ² > 1): ``std = stated_std * sqrt(reduced χ²)``.
    steps : tuple of str
        Where steps were fitted together with the line (flagged change points).
    """

    name: str
    slope: float
    std: float
    stated_std: float
    reduced_chi2: float
    dof: int
    n: int
    inflated: bool
    steps: tuple = ()
    time_unit: str = "s"
    seconds_per_unit: float | None = 1.0
    display: tuple = ("µm", 1e6)

    @property
    def z(self) -> float:
        """Slope over its standard error."""
        return self.slope / self.std if self.std > 0 else math.nan

    def per_hour(self) -> tuple[float, float] | None:
        """``(slope, std)`` [SI per hour]; None when the time unit is not a time (iterations)."""
        if self.seconds_per_unit is None:
            return None
        f = HOUR / self.seconds_per_unit
        return self.slope * f, self.std * f

    def note(self) -> str:
        """What the reader should know beyond slope ± error (empty when nothing)."""
        parts = []
        if self.inflated:
            parts.append(f"error scaled by sqrt(χ²/dof) = {math.sqrt(self.reduced_chi2):.2f}: the windows scatter "
                         "more about the line than their error bars allow (drift not linear, or errors too small)")
        elif not np.isfinite(self.reduced_chi2):
            parts.append("no degrees of freedom left to check the scatter against the error bars")
        if self.steps:
            parts.append(f"fitted with a step at {', '.join(self.steps)}")
        return "; ".join(parts)

    def text(self) -> str:
        unit, f = self.display
        ph = self.per_hour()
        rate = (f"{ph[0] * f:+.4g} ± {ph[1] * f:.2g} {unit}/h" if ph is not None else
                f"{self.slope * f:+.4g} ± {self.std * f:.2g} {unit}/{self.time_unit}")
        return f"{self.name}: {rate} (z {self.z:+.1f})"

    def to_json(self) -> dict:
        unit, f = self.display
        key = _key(unit)
        per = f"{key}_per_{self.time_unit}"
        out = {"parameter": self.name, f"slope_{per}": self.slope * f, f"std_{per}": self.std * f,
               f"stated_std_{per}": self.stated_std * f,
               "reduced_chi2": self.reduced_chi2 if np.isfinite(self.reduced_chi2) else None, "dof": self.dof,
               "n": self.n, "inflated": self.inflated, "steps": list(self.steps), "z": self.z, "note": self.note()}
        ph = self.per_hour()
        if ph is not None:
            out |= {f"slope_{key}_per_h": ph[0] * f, f"std_{key}_per_h": ph[1] * f}
        return out


def drift(series: Series, *, steps: Sequence[int] = (), inflate: bool = True) -> Drift:
    """The weighted least-squares slope of ``series`` over time, with steps at ``steps`` (indices, from
    :attr:`ChangePoints.steps`) fitted jointly; see the module docstring.

    Raises
    ------
    CampaignError
        Fewer points than the line and its steps need.
    """
    if len(series) < 2 + len(steps):
        raise CampaignError(f"{series.name}: {len(series)} identified window(s) cannot give a drift"
                            f"{' with ' + str(len(steps)) + ' step(s)' if steps else ''} (at least "
                            f"{2 + len(steps)} needed)")
    line = _line(series, steps)
    slope = float(line.coef[1])
    stated = float(np.sqrt(abs(line.cov[1, 1])))
    red = line.chi2 / line.dof if line.dof > 0 else math.nan
    inflated = bool(inflate and line.dof > 0 and red > 1.0)
    return Drift(series.name, slope, stated * math.sqrt(red) if inflated else stated, stated, red, line.dof,
                 len(series), inflated, tuple(series.where(s) for s in steps), series.time_unit,
                 series.seconds_per_unit, series.display)


# --- change points ----------------------------------------------------------------------------------------------

@dataclasses.dataclass(frozen=True)
class Step:
    """One candidate boundary: the jump fitted there (with the drift and the steps flagged before it).

    ``size``, ``std`` [SI]; ``z = size / std``; ``p``: two-sided p-value of this boundary alone; ``p_bound``:
    the Bonferroni bound ``min(1, m p)`` over the ``m`` candidates of its stage (set for the best candidate of
    each stage); ``flagged``: ``p_bound`` (or the simulated p-value) at most ``alpha``.
    """

    index: int
    at: str
    before: str
    time: float
    size: float
    std: float
    z: float
    p: float
    stage: int = 1
    p_bound: float | None = None
    p_simulated: float | None = None
    m: int = 0
    scale: float = 1.0
    flagged: bool = False

    def to_json(self, display=("µm", 1e6), time_unit: str = "s") -> dict:
        unit, f = display
        key = _key(unit)
        return {"at": self.at, "after": self.before, f"time_{time_unit}": self.time, f"jump_{key}": self.size * f,
                f"std_{key}": self.std * f, "z": self.z, "p": self.p, "stage": self.stage,
                "p_bonferroni": self.p_bound, "p_simulated": self.p_simulated, "candidates": self.m,
                "error_scale": self.scale, "flagged": self.flagged}


@dataclasses.dataclass(frozen=True)
class ChangePoints:
    """The change-point test of one parameter.

    Attributes
    ----------
    name : str
    scan : tuple of Step
        Stage 1: every candidate boundary's jump over its standard error, drift removed jointly.
    tests : tuple of Step
        The best candidate of each stage with its Bonferroni bound (flagged, or the one that stopped the search).
    flagged : tuple of Step
        The flagged steps, sizes and errors from the final model (drift and every flagged step).
    alpha : float
    drift : str
        How the drift entered: ``fitted``, ``none`` or ``given: slope ± std``.
    method : str
        ``bonferroni``, ``simulation`` (:func:`change_points`) or ``differences`` (:func:`differences`).
    """

    name: str
    scan: tuple
    tests: tuple
    flagged: tuple
    alpha: float
    drift: str
    method: str
    display: tuple = ("µm", 1e6)
    time_unit: str = "s"

    @property
    def steps(self) -> tuple[int, ...]:
        """Indices of the flagged steps, in time order (for :func:`drift`)."""
        return tuple(sorted(s.index for s in self.flagged))

    def to_json(self) -> dict:
        return {"parameter": self.name, "alpha": self.alpha, "drift": self.drift, "method": self.method,
                **{key: [s.to_json(self.display, self.time_unit) for s in getattr(self, key)]
                   for key in ("flagged", "tests", "scan")}}


def _how(prior, series: Series) -> str:
    """How the drift enters a test, in words: ``fitted``, ``none`` or ``given: slope ± std unit/time``."""
    if prior is None:
        return "fitted"
    if prior == (0.0, 0.0):
        return "none"
    unit, f = series.display
    return f"given: {prior[0] * f:+.4g} ± {prior[1] * f:.2g} {unit}/{series.time_unit}"


def _excess(line: _Line, scatter_p: float) -> bool:
    """The scatter about ``line`` exceeds its error bars beyond chance: P(χ²_dof >= χ²) < ``scatter_p``."""
    from scipy import stats

    return line.dof > 0 and line.chi2 > line.dof and float(stats.chi2.sf(line.chi2, line.dof)) < scatter_p


def _p_two_sided(z: float, dof: int | None) -> float:
    from scipy import stats

    return float(2 * (stats.t.sf(abs(z), dof) if dof else stats.norm.sf(abs(z))))


def _scan(series: Series, flagged: list[int], cands: list[int], prior) -> list[tuple[int, _Line, float, float]]:
    out = []
    for tau in cands:
        try:
            line = _line(series, sorted([*flagged, tau]), prior)
        except CampaignError:
            continue
        d, sd = line.step(sorted([*flagged, tau]).index(tau))
        out.append((tau, line, d, sd))
    return out


def _simulated_p(series, flagged, cands, prior, observed: float, n_sim: int, rng) -> float:
    """Monte Carlo p-value of ``max_τ z_τ²`` under the model with the ``flagged`` steps only, the errors taken as
    known (``observed`` already divided by the square of any error scale)."""
    a0, r0, _ = _design(series, sorted(flagged), prior)
    null = _line(series, sorted(flagged), prior)
    mean = a0 @ null.coef
    sims = mean[:, None] + rng.standard_normal((len(r0), n_sim))
    best = np.zeros(n_sim)
    for tau in cands:
        steps = sorted([*flagged, tau])
        try:
            line = _line(series, steps, prior)
        except CampaignError:
            continue
        a, _, first = _design(series, steps, prior)
        j = first + steps.index(tau)
        coef = line.cov @ a.T @ sims
        best = np.maximum(best, coef[j] ** 2 / line.cov[j, j])
    return float((1 + np.sum(best >= observed)) / (1 + n_sim))


def change_points(series: Series, *, alpha: float = ALPHA, drift: object = "fit", max_changes: int | None = None,
                  method: str = "bonferroni", n_sim: int = 2000, seed: int = 0, inflate: bool = True,
                  scatter_p: float = SCATTER_P) -> ChangePoints:
    """Steps in ``series`` beyond its drift and noise (the module docstring gives the test and its references).

    Parameters
    ----------
    series : Series
    alpha : float
        False-alarm probability per stage (and so, for the first flag, per parameter and campaign).
    drift : "fit", "none", Drift or (slope, std)
        ``fit``: the slope is fitted jointly with each candidate step (needs a few windows on either side);
        ``none``: no drift; a :class:`Drift` or ``(slope, std)`` [SI per time unit]: a drift measured
        elsewhere, entered as a Gaussian constraint on the slope.
    max_changes : int, optional
        Stop after this many flagged steps (default: until no candidate is significant).
    method : {"bonferroni", "simulation"}
        Which p-value decides: the Bonferroni bound, or ``n_sim`` simulations of the model without the step.
    inflate : bool
        When the model under test (drift, the steps flagged so far and the candidate) scatters beyond the error
        bars by more than chance (χ² p-value below ``scatter_p``), scale its errors by its Birge ratio; the
        p-value then comes from Student's t with its degrees of freedom.
    """
    if method not in ("bonferroni", "simulation"):
        raise ValueError(f"method must be 'bonferroni' or 'simulation', got {method!r}")
    prior = _slope_prior(drift)
    rng = np.random.default_rng(seed)
    remaining, flagged, tests, scan = series.candidates(), [], [], ()
    while remaining and (max_changes is None or len(flagged) < max_changes):
        found = _scan(series, flagged, remaining, prior)
        if not found:
            break
        z2 = [(d / sd) ** 2 for _, _, d, sd in found]
        if not scan:
            scan = tuple(Step(tau, series.where(tau), series.labels[tau - 1], float(series.t[tau]), d, sd, d / sd,
                              _p_two_sided(d / sd, None)) for tau, _, d, sd in found)
        tau, line, d, sd = found[int(np.argmax(z2))]
        scale, dof = (line.birge, line.dof) if inflate and _excess(line, scatter_p) else (1.0, None)
        z = d / (sd * scale)
        p = _p_two_sided(z, dof)
        bound = min(1.0, len(found) * p)
        sim = (_simulated_p(series, flagged, remaining, prior, max(z2) / scale**2, n_sim, rng)
               if method == "simulation" else None)
        hit = (sim if method == "simulation" else bound) <= alpha
        tests.append(Step(tau, series.where(tau), series.labels[tau - 1], float(series.t[tau]), d, sd * scale, z, p,
                          len(tests) + 1, bound, sim, len(found), scale, hit))
        if not hit:
            break
        flagged.append(tau)
        remaining = [c for c in remaining if c != tau]
    final = ()
    if flagged:
        line = _line(series, sorted(flagged), prior)
        scale = line.birge if inflate and _excess(line, scatter_p) else 1.0
        by_index = {s.index: s for s in tests}
        final = tuple(dataclasses.replace(by_index[tau], size=line.step(k)[0], std=line.step(k)[1] * scale,
                                          z=line.step(k)[0] / (line.step(k)[1] * scale))
                      for k, tau in enumerate(sorted(flagged)))
    return ChangePoints(series.name, scan, tuple(tests), final, alpha, _how(prior, series), method, series.display,
                        series.time_unit)


def differences(series: Series, *, drift: object = "none", alpha: float = ALPHA) -> ChangePoints:
    """The jump at every candidate boundary as the difference of its two neighbours less the drift between them,
    over its combined standard error: ``z = (y_j - y_{j-1} - b Δt) / sqrt(s_j² + s_{j-1}² + Δt² s_b²)``.

    This is the test of the model with a step at *every* boundary (a drift ``b ± s_b`` measured elsewhere, or
    none), each boundary judged on its own and flagged when the Bonferroni bound ``m p`` over the ``m``
    boundaries is at most ``alpha``.  Unlike :func:`change_points` it needs no windows beyond the two
    neighbours, so it suits a few experiments with a drift known from inside them (the paper's Table 1).
    A drift fitted on the same series would be correlated with the differences: give one from other data.
    """
    prior = _slope_prior(drift)
    if prior is None:
        raise ValueError("differences needs the drift as 'none', a Drift or (slope, std) from other data")
    b, sb = prior
    cands = series.candidates()
    steps = []
    for tau in cands:
        dt = float(series.t[tau] - series.t[tau - 1])
        d = float(series.y[tau] - series.y[tau - 1]) - b * dt
        sd = math.sqrt(series.s[tau] ** 2 + series.s[tau - 1] ** 2 + (dt * sb) ** 2)
        p = _p_two_sided(d / sd, None)
        bound = min(1.0, len(cands) * p)
        steps.append(Step(tau, series.where(tau), series.labels[tau - 1], float(series.t[tau]), d, sd, d / sd, p,
                          1, bound, None, len(cands), 1.0, bound <= alpha))
    return ChangePoints(series.name, tuple(steps), tuple(steps), tuple(s for s in steps if s.flagged), alpha,
                        _how(prior, series), "differences", series.display, series.time_unit)


# --- the whole campaign ------------------------------------------------------------------------------------------

@dataclasses.dataclass(frozen=True)
class Campaign:
    """Windows, drift and change points of one campaign (:func:`analyse`).

    Attributes
    ----------
    windows : tuple of Window
        Every window with readings, identified or not (``problem`` says why not).
    used : tuple of int
        Indices of the windows the drift and change-point tests use (identified, sharing no readings).
    drifts : dict
        Parameter name -> :class:`Drift`, or the reason there is none (str).
    changes : dict
        Parameter name -> :class:`ChangePoints`, or the reason there are none (str).
    mode : str
        How the windows were cut (``by experiment`` or ``windows of 3600 s every 3600 s``).
    notes : tuple of str
    """

    windows: tuple
    used: tuple
    drifts: dict
    changes: dict
    alpha: float
    mode: str
    source: str = "<data>"
    notes: tuple = ()

    @property
    def failed(self) -> list[Window]:
        """The windows that could not be identified."""
        return [w for w in self.windows if not w.identified]

    @property
    def jumps(self) -> dict[str, list[str]]:
        """Where a step was flagged -> the parameters that jump there."""
        out: dict[str, list[str]] = {}
        for name, cp in self.changes.items():
            if isinstance(cp, ChangePoints):
                for s in cp.flagged:
                    out.setdefault(s.at, []).append(name)
        return out

    def table(self) -> pd.DataFrame:
        """One row per window: span, centre [s], rows, experiments, estimates and errors [µm, N·m²/A²], χ²/dof,
        whether the tests use it, and why a window is not identified."""
        from ambfit.estimation.results import CONTRACT_PARAMS

        rows = []
        for j, w in enumerate(self.windows):
            row = {"window": w.label, "start_s": w.start_s, "end_s": w.end_s, "centre_s": w.centre_s,
                   "rows": w.n_rows, "experiments": "+".join(w.experiments), "identified": w.identified,
                   "used": j in self.used}
            for name, key, f in CONTRACT_PARAMS:
                v, s = w.estimate(name)
                row[key], row[key.replace("_um", "_std_um") if key.endswith("_um") else key + "_std"] = v * f, s * f
            row["reduced_chi2"] = w.fit.reduced_chi2 if w.fit is not None else math.nan
            row["problem"] = w.problem
            rows.append(row)
        return pd.DataFrame(rows)

    def drift_table(self) -> pd.DataFrame:
        """One row per parameter: drift per hour (and per second) ± error [µm], z, χ²/dof, note."""
        rows = []
        for name, d in self.drifts.items():
            if isinstance(d, Drift):
                ph = d.per_hour()
                rows.append({"parameter": name, "drift_um_per_h": ph[0] * 1e6, "std_um_per_h": ph[1] * 1e6,
                             "drift_um_per_s": d.slope * 1e6, "z": d.z, "reduced_chi2": d.reduced_chi2,
                             "windows": d.n, "note": d.note()})
            else:
                rows.append({"parameter": name, "note": d})
        return pd.DataFrame(rows)

    def change_table(self) -> pd.DataFrame:
        """One row per parameter and tested boundary (the best of each stage): jump ± error [µm], z, Bonferroni
        p, flagged."""
        rows = []
        for name, cp in self.changes.items():
            if not isinstance(cp, ChangePoints):
                rows.append({"parameter": name, "note": cp})
                continue
            final = {s.index: s for s in cp.flagged}
            for s in cp.tests:
                s = final.get(s.index, s)
                rows.append({"parameter": name, "at": s.at, "after": s.before, "jump_um": s.size * 1e6,
                             "std_um": s.std * 1e6, "z": s.z, "p_bonferroni": s.p_bound, "candidates": s.m,
                             "flagged": s.flagged})
        return pd.DataFrame(rows)

    def to_json(self) -> dict:
        def entry(v):
            return v.to_json() if hasattr(v, "to_json") else {"error": v}

        return {"source": self.source, "mode": self.mode, "alpha": self.alpha,
                "windows": [w.to_json() for w in self.windows], "used": [self.windows[j].label for j in self.used],
                "drift": {n: entry(d) for n, d in self.drifts.items()},
                "change_points": {n: entry(c) for n, c in self.changes.items()},
                "jumps": self.jumps, "notes": list(self.notes)}

    def summary(self) -> str:
        ok = sum(w.identified for w in self.windows)
        lines = [f"campaign ({self.mode}): {len(self.windows)} windows, {ok} identified, {len(self.used)} used"]
        lines += [f"  drift {d.text()}" + (f" ({d.note()})" if d.note() else "") if isinstance(d, Drift)
                  else f"  drift {n}: {d}" for n, d in self.drifts.items()]
        for where, names in self.jumps.items():
            lines.append(f"  change point at {where}: {', '.join(names)}")
        lines += [f"  ! {w.label}: {w.problem}" for w in self.failed]
        lines += [f"  note: {n}" for n in self.notes]
        return "\n".join(lines)

    __str__ = summary

    def _repr_html_(self) -> str:
        import html

        ok = sum(w.identified for w in self.windows)
        head = (f"<b>campaign ({html.escape(self.mode)})</b>: {len(self.windows)} windows, {ok} identified, "
                f"{len(self.used)} used")
        jumps = "".join(f"<li>change point at {html.escape(w)}: {html.escape(', '.join(n))}</li>"
                        for w, n in self.jumps.items()) or "<li>no change point</li>"
        bad = "".join(f"<li>{html.escape(w.label)}: {html.escape(w.problem)}</li>" for w in self.failed)
        return (head + self.drift_table().to_html(index=False, float_format=lambda v: f"{v:.4g}") +
                f"<ul>{jumps}{bad}</ul>")


def analyse(data, *, width_s: float | None = None, step_s: float | None = None, by: str | None = None,
            alpha: float = ALPHA, method: str = "bonferroni", bearing: Bearing = PAPER_BEARING, progress=None,
            **fit_kw) -> Campaign:
    """Identify a campaign window by window; the drift and change points of gap and origin.

    Parameters
    ----------
    data : Dataset or DataFrame
        Contract table with ``time_s`` on one clock over the whole campaign [s].
    width_s, step_s : float, optional
        Rolling windows of this width [s], every ``step_s`` (default: the width); see :func:`windows`.
    by : str, optional
        One window per value of this column (``"experiment"``).  Default: by experiment when ``width_s`` is
        not given.
    alpha : float
        False-alarm probability of the change-point test per parameter.
    method : {"bonferroni", "simulation"}
        The change-point test's p-value (:func:`change_points`).
    bearing : Bearing
    progress : callable, optional
        ``progress(what, done, total)`` per fitted window.
    **fit_kw
        Passed to :func:`ambfit.estimation.fit.fit` (``sigma_i``, ``loss``, ...).
    """
    frame, source = _frame(data)
    if width_s is not None and by is not None:
        raise ValueError("give either width_s (rolling windows) or by (one window per value of a column), not both")
    if width_s is None:
        by = by or "experiment"
        wins, mode = by_experiment(data, by), f"by {by}"
    else:
        wins = windows(data, width_s, step_s)
        mode = f"windows of {width_s:g} s every {step_s or width_s:g} s"
    wins = identify(wins, bearing=bearing, progress=progress, **fit_kw)
    notes = []
    keep = independent(wins)
    if len(keep) < len(wins):
        notes.append(f"the windows overlap (step {step_s:g} s < width {width_s:g} s): neighbouring estimates share "
                     f"readings, so the drift and change-point tests use the {len(keep)} windows that do not")
    used = tuple(j for j in keep if wins[j].identified)
    chosen = [wins[j] for j in used]
    drifts, changes = {}, {}
    for name in PARAMS:
        series = Series.from_windows(chosen, name)
        if len(series) < 3:
            drifts[name] = changes[name] = (f"{len(series)} identified window(s) estimate {name}: a drift with an "
                                            "error check needs at least 3")
            continue
        cp = change_points(series, alpha=alpha, method=method)
        changes[name] = cp
        try:
            drifts[name] = drift(series, steps=cp.steps)
        except CampaignError as exc:
            drifts[name] = str(exc)
    if "experiment" not in frame.columns:
        notes.append("the data name no experiments: change points are tested between every two windows")
    return Campaign(tuple(wins), used, drifts, changes, alpha, mode, source, tuple(notes))


# --- the seed paper's tables as a campaign -------------------------------------------------------------------------

@dataclasses.dataclass(frozen=True)
class PaperOrigins:
    """The paper's Tables 1 and 2 read as a campaign over iterations (:func:`paper_origins`).

    Attributes
    ----------
    drifts : dict
        Parameter -> :class:`Drift` inside Table 2 [m per iteration].
    moves : dict
        Parameter -> :func:`differences` between Table 1's consecutive experiments, noise only (no drift).
    changes : dict
        Parameter -> :func:`differences` between Table 1's consecutive experiments, Table 2's drift (with its
        error) removed.
    first : int
        The first Table 2 iteration used (iteration 1 ran before the rotor was re-centred).
    iterations : int
        Iterations per experiment (Table 2's rows): each Table 1 row is their mean.
    sd : dict
        Parameter -> per-iteration sd of Table 2's iterations ``first``..``iterations`` [m]: each iteration's error,
        and over ``sqrt(iterations)`` each Table 1 row's.
    source : int
        Table 1's row whose iterations Table 2 lists.
    """

    drifts: dict
    moves: dict
    changes: dict
    first: int
    iterations: int
    sd: dict
    source: int


def paper_origins(*, first: int = 2, source: int = 2, alpha: float = ALPHA) -> PaperOrigins:
    """Drift inside the paper's Table 2 and change points between Table 1's experiments.

    The paper gives estimates, not readings, and no times, so the clock is the iteration: Table 1's three
    experiments are taken to have run one after another, 10 iterations each (experiment ``e`` at iterations
    ``10 (e - 1) + 1 .. 10 e``, its mean at their centre), Table 2 being the iterations of experiment
    ``source``.  Errors: each iteration's is the per-iteration sd of Table 2's iterations ``first``..10, each
    Table 1 row's that over ``sqrt(10)`` (the three experiments are assumed as noisy as Table 2's).  Each
    boundary is tested by :func:`differences` twice: against noise alone (did the origin move?) and with Table
    2's drift removed, its error included (did it move more than Table 2's drift explains?).  Three experiments
    cannot separate a drift from a jump on their own.
    """
    from ambfit.studies import paper

    t2, t1 = paper.load_table(2), paper.load_table(1)
    n = len(t2)
    it = t2["iteration"].to_numpy(float)
    keep = it >= first
    sel = t1["source_row"].astype(int).to_numpy()
    centre = (sel - 1) * n + 0.5 * (n + 1)
    drifts, moves, changes, sd = {}, {}, {}, {}
    for name in PARAMS:
        y = t2[f"{name}_um"].to_numpy(float)[keep] * 1e-6
        sd[name] = float(np.std(y, ddof=1))
        inside = Series(name, (source - 1) * n + it[keep], y, np.full(len(y), sd[name]),
                        labels=tuple(f"iteration {int(k)}" for k in it[keep]), time_unit="iteration",
                        seconds_per_unit=None)
        drifts[name] = drift(inside)
        between = Series(name, centre, t1[f"{name}_um"].to_numpy(float) * 1e-6,
                         np.full(len(t1), sd[name] / math.sqrt(n)), labels=tuple(str(r) for r in sel),
                         groups=tuple(str(r) for r in sel), time_unit="iteration", seconds_per_unit=None)
        moves[name] = differences(between, alpha=alpha)
        changes[name] = differences(between, drift=drifts[name], alpha=alpha)
    return PaperOrigins(drifts, moves, changes, first, n, sd, source)
