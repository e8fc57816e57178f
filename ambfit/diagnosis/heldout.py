"""Held-out scoring: block cross-validation folds over operating regions and the excess a model leaves on them.

A model is fitted with each fold held out and scored on it: ``excess = sqrt(max(mean(z^2) - 1, 0))``
of the pooled held-out standardized residuals, the model error beyond the noise floor in noise
units (contract section 3); ``shrink = 1 - excess_after / excess_before`` is the fraction of the
ideal law's excess a candidate removes.  :class:`Candidate` is one model's score.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pandas as pd

from ambfit.data import load_groups, zero_based
from ambfit.estimation.results import FitResult

HEAD = ("g_v0", "v0", "g_w0", "w0", "k_v", "k_w")


def folds(data: pd.DataFrame) -> tuple[str, list]:
    """Block cross-validation folds over operating regions: leave one load out when there are three or more
    load groups, else leave one bias out, else alternate iterations.  Returns (name, [bool test masks])."""
    df = data.reset_index(drop=True)
    if "load_id" in df and df["load_id"].nunique() >= 3:
        return "leave-one-load-out", [(df["load_id"] == v).to_numpy() for v in df["load_id"].unique()]
    b = np.round(df["bias_A"].to_numpy(float), 6)
    if len(np.unique(b)) >= 3:
        return "leave-one-bias-out", [b == v for v in np.unique(b)]
    it = pd.to_numeric(df["iteration"], errors="coerce").fillna(0).to_numpy() if "iteration" in df else np.arange(len(df))
    return "alternate iterations", [(it % 2) == 0, (it % 2) == 1]


def excess(z) -> float:
    """``sqrt(max(mean(z^2) - 1, 0))``: model error beyond the noise floor, in noise units (contract section 3)."""
    return float(np.sqrt(max(np.mean(np.asarray(z) ** 2) - 1.0, 0.0)))


def shrink(before: float, after: float) -> float:
    """Fraction of the held-out excess that a model removes: ``1 - after / before`` (0 when there is none)."""
    return 1.0 - after / before if before > 0 else 0.0


def heldout_residuals(fitted: FitResult, data: pd.DataFrame, test: np.ndarray, groups=None) -> np.ndarray:
    """Standardized residuals of the ``test`` rows (bool mask) under a fit that held them out.

    A nuisance load that no row the fit used constrained is refitted on the test rows alone
    (its weighted mean misfit is removed, one number per group): the held-out check is
    about the shape of the force law, not about an unknown load the training data never saw.  ``groups``: the
    rows' load groups (:func:`ambfit.data.load_groups`), when the caller has them.
    """
    z = fitted.residuals.copy()
    groups = load_groups(zero_based(data)).to_numpy() if groups is None else np.asarray(groups)
    known = data["load_N"].notna().to_numpy() if "load_N" in data else np.zeros(len(data), bool)
    train = fitted.fitted_rows & ~test          # the rows the fit used (a fold leaves out its model's outliers too)
    for g in np.unique(groups[test & ~known]):
        m = groups == g
        if not np.any(m & train):
            zz = z[m & test]
            z[m & test] = zz - zz.mean()
    return z[test]


@dataclasses.dataclass(frozen=True)
class Candidate:
    """One model's held-out score: the effects, the excess before and after, and its in-sample fit.

    Attributes
    ----------
    effect : str
        The model's name: ``ideal``, an effect's, or ``+``-joined effects'.
    heldout_z : array[n]
        Standardized residuals of every fold's held-out readings, pooled.
    before : float
        The ideal law's held-out excess (noise units).
    fit : FitResult
        The model fitted to every row.
    folds : tuple
        ``(test mask, fit without those rows)`` per fold.
    kind : {"ideal", "law", "pair"}
        The ideal law, one library law, or a pair of them.
    """

    effect: str
    heldout_z: np.ndarray
    before: float
    fit: FitResult
    folds: tuple = ()
    kind: str = "law"

    @property
    def families(self) -> tuple[str, ...]:
        """The families the model names."""
        return tuple(self.effect.split("+"))

    @property
    def label(self) -> str:
        return self.effect

    @property
    def after(self) -> float:
        return excess(self.heldout_z)

    @property
    def shrink(self) -> float:
        return shrink(self.before, self.after)

    @property
    def score(self) -> float:
        """Mean squared held-out standardized residual (lower is better)."""
        return float(np.mean(self.heldout_z**2))

    def to_json(self, baseline: Candidate) -> dict:
        head = {n: (self.fit.value(n), self.fit.error(n)) for n in self.fit.names if not n.startswith("load[")}
        base = {n: baseline.fit.value(n) for n in baseline.fit.names}
        z_in = self.fit.residuals
        aic0 = float(np.sum(baseline.fit.residuals**2) + 2 * len(baseline.fit.names))
        return {"effect": self.effect,
                "heldout_rms_before": float(np.sqrt(np.mean(baseline.heldout_z**2))),
                "heldout_rms_after": float(np.sqrt(self.score)), "heldout_excess_before": self.before,
                "heldout_excess_after": self.after, "shrink": self.shrink, "score": self.score,
                "insample_mean_z2": float(np.mean(z_in**2)),
                # Akaike's criterion on the in-sample fit (chi2 + 2 p), relative to the ideal model
                "delta_aic": float(np.sum(z_in**2) + 2 * len(self.fit.names) - aic0),
                "converged": self.fit.converged,
                "params": {k: v[0] for k, v in head.items() if "." in k},
                "params_std": {k: v[1] for k, v in head.items() if "." in k},
                "shift": {k: head[k][0] - base[k] for k in HEAD if k in head and k in base},
                # standard error of the extended estimate (the shift's reference, the ideal fit on the
                # same data, is strongly correlated with it; sqrt(var_ext - var_base) can be negative)
                "shift_std": {k: head[k][1] for k in HEAD if k in head and k in base}}
