"""How far to trust the closed form's mean: its interval (Student t, n - 1 degrees of freedom) and its agreement
with least squares on the same readings.

The paper reports the mean of ``n`` iterations and its standard error.  With ``n = 10`` the standard error is
itself estimated from 9 degrees of freedom, so a 95 % interval is ``mean ± t(0.975, n - 1) sem`` (2.26 sem), not
1.96 sem (which covers about 92 % for ``n = 10``; Student 1908, see any text, e.g. Wasserman, *All of Statistics*,
Sec. 10.7).

Eq. 6-7 are a nonlinear function of noisy currents (an errors-in-variables estimator): at each iteration the gap
goes as ``1 / (1 - P)`` with ``P`` a ratio of differences of squared currents, so its mean is biased by a term
of the order of the squared relative noise of ``1 - P`` and its distribution has heavy tails, in which a run of
ten iterations can show too small a scatter.  Neither shows in the standard error.  Least squares on the same
readings has neither problem to the same degree (its bias is ``benchmarks/ls_bias.py``'s) and a much smaller
error, so a closed-form mean that differs from it by more than their errors allow is flagged, with the
difference: the bias (or the missed scatter) of this run.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

LEVEL = 0.95
"""Confidence level of the closed form's reported interval."""

AGREEMENT_ALPHA = 0.01
"""False-alarm probability per axis of the closed form / least squares comparison on clean data, if the closed
form were unbiased (Bonferroni over gap and origin; measured by ``benchmarks/closed_form_coverage.py``)."""


def t_quantile(n: int, level: float = LEVEL) -> float:
    """Two-sided Student t quantile for the mean of ``n`` values (``n - 1`` degrees of freedom); NaN for n < 2."""
    from scipy.stats import t

    return float(t.ppf(0.5 + level / 2, n - 1)) if n >= 2 else math.nan


def interval(mean: float, sem: float, n: int, level: float = LEVEL) -> tuple[float, float]:
    """``mean ± t(0.5 + level/2, n - 1) sem``: the level-``level`` interval of a mean of ``n`` values."""
    half = t_quantile(n, level) * sem
    return mean - half, mean + half


@dataclasses.dataclass(frozen=True)
class Reference:
    """Least squares on the same readings as one closed-form estimate (SI units).

    ``g0, g0_err, x0, x0_err`` are NaN and ``why`` says why when no usable fit exists.
    """

    g0: float = math.nan
    g0_err: float = math.nan
    x0: float = math.nan
    x0_err: float = math.nan
    why: str = ""

    @classmethod
    def of(cls, result, axis: str) -> Reference:
        """One axis of a :class:`~ambfit.estimation.results.FitResult` (a failed fit names its health)."""
        if not (result.converged and result.well_conditioned):
            return cls(why="least squares on the same readings failed: " + "; ".join(result.health()))
        g, x = f"g_{axis}0", f"{axis}0"
        return cls(result.value(g), result.error(g), result.value(x), result.error(x))

    @property
    def usable(self) -> bool:
        return bool(np.isfinite(self.g0) and np.isfinite(self.x0))


def disagreement(est, ref: Reference) -> list[tuple[str, float, float, float]]:
    """``(name, difference [m], z, p)`` for gap and origin: closed form minus least squares, in units of
    ``sqrt(sem^2 + err^2)``, with the two-sided p-value of Student t on ``n - 1`` degrees of freedom (the closed
    form's standard error dominates; adding the least-squares error, rather than subtracting it as the
    correlation of the two estimates would allow, keeps the test conservative)."""
    from scipy.stats import t

    out = []
    for name, cf, sem, ls, err in (("gap", est.g0, est.g0_sem, ref.g0, ref.g0_err),
                                   ("origin", est.x0, est.x0_sem, ref.x0, ref.x0_err)):
        scale = math.hypot(sem, err)
        z = (cf - ls) / scale if scale > 0 else math.inf
        p = float(2 * t.sf(abs(z), est.n - 1)) if est.n >= 2 else math.nan
        out.append((name, cf - ls, z, p))
    return out


def check(est, alpha: float = AGREEMENT_ALPHA) -> tuple[str, bool | None, str]:
    """The ``agrees_with_least_squares`` health check of one axis' closed-form mean."""
    ref = est.reference
    where = f"closed form, axis {est.axis}" + (f", experiment {est.experiment}" if est.experiment != "all" else "")
    if ref is None or not ref.usable or est.n < 2:
        why = ref.why if ref is not None and ref.why else "no least-squares reference"
        return "agrees_with_least_squares", None, f"{where}: not compared with least squares ({why})"
    rows = disagreement(est, ref)
    worst = min(rows, key=lambda r: r[3])
    ok = bool(worst[3] >= alpha / len(rows))
    name, diff, z, p = worst
    cf, ls, err = (est.g0, ref.g0, ref.g0_err) if name == "gap" else (est.x0, ref.x0, ref.x0_err)
    sem = est.g0_sem if name == "gap" else est.x0_sem
    return ("agrees_with_least_squares", ok,
            f"{where}: the {name} {cf * 1e6:.1f} ± {sem * 1e6:.1f} µm differs from least squares on the same "
            f"readings ({ls * 1e6:.1f} ± {err * 1e6:.1f} µm) by {diff * 1e6:+.1f} µm, {abs(z):.1f} times their "
            f"combined error (p = {p:.2g}, t with {est.n - 1} dof): Eq. 6-7 are nonlinear in the noisy currents, so "
            "at this noise the mean of the iterations is biased or its standard error too small; use least squares "
            "(ambfit identify without --method), a larger bias step or more readings per set-point")
