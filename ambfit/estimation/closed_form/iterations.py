"""The paper's tables: a data set's iterations (experiment, iteration and axis) solved by Eq. 5-7 and averaged,
with the mean's standard error and the checks that say whether to trust it (:func:`identify`)."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pandas as pd

from ambfit.data import Dataset
from ambfit.estimation.closed_form import agreement
from ambfit.estimation.closed_form.equations import ClosedFormError, Solution, position_labels, solve
from ambfit.physics.bearing import AXES, PAPER_BEARING, Bearing

MAX_RELATIVE_SEM = 0.05
"""The mean gap of an axis is trusted when its standard error is below this fraction of it."""

MAX_REJECTED_FRACTION = 0.5
"""More rejected iterations than this fraction: the protocol does not suit the noise, the mean is not trusted."""

MAX_SCATTER_RATIO = 2.0
"""Iteration-to-iteration scatter of the gap above this multiple of the scatter the noise predicts is flagged."""

@dataclasses.dataclass(frozen=True)
class AxisEstimate:
    """Mean over iterations of one axis' closed-form solutions (SI units).

    ``*_sem`` is the standard error of the mean (std / sqrt(n), NaN for n < 2);
    ``*_std`` the iteration-to-iteration scatter.  ``iterations`` holds the
    per-iteration :class:`Solution` records (for plots), ``rejected`` the
    iterations that could not be solved and why; ``reference`` least squares on
    the same readings (:mod:`~ambfit.estimation.closed_form.agreement`), None when not compared.
    """

    axis: str
    experiment: str
    g0: float
    g0_sem: float
    g0_std: float
    x0: float
    x0_sem: float
    x0_std: float
    k: float
    k_sem: float
    iterations: dict
    rejected: dict
    reference: agreement.Reference | None = None

    @property
    def n(self) -> int:
        return len(self.iterations)

    def interval(self, name: str = "g0", level: float = agreement.LEVEL) -> tuple[float, float]:
        """Level-``level`` interval of ``g0``, ``x0`` or ``k`` [SI]: mean ± Student t (n - 1 dof) x standard error."""
        return agreement.interval(getattr(self, name), getattr(self, f"{name}_sem"), self.n, level)

    @property
    def g0_std_predicted(self) -> float:
        """Iteration-to-iteration std of the gap that the current noise alone predicts (NaN when unknown)."""
        pred = [s.g0_std_predicted for s in self.iterations.values() if np.isfinite(s.g0_std_predicted)]
        return float(np.sqrt(np.mean(np.square(pred)))) if pred else math.nan

    def checks(self) -> list[tuple[str, bool | None, str]]:
        """Health of this axis' mean as ``(name, passed, cause and fix)`` (``passed`` None: cannot be judged)."""
        where = f"closed form, axis {self.axis}" + (f", experiment {self.experiment}" if self.experiment != "all" else "")
        total = self.n + len(self.rejected)
        rel = self.g0_sem / self.g0 if self.n > 1 and self.g0 > 0 else math.nan
        ratio = self.g0_std / self.g0_std_predicted if np.isfinite(self.g0_std_predicted) and self.n > 2 else math.nan
        return [
            ("enough_iterations", self.n >= 2,
             f"{where}: {self.n} usable iteration(s) of {total}; a mean needs at least two to have an error bar"),
            ("few_rejected", len(self.rejected) <= MAX_REJECTED_FRACTION * total,
             f"{where}: {len(self.rejected)} of {total} iterations rejected (ill-conditioned or non-physical); the "
             "rest are the lucky draws of a protocol whose bias step is too small for this noise, so their mean is "
             "biased; use least squares, a larger bias step or more readings per set-point"),
            ("precise", None if not np.isfinite(rel) else bool(rel <= MAX_RELATIVE_SEM),
             f"{where}: the gap's standard error is {100 * rel:.0f} % of the gap (trusted below "
             f"{100 * MAX_RELATIVE_SEM:.0f} %); Eq. 6 is too noisy at this protocol; use least squares (all readings) "
             "or more iterations"),
            ("scatter_as_predicted", None if not np.isfinite(ratio) else bool(ratio <= MAX_SCATTER_RATIO),
             f"{where}: the iterations' gaps scatter {ratio:.1f} times more than the current noise predicts "
             f"({self.g0_std * 1e6:.3g} µm against {self.g0_std_predicted * 1e6:.3g} µm): the load or the origin "
             "changed between iterations, or the noise is larger than the std columns say"),
            agreement.check(self),
        ]


