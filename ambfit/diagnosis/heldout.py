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
from ambfit.estimation.robust import MAD_DOF, MAX_FRACTION, robust_scale
from ambfit.estimation.units import HEAD

FOLDS = 4
"""Cross-validation folds of the time-block scheme."""

BLOCKS_PER_FOLD = 4
"""Contiguous blocks of readings in each time-block fold: spread over the run, each held-out block lies between
readings the fold's fit sees (interpolation in time), the first and the last at its ends (extrapolation)."""


BIAS_RANGES = 8
"""Most folds over biases: with more biases than this, neighbouring ones are held out together, in this many
ranges of about equal count (an improvised protocol with 60 biases would otherwise refit every model 60 times,
each fold nearly the whole data set)."""


def folds(data: pd.DataFrame, scheme: str = "regions") -> tuple[str, list]:
    """Block cross-validation folds.  Returns ``(name, [bool test masks])``.

    ``scheme="regions"``: over operating regions: leave one load out when there are three or more load groups,
    else leave one bias out (one range of neighbouring biases when there are more than :data:`BIAS_RANGES`), else
    alternate iterations.  ``scheme="time"``: the readings in the order they were
    taken (``time_s``, else the rows' order) cut into ``FOLDS * BLOCKS_PER_FOLD`` contiguous blocks, block ``j``
    in fold ``j mod FOLDS``: every fold holds readings from the whole run, each between readings its fit sees,
    so a drift is tested by interpolation as well as extrapolation, and every load, bias and set-point region is
    in every fit."""
    df = data.reset_index(drop=True)
    if scheme == "time":
        n = len(df)
        t = pd.to_numeric(df["time_s"], errors="coerce").to_numpy(float) if "time_s" in df else np.full(n, np.nan)
        order = np.argsort(t if np.isfinite(t).all() else np.arange(n), kind="stable")
        blocks = max(min(FOLDS * BLOCKS_PER_FOLD, n // 5), FOLDS)
        block = np.empty(n, int)
        block[order] = np.arange(n) * blocks // max(n, 1)
        return "time blocks", [(block % FOLDS) == k for k in range(FOLDS)]
    if scheme != "regions":
        raise ValueError(f"scheme must be 'regions' or 'time', got {scheme!r}")
    if "load_id" in df and df["load_id"].nunique() >= 3:
        return "leave-one-load-out", [(df["load_id"] == v).to_numpy() for v in df["load_id"].unique()]
    b = np.round(df["bias_A"].to_numpy(float), 6)
    biases = np.unique(b)
    if len(biases) > BIAS_RANGES:
        # neighbouring biases held out together: each fold an operating range the fit does not see
        rank = np.searchsorted(biases, b) * BIAS_RANGES // len(biases)
        return f"leave-one-bias-range-out ({BIAS_RANGES} ranges of {len(biases)} biases)", [
            rank == k for k in range(BIAS_RANGES)]
    if len(biases) >= 3:
        return "leave-one-bias-out", [b == v for v in biases]
    it = pd.to_numeric(df["iteration"], errors="coerce").fillna(0).to_numpy() if "iteration" in df else np.arange(len(df))
    return "alternate iterations", [(it % 2) == 0, (it % 2) == 1]


def deviance(z, var=None) -> np.ndarray:
    """``z^2 / var + log(var)`` per reading: minus twice the Gaussian log predictive density of a residual ``z``
    (noise units) whose predictive variance is ``var``, up to a constant."""
    z = np.asarray(z, dtype=float)
    if var is None:
        return z**2
    var = np.asarray(var, dtype=float)
    return z**2 / var + np.log(var)


def excess(z) -> float:
    """``sqrt(max(mean(z^2) - 1, 0))``: model error beyond the noise floor, in noise units (contract section 3)."""
    return float(np.sqrt(max(np.mean(np.asarray(z) ** 2) - 1.0, 0.0)))


def shrink(before: float, after: float) -> float:
    """Fraction of the held-out excess that a model removes: ``1 - after / before`` (0 when there is none)."""
    return 1.0 - after / before if before > 0 else 0.0


GROSS_SHARE = MAX_FRACTION
"""The largest share of the readings :func:`gross_errors` leaves out of the held-out scores: the fit's own limit
between a few bad readings and a model that does not fit (:data:`ambfit.estimation.robust.MAX_FRACTION`; a fit that
finds more keeps every reading, so a diagnosis' fits hold to it already).  Readings that no model at the floor fits
are left out when they are that few (a position reading spiking by micrometres on a sensor good to a tenth); more is
a finding the scores must keep."""


FLOOR_SCALE_SE = 3.0
"""A fit is at the floor on the readings it used when their standardized residuals' robust scale (``1.4826 median
|z|``, :func:`ambfit.estimation.robust.robust_scale`) exceeds the floor's by at most this many of its standard errors
(``sqrt(1.36 / n)`` relative for Gaussian noise, :data:`ambfit.estimation.robust.MAD_DOF`)."""


def _scale(fit: FitResult) -> tuple[float, int]:
    """The robust scale of ``fit``'s standardized residuals on the rows it used, and how many there are."""
    used = np.asarray(fit.fitted_rows[:len(fit.residuals)])
    z = np.asarray(fit.residuals)[used]
    z = z[np.isfinite(z)]
    return (robust_scale(z, known_noise=not fit.noise_estimated) if z.size else np.inf), int(z.size)


def at_the_floor(fits: list) -> list[bool]:
    """Whether each fit describes the bulk of the readings it used to the noise (:data:`FLOOR_SCALE_SE`): its robust
    scale is at most ``1 + FLOOR_SCALE_SE sqrt(1.36 / n)`` times the floor's, 1 with the noise known; with the noise
    estimated from the residuals (no absolute floor), the smallest of the fits'.  A model that misfits the bulk reads
    every residual against a larger scale and names few outliers, whatever they are."""
    scales = [_scale(f) for f in fits]
    estimated = any(f.noise_estimated for f in fits)
    floor = min((s for s, _ in scales), default=np.inf) if estimated else 1.0
    return [bool(n) and s <= floor * (1.0 + FLOOR_SCALE_SE * np.sqrt(MAD_DOF / 2.0 / n)) for s, n in scales]


def gross_errors(models, share: float = GROSS_SHARE) -> np.ndarray:
    """The readings (bool per row) that every model at the floor names outliers in its fit of every row (a
    converged fit describing the bulk of the readings to the noise, :func:`at_the_floor`), when they are at most
    ``share`` of the readings (else none).  A fit that did not converge has no say (its outlier test judged residuals
    short of the fit's minimum), nor has one that misfits the bulk (beside an effect it lacks, the spikes hide in
    its own misfit); with no model at the floor, none is left out.

    A reading that no model at the floor fits predicts nothing about which of them is right, yet one standardized
    residual of 30 weighs as much as 900 readings at the noise floor in a mean square: left in, a few spikes make
    clean data look unexplained.  Such readings are left out of every held-out score and of what the widened laws
    learn from.  They are a sensor's gross errors, or an effect that no library law holds, confined to them."""
    n = max((len(m.fit.residuals) for m in models if m.fit is not None), default=0)
    fits = [m.fit for m in models if m.fit is not None and m.fit.converged]
    rows = [np.asarray(f.fitted_rows[:n]) for f, ok in zip(fits, at_the_floor(fits)) if ok]
    if not rows:
        return np.zeros(n, bool)
    out = ~np.logical_or.reduce(rows)
    return out if out.sum() <= share * len(out) else np.zeros_like(out)


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


def predictive_variance(fitted: FitResult, rows: np.ndarray) -> np.ndarray:
    """What the fit's parameter uncertainty adds to the variance of its prediction of ``rows`` (bool mask), in
    noise units: the leverage ``h`` of those rows (:func:`ambfit.estimation.robust.leverage`) under the rows the fit
    used, with the unit precision of the effect parameters' priors.  A held-out reading's standardized residual has
    variance ``1 + h`` when the model is right."""
    from ambfit.estimation.robust import leverage

    jac = fitted.jacobian_rows
    if jac is None or not np.any(rows):
        return np.zeros(int(np.sum(rows)))
    mask = fitted.row_weights[:len(jac)]
    prior = np.array([1.0 if "." in name else 0.0 for name in fitted.names[:jac.shape[1]]])
    return leverage(jac[None], (mask**2)[None], prior)[0][rows]


@dataclasses.dataclass(frozen=True)
class Candidate:
    """One model's held-out score: the effects, the excess before and after, and its in-sample fit.

    Attributes
    ----------
    effect : str
        The model's name: ``ideal``, an effect's, or ``+``-joined effects'.
    heldout_z : array[n]
        Standardized residuals of every fold's held-out readings, pooled (in noise units).
    before : float
        The ideal law's held-out excess (noise units).
    fit : FitResult
        The model fitted to every row.
    folds : tuple
        ``(test mask, fit without those rows)`` per fold.
    kind : {"ideal", "law", "pair"}
        The ideal law, one library law, or a pair of them.
    heldout_var : array[n] or None
        Each held-out reading's predictive variance ``1 + h`` in noise units (:func:`predictive_variance`): the
        variance of its residual when the model is right (None: 1).
    """

    effect: str
    heldout_z: np.ndarray
    before: float
    fit: FitResult
    folds: tuple = ()
    kind: str = "law"
    heldout_var: np.ndarray | None = None

    @property
    def heldout_deviance(self) -> np.ndarray:
        """Each held-out reading's ``z^2 / (1 + h) + log(1 + h)``: minus twice its log predictive density, up to a
        constant (the flexibility a model pays: a wider prediction is less surprised, and pays its width)."""
        return deviance(self.heldout_z, self.heldout_var)

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
