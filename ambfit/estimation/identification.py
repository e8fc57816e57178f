"""Whether the data determine an extended model's effect parameters: the share of an effect parameter's prior that
may remain, the experiment that shows each effect, and the words of a fit whose effect the data cannot see
(:func:`prior_shares`; :func:`ambfit.estimation.conditioning.effect_identification` from a data table)."""

from __future__ import annotations

import numpy as np

from ambfit.estimation.core import Meta, Model, Problem, free_mask, free_names
from ambfit.estimation.lm import measure

MAX_PRIOR_SHARE = 0.25
"""An effect parameter is determined by the data when its variance, at the start of the extended fit, is below this
share of its weak prior's: the data at least halve the prior's standard deviation.  On the paper's Table 2
protocol saturation's parameters keep 0.52-0.62 (two close biases); on the rich preset 0.001."""

SEPARATE_BY = {
    "saturation": "a bias sweep towards the coil limit (ambfit simulate --preset rich: four biases up and down, from a "
                  "third to over half of the limit)",
    "iron_reluctance": "a bias sweep towards the coil limit (the rich preset) and a known-displacement calibration",
    "leakage": "a bias sweep with known loads (the rich preset; a constant leakage is part of k)",
    "hysteresis": "approaching each set-point from both directions (biases up and down)",
    "cross_coupling": "moving the other axis while this one is perturbed",
    "thermal_drift": "readings over a range of temperature (temperature_C) or, without one, of time (time_s)",
}
"""The experiment that shows each effect, for the message of an effect the data do not determine."""


def undetermined_text(shares: dict, max_share: float = MAX_PRIOR_SHARE) -> str:
    """The effects whose parameters these data do not determine, and the experiment that would (empty when all
    are determined)."""
    bad = {n: s for n, s in shares.items() if s > max_share}
    if not bad:
        return ""
    families = list(dict.fromkeys(n.split(".")[0] for n in bad))
    params = ", ".join(f"{n} ({100 * s:.0f} % of its prior's variance left)" for n, s in bad.items())
    runs = "; ".join(SEPARATE_BY.get(f, "a design that varies what it depends on (ambfit design)")
                     + (f" for {f}" if len(families) > 1 else "") for f in families)
    return (f"not identifiable: {params} are not determined by these data (the solver can only wander along them). "
            f"To see {' and '.join(families)}, run {runs}")


def prior_shares(prob: Problem, meta: Meta, model: Model, start) -> dict:
    """How much each effect parameter's prior still holds after these data, where the extended fit starts.

    The extended model's Jacobian is taken at ``start`` (the ideal law's :class:`ambfit.FitResult` on these rows;
    effects at their prior centre).  With the data's information ``J^T J`` (scaled parameters) and the unit prior of
    each effect coordinate, the posterior variance of a coordinate, ``[(J^T J + P)^-1]_jj`` in ``(0, 1]``, is the
    share of the prior's variance the data leave: near 1 the data do not determine that parameter, and a solver
    that looks for it wanders.  Returns ``{parameter name: share}`` for every effect parameter, except those of
    a law no reading uses while the data see another parameter of the same effect (the rates of
    :class:`~ambfit.physics.effects.ThermalDrift` on data with a temperature): their Jacobian column is zero,
    the prior pins them at its centre and the solver cannot wander along them.
    """
    if not model.n:
        return {}
    theta = np.concatenate([np.asarray(start.theta), np.zeros(model.n)])
    # measured by the solve's own program (no step): the fit just compiled it for this model and shape
    rows = np.asarray(measure(theta, prob, model).jac_all)[: len(np.asarray(prob.mask))]
    jac = rows[:, free_mask(prob, meta, model)][start.fitted_rows]
    info = jac.T @ jac
    info[-model.n:, -model.n:] += np.eye(model.n)          # q ~ N(0, 1): the effects' weak priors
    share = np.diag(np.linalg.pinv(info))[-model.n:]
    names = free_names(meta, free_mask(prob, meta, model), model)[-model.n:]
    unused = ~np.any(jac[:, -model.n:] != 0.0, axis=0)
    seen = {n.split(".")[0] for n, u in zip(names, unused) if not u}
    return {n: float(v) for n, v, u in zip(names, share, unused) if not (u and n.split(".")[0] in seen)}