def _mean_sem(values):
    v = np.asarray([a for a in values if np.isfinite(a)], dtype=float)
    if v.size == 0:
        return math.nan, math.nan, math.nan
    std = float(np.std(v, ddof=1)) if v.size > 1 else math.nan
    return float(np.mean(v)), std / math.sqrt(v.size) if v.size > 1 else math.nan, std


def solve_rows(df: pd.DataFrame, *, bearing: Bearing = PAPER_BEARING) -> Solution:
    """Solve one iteration of one axis from its contract rows (see :func:`solve`).

    Positions are the own-axis set-points when every row has one, else the measured positions clustered within
    ``POSITION_TOLERANCE`` (:func:`~ambfit.estimation.closed_form.equations.position_labels`); replicated
    readings at one position and bias are averaged.
    """
    own = f"{df['axis'].iloc[0]}_um"
    labels = position_labels(df, set_point_tolerance=1e-9)     # a set-point is a commanded value: equal or not
    bias = df["bias_A"].to_numpy(float)
    biases = np.unique(bias)
    if len(biases) != 2:
        raise ClosedFormError(f"Eq. 6 needs exactly two bias settings per iteration, found {biases.tolist()} A")
    n_pos = int(labels.max()) + 1                              # (labels number the positions 0, 1, ...)
    cell = labels * 2 + np.searchsorted(biases, bias)          # (position, bias)
    position = _means(df[own].to_numpy(float), labels, n_pos)
    count = np.bincount(cell, minlength=2 * n_pos).reshape(n_pos, 2)
    if not count.all():
        p, b = np.argwhere(count == 0)[0]
        raise ClosedFormError(f"position {position[p]:.4g} µm has no reading at bias {biases[b]:g} A: each position "
                              "needs both biases")
    if "load_id" in df.columns:
        ids = pd.factorize(df["load_id"])[0]                   # (a missing id is no id: -1)
        known = ids >= 0
        lo, hi = np.full(n_pos, np.iinfo(np.int64).max), np.full(n_pos, -1)
        np.minimum.at(lo, labels[known], ids[known])
        np.maximum.at(hi, labels[known], ids[known])
        mixed = np.nonzero((hi >= 0) & (lo != hi))[0]
        if len(mixed):
            p = mixed[0]
            found = sorted(df["load_id"][labels == p].dropna().unique().tolist())
            raise ClosedFormError(f"position {position[p]:.4g} µm: the two biases carry different loads {found}; "
                                  "Eq. 5 needs the same load")
    it = _means(df["i_top_A"].to_numpy(float), cell, 2 * n_pos).reshape(n_pos, 2)
    ib = _means(df["i_bottom_A"].to_numpy(float), cell, 2 * n_pos).reshape(n_pos, 2)
    loads = (_means(df["load_N"].to_numpy(float), cell, 2 * n_pos).reshape(n_pos, 2) if "load_N" in df.columns
             else np.full((n_pos, 2), math.nan))
    xs = position * 1e-6
    sigma = None
    if all(c in df.columns for c in ("i_top_std_A", "i_bottom_std_A")):
        std = df[["i_top_std_A", "i_bottom_std_A"]].to_numpy(float)
        sigma = float(np.mean(std)) if np.isfinite(std).all() else None
    n_avg = max(1, len(df) // (2 * len(xs)))
    return solve(xs, it, ib, biases=tuple(biases), loads=loads, bearing=bearing, sigma_i=sigma, n_avg=n_avg)


def _means(values: np.ndarray, group: np.ndarray, n: int) -> np.ndarray:
    """Each group's mean of ``values``, missing values left out (NaN for a group with none), as pandas' mean."""
    known = ~np.isnan(values)
    total = np.bincount(group[known], weights=values[known], minlength=n)
    count = np.bincount(group[known], minlength=n)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(count > 0, total / count, np.nan)


@dataclasses.dataclass(frozen=True)
class ClosedFormResult:
    """Closed-form identification of a data set: one :class:`AxisEstimate` per (experiment, axis)."""

    estimates: dict  # {(experiment, axis): AxisEstimate}
    n_rows: int
    by_experiment: bool

    def params(self, experiment: str = "all") -> dict:
        """Contract parameter block (µm, N m^2/A^2) for one experiment key."""
        out = {}
        names = {"v": ("g_v0_um", "v0_um", "k_v_Nm2_per_A2"), "w": ("g_w0_um", "w0_um", "k_w_Nm2_per_A2")}
        for ax in AXES:
            est = self.estimates.get((experiment, ax))
            if est is None or est.n == 0:
                continue
            gn, xn, kn = names[ax]
            out[gn] = {"value": est.g0 * 1e6, "std": _none(est.g0_sem * 1e6)}
            out[xn] = {"value": est.x0 * 1e6, "std": _none(est.x0_sem * 1e6)}
            if np.isfinite(est.k):
                out[kn] = {"value": est.k, "std": _none(est.k_sem)}
        return out

    def display_rows(self) -> list[dict]:
        """One ``{column: text}`` row per (experiment, axis): mean ± standard error over iterations."""
        from ambfit.estimation.units import pm

        level = f"{100 * agreement.LEVEL:.0f} %"
        return [{"experiment": exp, "axis": ax, "iterations": str(e.n), "gap [µm]": pm(e.g0 * 1e6, e.g0_sem * 1e6),
                 f"gap {level} [µm]": _span(e.interval("g0"), 1e6),
                 "origin [µm]": pm(e.x0 * 1e6, e.x0_sem * 1e6), f"origin {level} [µm]": _span(e.interval("x0"), 1e6),
                 "k [N·m²/A²]": pm(e.k, e.k_sem) if np.isfinite(e.k) else "–", "rejected": str(len(e.rejected))}
                for (exp, ax), e in self.estimates.items()]

    def checks(self) -> list[tuple[str, bool | None, str]]:
        """Every axis' health checks (:meth:`AxisEstimate.checks`)."""
        return [c for e in self.estimates.values() for c in e.checks()]

    def health(self) -> list[str]:
        """Every failed check as a sentence with its cause and fix (empty when the result can be trusted)."""
        return [text for _, ok, text in self.checks() if ok is False]

    @property
    def trusted(self) -> bool:
        """Every axis has at least two iterations, few rejections, a precise mean and scatter its noise explains."""
        return not self.health()

    def rejections(self) -> list[str]:
        """Each rejected iteration and why."""
        return [f"rejected {exp}/{ax} iteration {it}: {why}" for (exp, ax), e in self.estimates.items()
                for it, why in e.rejected.items()]

    def to_dataframe(self) -> pd.DataFrame:
        """One row per (experiment, axis) in SI units: n, g0, x0, k and their standard errors."""
        return pd.DataFrame([{"experiment": exp, "axis": ax, "n": e.n, "g0": e.g0, "g0_sem": e.g0_sem, "x0": e.x0,
                              "x0_sem": e.x0_sem, "k": e.k, "k_sem": e.k_sem, "rejected": len(e.rejected)}
                             for (exp, ax), e in self.estimates.items()])

    def summary(self) -> str:
        lines = [f"closed form (Eq. 5-7), {self.n_rows} rows"]
        lines += ["  " + ", ".join(f"{k} {v}" for k, v in r.items()) for r in self.display_rows()]
        return "\n".join(lines + ["  " + r for r in self.rejections()])

    __str__ = summary

    def _repr_html_(self) -> str:
        return self.to_dataframe().to_html(index=False)

    def to_json(self) -> dict:
        """The contract section 2 record (plus per-axis detail)."""
        keys = sorted({e for e, _ in self.estimates})
        main = "all" if "all" in keys else keys[0]
        detail = {}
        for (exp, ax), est in self.estimates.items():
            detail.setdefault(exp, {})[ax] = {
                "n_iterations": est.n,
                "g0_scatter_um": _none(est.g0_std * 1e6),
                "g0_scatter_predicted_um": _none(est.g0_std_predicted * 1e6),
                "x0_scatter_um": _none(est.x0_std * 1e6),
                "iterations": {str(i): {"g0_um": s.g0 * 1e6, "x0_um": s.x0 * 1e6, "condition": s.condition,
                                         "ratios": s.ratios.tolist()} for i, s in est.iterations.items()},
                "rejected": {str(i): r for i, r in est.rejected.items()},
                "interval": _intervals(est),
                "least_squares": _reference_json(est),
            }
        out = {
            "method": "closed_form",
            "params": self.params(main),
            "converged": all(e.n > 0 for e in self.estimates.values()),
            "trusted": self.trusted, "health": self.health(),
            "n_rows": self.n_rows,
            "std_meaning": "standard error of the mean over iterations (null with one iteration); detail's interval: "
                           f"{100 * agreement.LEVEL:g} % interval, mean ± Student t (n - 1 dof) x standard error",
            "detail": detail,
        }
        if self.by_experiment:
            out["experiments"] = {k: self.params(k) for k in keys}
        return out


def _none(x):
    return None if not np.isfinite(x) else float(x)


def _reference(ls, axis: str) -> agreement.Reference | None:
    """One axis of the least-squares reference: None when not asked for, the reason when it failed."""
    if ls is None:
        return None
    if isinstance(ls, Exception):
        return agreement.Reference(why=f"least squares on the same readings failed: {ls}")
    if f"g_{axis}0" not in ls.names:
        return agreement.Reference(why=f"least squares has no axis {axis}")
    return agreement.Reference.of(ls, axis)


def _intervals(est: AxisEstimate) -> dict:
    """The t intervals of gap and origin [µm] (and k) with their level and degrees of freedom."""
    out = {"level": agreement.LEVEL, "dof": est.n - 1 if est.n > 1 else None}
    for name, key, f in (("g0", "g0_um", 1e6), ("x0", "x0_um", 1e6), ("k", "k_Nm2_per_A2", 1.0)):
        lo, hi = est.interval(name)
        out[key] = [_none(lo * f), _none(hi * f)]
    return out


def _span(lo_hi, f: float) -> str:
    lo, hi = lo_hi
    return f"{lo * f:.4g} – {hi * f:.4g}" if np.isfinite(lo) and np.isfinite(hi) else "–"


def _reference_json(est: AxisEstimate) -> dict | None:
    ref = est.reference
    if ref is None:
        return None
    if not ref.usable:
        return {"why": ref.why}
    return {"g0_um": ref.g0 * 1e6, "g0_std_um": ref.g0_err * 1e6, "x0_um": ref.x0 * 1e6, "x0_std_um": ref.x0_err * 1e6,
            "difference": {name: {"um": d * 1e6, "z": z, "p": p} for name, d, z, p in agreement.disagreement(est, ref)}}


def identify(data: Dataset | pd.DataFrame, *, by_experiment: bool = False,
             bearing: Bearing = PAPER_BEARING, reference=None) -> ClosedFormResult:
    """Closed-form identification of every iteration, averaged as in the paper's tables.

    Iterations are the (``experiment``, ``iteration``) groups of each axis (a file
    without these columns is one iteration).  With ``by_experiment`` each experiment
    gets its own estimate; otherwise all iterations are pooled under ``"all"``.
    An iteration that cannot be solved is listed in ``rejected`` with the reason.

    ``reference`` is least squares on the same readings: a mean that differs from it by more than their errors
    allow fails the ``agrees_with_least_squares`` check (:mod:`~ambfit.estimation.closed_form.agreement`: at
    higher noise Eq. 6-7's mean is biased).  It is a function of an estimate's rows (all of them, or with
    ``by_experiment`` each experiment's) that returns their fit or the error it raised, such as
    ``lambda rows: ambfit.fit_many([rows], bearing=bearing)[0]``; or the fit of all rows itself (a
    :class:`~ambfit.estimation.results.FitResult` or the error its fit raised; not with ``by_experiment``).
    None (default): not compared, the check cannot be judged.  The closed form is a lower layer than least
    squares (whose starts it gives): it does not fit by itself.

    Raises
    ------
    ClosedFormError
        When no iteration of an axis can be solved (the reasons are listed).

    Examples
    --------
    >>> from ambfit.rig import protocol, virtual as rig
    >>> sim = rig.simulate(rig.PAPER_RIG, protocol.paper_table2(iterations=1), noise=rig.NOISE_FREE)
    >>> est = identify(sim.data).estimates[("all", "v")]
    >>> round(est.g0 * 1e6, 6), round(est.x0 * 1e6, 6)
    (775.0, 33.3)
    """
    if by_experiment and reference is not None and not callable(reference):
        raise ValueError("reference: a fit of all rows cannot be compared with each experiment's closed form; "
                         "with by_experiment pass a function of the rows that fits them")
    df = (data.frame if isinstance(data, Dataset) else data).copy()
    if "experiment" not in df.columns:
        df["experiment"] = "all"
    if "iteration" not in df.columns:
        df["iteration"] = 1
    df["experiment"] = df["experiment"].astype(str)
    df["_it"] = pd.to_numeric(df["iteration"], errors="coerce").fillna(1).astype(int)
    estimates = {}
    exp_keys = list(dict.fromkeys(df["experiment"])) if by_experiment else ["all"]
    for exp in exp_keys:
        sub_e = df if exp == "all" and not by_experiment else df[df["experiment"] == exp]
        ls = reference
        if callable(reference):
            ls = reference(data if exp == "all" and not by_experiment else sub_e.drop(columns="_it"))
        for ax in AXES:
            sub = sub_e[sub_e["axis"] == ax]
            if sub.empty:
                continue
            sols, rejected = {}, {}
            for (e, i), grp in sub.groupby(["experiment", "_it"], sort=False):
                key = f"{e}:{i}" if not by_experiment else i
                try:
                    sols[key] = solve_rows(grp, bearing=bearing)
                except ClosedFormError as exc:
                    rejected[key] = str(exc)
            if not sols:
                reasons = "; ".join(f"iteration {k}: {r}" for k, r in list(rejected.items())[:3])
                raise ClosedFormError(f"axis {ax}, experiment {exp}: no iteration could be solved ({reasons})")
            g = _mean_sem([s.g0 for s in sols.values()])
            x = _mean_sem([s.x0 for s in sols.values()])
            k = _mean_sem([s.k for s in sols.values()])
            estimates[(exp, ax)] = AxisEstimate(
                axis=ax, experiment=exp, g0=g[0], g0_sem=g[1], g0_std=g[2], x0=x[0], x0_sem=x[1], x0_std=x[2],
                k=k[0], k_sem=k[1], iterations=sols, rejected=rejected, reference=_reference(ls, ax))
    return ClosedFormResult(estimates=estimates, n_rows=len(df), by_experiment=by_experiment)
