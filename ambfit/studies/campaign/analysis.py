"""A whole campaign analysed: windows identified, then each parameter's drift and change points."""

from __future__ import annotations

import dataclasses
import math

import pandas as pd

from ambfit.physics.bearing import PAPER_BEARING, Bearing
from ambfit.studies.campaign.series import Drift, Series, drift
from ambfit.studies.campaign.steps import ALPHA, ChangePoints, change_points
from ambfit.studies.campaign.window import (
    PARAMS,
    CampaignError,
    Window,
    _frame,
    by_experiment,
    identify,
    independent,
    windows,
)


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
        from ambfit.estimation.units import CONTRACT_PARAMS

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
