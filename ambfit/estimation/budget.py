"""The uncertainty budget in the GUM's sense (JCGM 100:2008): the readings' noise (type A) and the calibration the
bearing description declares (type B), combined.

A fit's standard errors count only the noise of the readings.  A real rig also reads its currents and positions
through channels calibrated to a tolerance: a current channel 0.1 % high, a current zero 1 mA off, a position
sensor 0.25 % high, loads 0.1 % heavy.  Such an error is the same in every reading, so no number of readings
averages it away, and it moves the estimate.  Each declared tolerance is one input quantity ``δ`` of zero
expectation and standard uncertainty ``u`` (:attr:`~ambfit.physics.bearing.Bearing.tolerance_distribution`:
a uniform ±a gives ``a / √3``); its sensitivity ``c = ∂θ̂/∂δ`` is measured by refitting the readings as that
error would have recorded them, at ``δ = ±u`` from the fit (a central difference, GUM 5.1.3).  The combined
covariance is ``V = V_A + Σ_k (c_k u_k)(c_k u_k)ᵀ`` (the terms are independent), and each parameter's budget names
each term's share of its combined variance.

The terms (:func:`terms`): the gain of each coil's current channel (per axis, top and bottom), the zero of each
coil's current channel, the gain of each axis' position sensor, and the scale of the known loads.

Example
-------
>>> from ambfit.rig import protocol, virtual as rig
>>> from ambfit.estimation.fit import fit
>>> data = rig.simulate(rig.PAPER_RIG, protocol.paper_table2(center=(-33.3e-6, 11.3e-6)), seed=1).data
>>> b = budget(data, fit(data))
>>> b.u_combined("v0") > b.std("v0")          # the calibration adds to the noise
True
>>> {name for name, u, share in b.shares("v0")[:3]} == {NOISE_TERM, "current gain, axis v, top",
...                                                  "current gain, axis v, bottom"}      # the origin's largest
True
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable

import numpy as np
import pandas as pd

from ambfit.estimation.units import CONTRACT_PARAMS
from ambfit.physics.bearing import AXES, TOLERANCE_DISTRIBUTIONS, Bearing

NOISE_TERM = "readings' noise (type A)"
"""The budget's name of the statistical term: the fit's own standard error."""


@dataclasses.dataclass(frozen=True)
class Term:
    """One calibration input quantity: ``name`` in words, its declared ``tolerance`` (in ``unit``), its standard
    uncertainty ``u`` and how an error ``delta`` of it changes the recorded table (``record(frame, delta)``)."""

    name: str
    tolerance: float
    unit: str
    u: float
    record: Callable[[pd.DataFrame, float], pd.DataFrame] = dataclasses.field(repr=False, compare=False)


def standard_uncertainty(tolerance: float, distribution: str) -> float:
    """``u`` of a tolerance ``a``: ``a / sqrt(3)`` for a uniform ±a (GUM 4.3.7), ``a`` itself for ``"normal"``."""
    if distribution not in TOLERANCE_DISTRIBUTIONS:
        raise ValueError(f"distribution must be one of {', '.join(TOLERANCE_DISTRIBUTIONS)}, got {distribution!r}")
    return tolerance / math.sqrt(3.0) if distribution == "uniform" else tolerance


def _recorder(column: str, rows: str | None, offset: bool = False):
    """``record(frame, delta)``: ``column`` as a channel ``delta`` off records it, a gain ``1 + delta`` (or, with
    ``offset``, a zero ``delta`` added), on the rows of axis ``rows`` (None: every row)."""
    def record(frame: pd.DataFrame, delta: float) -> pd.DataFrame:
        out = frame.copy()
        at = slice(None) if rows is None else (out["axis"] == rows).to_numpy()
        x = out.loc[at, column].astype(float)
        out.loc[at, column] = x + delta if offset else x * (1.0 + delta)
        return out

    return record


FITTED = {"current_offset": "current zero"}
"""Effects whose fit estimates a calibration term (``effect name: the terms' name``): a model holding the effect
fits the channels' zeros from the readings (several biases identify them), so they are not budgeted again."""


def terms(frame: pd.DataFrame, bearing: Bearing, fitted_effects: tuple = ()) -> list[Term]:
    """The calibration terms the bearing description declares and these readings depend on.

    Parameters
    ----------
    frame : DataFrame
        The readings (contract columns): a coil's channels count only where its axis has readings, the load
        scale only where known loads are.
    bearing : Bearing
        Its tolerances and how they are distributed.
    fitted_effects : tuple of str
        Effect names of the model: no term that one of them estimates (:data:`FITTED`).
    """
    dist = bearing.tolerance_distribution
    out = []
    axes = [ax for ax in AXES if (frame["axis"] == ax).any()]
    for ax in axes:
        for coil in ("top", "bottom"):
            tol = bearing.current_gain_tolerance
            if tol > 0:
                out.append(Term(f"current gain, axis {ax}, {coil}", tol, "relative", standard_uncertainty(tol, dist),
                                _recorder(f"i_{coil}_A", ax)))
    for ax in axes:
        for coil in ("top", "bottom"):
            tol = bearing.current_offset_tolerance
            if tol > 0 and "current_offset" not in fitted_effects:
                out.append(Term(f"current zero, axis {ax}, {coil}", tol, "A", standard_uncertainty(tol, dist),
                                _recorder(f"i_{coil}_A", ax, offset=True)))
    for ax in AXES:
        tol = bearing.position_gain_tolerance
        if tol > 0 and f"{ax}_um" in frame:
            out.append(Term(f"position gain, axis {ax}", tol, "relative", standard_uncertainty(tol, dist),
                            _recorder(f"{ax}_um", None)))
    tol = bearing.load_scale_tolerance
    if tol > 0 and "load_N" in frame and np.isfinite(pd.to_numeric(frame["load_N"], errors="coerce")).any():
        out.append(Term("load scale", tol, "relative", standard_uncertainty(tol, dist), _recorder("load_N", None)))
    return out


@dataclasses.dataclass(frozen=True)
class Budget:
    """Type-A and type-B uncertainty of a fit's parameters (SI units).

    ``names`` and ``values`` are the fit's; ``cov_a`` its statistical covariance; ``contributions[k]`` the shift
    ``c_k u_k`` of every parameter that term ``terms[k]`` makes at one standard uncertainty (NaN where its refits
    failed, named in ``failed``)."""

    names: tuple
    values: np.ndarray
    cov_a: np.ndarray
    terms: tuple
    contributions: np.ndarray
    distribution: str = "uniform"
    """How the terms' errors are distributed (:attr:`~ambfit.physics.bearing.Bearing.tolerance_distribution`)."""
    failed: tuple = ()
    fitted_terms: tuple = ()
    """The calibration terms the model fits instead (their error is in ``cov_a``), by name (:data:`FITTED`)."""

    @property
    def cov_b(self) -> np.ndarray:
        """The calibration's (type B) covariance ``Σ_k (c_k u_k)(c_k u_k)ᵀ``; a failed term (``failed``) adds
        nothing, and :meth:`to_json` says so."""
        c = np.nan_to_num(self.contributions)
        return c.T @ c

    @property
    def cov(self) -> np.ndarray:
        """The combined covariance ``V_A + V_B``."""
        return self.cov_a + self.cov_b

    def std(self, name: str) -> float:
        """The statistical (type A) standard error of ``name``."""
        i = self.names.index(name)
        return float(math.sqrt(self.cov_a[i, i]))

    def u_combined(self, name: str, type_a: float | None = None) -> float:
        """The combined standard uncertainty of ``name`` (GUM 5.1.2); ``type_a``: another statistical standard
        uncertainty in place of the fit's (a posterior's sd)."""
        i = self.names.index(name)
        a = self.cov_a[i, i] if type_a is None else type_a**2
        return float(math.sqrt(a + self.cov_b[i, i]))

    def shares(self, name: str, type_a: float | None = None,
               type_a_name: str = NOISE_TERM) -> list[tuple[str, float, float]]:
        """``(term, u, share)`` of ``name``'s combined variance, largest first, the readings' noise among them
        (``type_a``, ``type_a_name``: another statistical term, see :meth:`u_combined`)."""
        i = self.names.index(name)
        total = self.u_combined(name, type_a) ** 2
        rows = [(type_a_name, math.sqrt(self.cov_a[i, i]) if type_a is None else float(type_a))]
        rows += [(t.name, abs(float(c))) for t, c in zip(self.terms, self.contributions[:, i]) if np.isfinite(c)]
        return sorted(((n, u, u * u / total if total > 0 else 0.0) for n, u in rows), key=lambda r: -r[2])

    def to_contract(self, type_a: dict | None = None, type_a_name: str = NOISE_TERM) -> dict:
        """Per contract key (section 2): ``u_combined`` and ``budget`` (each term's tolerance, ``u`` in the
        parameter's unit and share of the combined variance), in the contract's units.  ``type_a``: ``{name:
        standard uncertainty [SI]}`` in place of the fit's statistical errors (a posterior's sd), named
        ``type_a_name``."""
        out = {}
        tolerance = {t.name: (t.tolerance, t.unit) for t in self.terms}
        for name, key, factor in CONTRACT_PARAMS:
            if name not in self.names:
                continue
            a = None if type_a is None else type_a.get(name)
            out[key] = {"u_combined": self.u_combined(name, a) * factor,
                        "budget": [{"term": n, "tolerance": tolerance.get(n, (None, None))[0],
                                    "tolerance_unit": tolerance.get(n, (None, None))[1], "u": u * factor,
                                    "share": share} for n, u, share in self.shares(name, a, type_a_name)]}
        return out

    def merge(self, params: dict, type_a: dict | None = None, type_a_name: str = NOISE_TERM) -> None:
        """Add :meth:`to_contract`'s ``u_combined`` and ``budget`` to a contract ``params`` block's entries."""
        for key, extra in self.to_contract(type_a, type_a_name).items():
            if key in params:
                params[key].update(extra)

    def propagate(self, draws: dict, rng: np.random.Generator) -> dict:
        """Posterior draws with the calibration marginalised (GUM Supplement 1's Monte Carlo on the linearised
        sensitivities): each draw shifted by ``Σ_k c_k δ_k`` with every term's error ``δ_k`` drawn anew from its
        :attr:`distribution` (uniform within ±tolerance, or normal of sd u).  ``draws``: ``{name: array [SI]}`` of this
        budget's parameters; returns the same with the shifts added."""
        n = len(next(iter(draws.values())))
        ok = np.all(np.isfinite(self.contributions), axis=1)
        if self.distribution == "uniform":     # unit-variance draws, scaled by the term's u below
            z = rng.uniform(-math.sqrt(3.0), math.sqrt(3.0), size=(n, int(ok.sum())))
        else:
            z = rng.standard_normal((n, int(ok.sum())))
        shift = z @ self.contributions[ok]     # the contributions are c_k u_k, z_k = δ_k / u_k
        return {name: np.asarray(v, float) + shift[:, self.names.index(name)] for name, v in draws.items()}

    def to_json(self, type_a_name: str = NOISE_TERM) -> dict:
        """What the budget was made of: method, distribution, every term (tolerance, unit, u), the terms whose
        refits failed (left out of u_combined) and those the model fits instead."""
        return {"method": f"GUM (JCGM 100): type A {type_a_name}, type B the bearing description's calibration "
                          "tolerances, sensitivities by refitting at ±u",
                "distribution": self.distribution,
                "terms": [{"term": t.name, "tolerance": t.tolerance, "unit": t.unit, "u": t.u} for t in self.terms],
                "failed": list(self.failed), "fitted_instead": list(self.fitted_terms)}

    def failed_text(self) -> str:
        """The terms whose refits failed, in a sentence ("" when none did)."""
        if not self.failed:
            return ""
        return (f"the calibration terms {', '.join(self.failed)} could not be propagated (their refits did not "
                "converge); u_combined leaves them out")

    def summary_rows(self) -> list[dict]:
        """One row per head parameter: value, statistical error, combined uncertainty, the largest term."""
        from ambfit.estimation.units import DISPLAY

        rows = []
        for name, _, _ in CONTRACT_PARAMS:
            if name not in self.names:
                continue
            unit, f = DISPLAY[name]
            top = next((s for s in self.shares(name) if s[0] != NOISE_TERM), None)
            rows.append({"parameter": f"{name} [{unit}]", "std (noise)": f"{self.std(name) * f:.3g}",
                         "u_combined": f"{self.u_combined(name) * f:.3g}",
                         "largest calibration term": "-" if top is None else f"{top[0]} ({100 * top[2]:.0f} %)"})
        return rows


def budget(data, res, *, refit: Callable | None = None, bearing: Bearing | None = None, **fit_kw) -> Budget:
    """The GUM budget of the fit ``res`` of ``data``: its statistical covariance and, for every calibration term
    of the bearing description (:func:`terms`), the parameters' shift at ``±u`` measured by refitting.

    ``refit(frame) -> FitResult`` refits a table as the fit was made (default: :func:`ambfit.estimation.fit.fit`
    with ``res``'s effects, bearing, loss and rows, from ``res``, with ``fit_kw``, e.g. the declared noise the
    fit was given; the outlier test is not run again, so that every refit fits the same rows).
    """
    from ambfit.data import Dataset
    from ambfit.estimation.fit import _FAILURES, fit
    from ambfit.estimation.problem import fitted_once

    frame = (data.frame if isinstance(data, Dataset) else data).reset_index(drop=True)
    bearing = bearing or res.bearing
    if refit is None:
        keep = res.fitted_rows.astype(float)

        def refit(table):
            # the plain estimate: a bias correction would cancel in the difference of a term's two refits
            return fit(table, res.effects, bearing=res.bearing, start_from=res, mask=keep, alpha=0.0, throw=False,
                       **({"loss": res.loss} | fit_kw | {"debias": "none"}))

    effects = tuple(type(e).name for e in res.effects)
    found = terms(frame, bearing, effects)
    contributions = np.full((len(found), len(res.names)), np.nan)
    failed = []
    for k, term in enumerate(found):
        try:
            with fitted_once():         # each recorded copy is fitted once: no need to hash and keep its problem
                ends = [refit(term.record(frame, sign * term.u)) for sign in (1.0, -1.0)]
        except _FAILURES:               # the readings so recorded cannot be fitted at all: the term is not propagated
            failed.append(term.name)
            continue
        if not all(e.converged and list(e.names) == list(res.names) for e in ends):
            failed.append(term.name)
            continue
        contributions[k] = (np.asarray(ends[0].values) - np.asarray(ends[1].values)) / 2.0
    return Budget(tuple(res.names), np.asarray(res.values), np.asarray(res.cov), tuple(found), contributions,
                  bearing.tolerance_distribution, tuple(failed), tuple(FITTED[e] for e in effects if e in FITTED))


def declared_text(bearing: Bearing, fitted_terms: tuple = ()) -> str:
    """The bearing description's tolerances in words (``uniform: current gain ±0.1 %, ...``), without the terms a
    model fits instead."""
    declared = {"current gain": f"±{100 * bearing.current_gain_tolerance:g} %",
                "current zero": f"±{bearing.current_offset_tolerance * 1e3:g} mA",
                "position gain": f"±{100 * bearing.position_gain_tolerance:g} %",
                "load scale": f"±{100 * bearing.load_scale_tolerance:g} %"}
    listed = ", ".join(f"{k} {v}" for k, v in declared.items() if k not in fitted_terms)
    return f"{bearing.tolerance_distribution}: {listed}"


ZERO_SHARE = 0.25
"""The current zeros' share of a head parameter's combined variance above which :func:`fit_instead` asks whether
the readings determine them (one Jacobian) and, if they do, fits them (one fit and its budget)."""


@dataclasses.dataclass(frozen=True)
class Instead:
    """The current zeros fitted instead of budgeted (:func:`fit_instead`): the ``parameter`` whose combined
    variance they dominated (``zero_share``), its combined uncertainty before and after (display units), the fit
    with ``current_offset`` and that fit's budget."""

    effect: str
    parameter: str
    zero_share: float
    u_combined: float
    u_combined_fitted: float
    unit: str
    fit: object = dataclasses.field(repr=False, compare=False)
    budget: Budget = dataclasses.field(repr=False, compare=False)

    @property
    def text(self) -> str:
        return (f"the current zeros make {100 * self.zero_share:.0f} % of {self.parameter}'s combined variance and "
                f"these readings determine them: fitting them ({self.effect}) takes {self.parameter}'s u_combined "
                f"from {self.u_combined:.3g} to {self.u_combined_fitted:.3g} {self.unit}")

    def to_json(self) -> dict:
        return {"effect": self.effect, "parameter": self.parameter, "zero_share": self.zero_share,
                "u_combined": self.u_combined, "u_combined_fitted": self.u_combined_fitted, "unit": self.unit,
                "text": self.text}


def fit_instead(data, res, b: Budget, **fit_kw) -> Instead | None:
    """When the ideal law fits its data (``res``, budget ``b``), the current zeros dominate an uncertainty of it and
    the readings determine them (every offset keeps less than :data:`~ambfit.estimation.identification.MAX_PRIOR_SHARE`
    of its prior's variance: several biases do), the fit with ``current_offset`` and what it gives
    (:class:`Instead`); None otherwise.  ``fit_kw``: how ``res`` was fitted (noise, ``require_k``, ``loss``)."""
    from ambfit.estimation.conditioning import effect_identification
    from ambfit.estimation.fit import fit
    from ambfit.estimation.identification import MAX_PRIOR_SHARE
    from ambfit.estimation.units import DISPLAY
    from ambfit.physics.effects import CurrentOffset

    if res.effects or res.adequate is False:
        # (the identification is judged from the ideal law's estimate; a law that does not fit has misfit for the
        # offsets to absorb, and a budget that assumes the law)
        return None
    heads = [n for n, _, _ in CONTRACT_PARAMS if n in b.names]
    share = {n: sum(sh for t, _, sh in b.shares(n) if t.startswith(FITTED["current_offset"])) for n in heads}
    worst = max(share, key=share.get, default=None)
    if worst is None or share[worst] <= ZERO_SHARE:
        return None
    shares = effect_identification(data, [CurrentOffset()], res, bearing=res.bearing, sigma_i=fit_kw.get("sigma_i"),
                                   sigma_x=fit_kw.get("sigma_x"))
    if not shares or max(shares.values()) > MAX_PRIOR_SHARE:
        return None
    alt = fit(data, [CurrentOffset()], bearing=res.bearing, throw=False, **fit_kw)
    if not (alt.converged and alt.well_conditioned):
        return None
    b_alt = budget(data, alt, **fit_kw)
    unit, f = DISPLAY[worst]
    return Instead("current_offset", worst, share[worst], b.u_combined(worst) * f, b_alt.u_combined(worst) * f,
                   unit, alt, b_alt)
