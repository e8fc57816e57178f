"""One parameter's estimates over a campaign, the weighted least-squares line through them and its drift.

A :class:`Series` holds ``y_j ± s_j`` at times ``t_j``; :func:`_line` fits ``y = a + b t`` plus any
steps by weighted least squares; :func:`drift` reports the slope, its error scaled by the Birge
ratio when the scatter exceeds the error bars (see :mod:`ambfit.studies.campaign`).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence

import numpy as np

from ambfit.rig.campaign import HOUR
from ambfit.studies.campaign.window import PARAMS, CampaignError, Window


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
