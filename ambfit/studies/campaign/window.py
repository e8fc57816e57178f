"""A campaign's windows of time: cutting the contract table into windows and identifying each.

Rolling windows of ``time_s`` (:func:`windows`) or one window per experiment (:func:`by_experiment`);
:func:`identify` fits each by least squares; :func:`independent` picks windows that share no readings.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence

import numpy as np
import pandas as pd

from ambfit.data import DataError, Dataset
from ambfit.estimation.units import GEOMETRY
from ambfit.physics.bearing import PAPER_BEARING, Bearing

PARAMS = GEOMETRY

MAX_WINDOWS = 2_000
"""Rolling windows a campaign may be cut into: each is a least-squares fit of its own (a tenth of a second to a
second), so 2,000 are minutes of work; a width or step of a nanosecond would ask for billions."""

MAX_WINDOW_ROWS = 2_000_000
"""Readings all windows may hold together: overlapping windows each copy their readings (a step a thousandth of
the width holds every reading a thousand times)."""
"""The parameters whose drift and jumps a campaign studies (internal names, SI)."""


class CampaignError(ValueError):
    """A series too short for the requested analysis (too few identified windows)."""


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
    t0, span = float(t.min()), float(t.max() - t.min())
    n = math.floor(span / step) + 1
    if n > MAX_WINDOWS:
        raise DataError(f"windows every {step:g} s over the campaign's {span:g} s would be {n:.3g} windows, each a "
                        f"fit of its own; at most {MAX_WINDOWS:,} (minutes of work): give a longer step or window",
                        file=source, column="time_s")
    ts = np.sort(t)
    starts = t0 + step * np.arange(n)
    held = int(np.sum(np.searchsorted(ts, starts + width_s, side="left") - np.searchsorted(ts, starts, side="left")))
    if held > MAX_WINDOW_ROWS:
        raise DataError(f"windows {width_s:g} s wide every {step:g} s would hold {held:.3g} readings together (each "
                        f"reading in about {held / len(t):.0f} windows); at most {MAX_WINDOW_ROWS:,}: give a step "
                        "closer to the width", file=source, column="time_s")
    out = []
    for k in range(n):
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
