"""Change points: steps in a parameter's series beyond its drift and noise, and jumps against a drift measured
elsewhere (the tests and their references are in :mod:`ambfit.studies.campaign`)."""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from ambfit.studies.campaign.series import Series, _design, _key, _Line, _line, _slope_prior
from ambfit.studies.campaign.window import CampaignError

ALPHA = 0.01
"""False-alarm probability of the change-point test per parameter and campaign (Bonferroni bound)."""

SCATTER_P = 0.01
"""The change-point test scales the error bars when the scatter about its model has a χ² p-value below this: the
windows' errors are trusted unless they are clearly too small (scaled and judged by Student's t with a few degrees
of freedom, a 7-sigma jump can drop below a Bonferroni bound; a pre-test at 5 % does so in 4 % of the benchmark's
campaigns)."""


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
