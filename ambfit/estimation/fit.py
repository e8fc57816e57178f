"""Least squares over every reading: gap, origin, (with known loads) the force constant, and any effects.

Likelihood
----------
Every reading is a static equilibrium: the true currents ``(i_t, i_b)`` and true
position ``x`` satisfy ``F(i_t, i_b, x; g0, x0, k) = L`` with ``L`` the load.  All
three are *measured* with noise (std ``s_t``, ``s_b``, ``s_x``), so this is an
errors-in-variables problem.  We use the **effective-variance** residual

    r = (F(measured; theta) - L) / s_eff,
    s_eff^2 = (dF/di_t s_t)^2 + (dF/di_b s_b)^2 + (dF/dx s_x)^2

(Clutton-Brock, Technometrics 9, 261, 1967; Orear, Am. J. Phys. 50, 912, 1982).
For Gaussian noise that is small next to the operating point (0.6 mA against
1.5 A here) the constraint is locally linear, and this is the exact likelihood
with the latent true values profiled out; its information matrix is the
Cramér-Rao bound of :mod:`ambfit.estimation.information`.  We prefer it to *output error*
(predict the control current and compare) because it treats both coils and the
position sensor symmetrically and needs no root solve per reading; unbiasedness
and unit-variance pulls are checked on rig data in the tests and in
``benchmarks/ls_efficiency.py``.  ``s_eff`` is held fixed while Levenberg-Marquardt
runs and re-evaluated at its estimate (``REWEIGHTINGS`` rounds: iteratively
reweighted least squares), the usual choice that keeps the estimator consistent.

The model is the ideal law (Eq. 4) extended by any tuple of
:mod:`ambfit.physics.effects`; the ideal model is ``effects=()``.  Residuals, solve
and convergence test are those of :mod:`ambfit.estimation.core`, for every model.

Loads and the force constant
----------------------------
``L`` is the row's known load (``load_N``) or, where unknown, a nuisance parameter
shared by the rows of one load group (``load_id`` and axis).  Only known loads fix
the scale of ``k``: an axis without any known load has ``k`` held at
``K_REFERENCE`` and it is **not** reported (gap and origin come from the
current ratios, where ``k`` cancels).

Noise levels come from the contract's std columns, else from a declared level,
else they are estimated from the residuals (reduced χ² scaling); the result
says which.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import jax.numpy as jnp
import numpy as np
import optimistix as optx
import pandas as pd

from ambfit.data import Dataset
from ambfit.estimation import closed_form
from ambfit.estimation.core import (
    EDM_MAX,
    FIRST_STEPS,
    K_REFERENCE,
    FitError,
    Meta,
    Model,
    Problem,
    build_problem,
    free_mask,
    free_names,
    jacobian,
    seed_loads_and_k,
    si_scale,
    solve_and_measure,
    standardized,
    to_theta,
)
from ambfit.estimation.results import FitResult, Thresholds, describe_weakness
from ambfit.physics.bearing import AXES, PAPER_BEARING, Bearing
from ambfit.physics.effects import Effect
from ambfit.physics.model import horseshoe_force, pole_gaps


def start(prob: Problem, meta: Meta, data: pd.DataFrame, bearing: Bearing = PAPER_BEARING) -> tuple[np.ndarray, str]:
    """Starting point: the closed form (Eq. 7) where the design has two biases at two positions,
    else a coarse grid over gap and origin; nuisance loads from the model there.  Never the truth."""
    g, x, how = [bearing.nominal_gap] * 2, [0.0, 0.0], []
    for a, ax in enumerate(AXES):
        if not meta.axes_present[a]:
            continue
        try:
            est = closed_form.identify(data[data["axis"] == ax], bearing=bearing).estimates[("all", ax)]
            if np.isfinite(est.g0) and est.g0 > 0:
                g[a], x[a] = est.g0, est.x0
                how.append(f"{ax}: closed form")
                continue
        except closed_form.ClosedFormError:
            pass
        g[a], x[a] = _grid_start(prob, a, bearing)
        how.append(f"{ax}: grid")
    theta = to_theta(g, x, K_REFERENCE, np.zeros(prob.n_loads))
    return seed_loads_and_k(theta, prob, Model.of((), bearing)), ", ".join(how)


def _grid_start(prob: Problem, axis: int, bearing: Bearing) -> tuple[float, float]:
    """Best (gap, origin) of a coarse grid (gap 0.5-1.5 x nominal, origin ±0.3 x nominal), loads profiled."""
    nominal = bearing.nominal_gap
    gs = np.linspace(0.5, 1.5, 41) * nominal
    xs = np.linspace(-0.3, 0.3, 61) * nominal
    sel = np.asarray(prob.ax) == axis
    best, arg = np.inf, (nominal, 0.0)
    it, ib, x = (np.asarray(v)[sel] for v in (prob.i_top, prob.i_bottom, prob.x))
    gid = np.where(np.asarray(prob.known)[sel], -1, np.asarray(prob.gidx)[sel])
    load = np.asarray(prob.load)[sel]
    for g in gs:
        gt, gb = pole_gaps(g, xs[:, None], x[None, :], bearing.cos_alpha)
        ok = np.all(np.minimum(gt, gb) > 0.05 * g, axis=1)
        with np.errstate(divide="ignore", invalid="ignore"):
            unit = horseshoe_force(1.0, it, gt, 1.0, ib, gb)   # [origin, row], Eq. 4 with k = 1
        # per load group, the best load (or k for known loads) is the mean: relative spread is the cost
        cost = np.zeros(len(xs))
        for grp in np.unique(gid):
            m = gid == grp
            if grp < 0:
                kfit = (unit[:, m] @ load[m]) / np.maximum(np.sum(unit[:, m] ** 2, axis=1), 1e-300)
                res = kfit[:, None] * unit[:, m] - load[m]
                cost += np.sum(res**2, axis=1) / np.maximum(np.sum(load[m] ** 2), 1e-300)
            else:
                mu = unit[:, m].mean(axis=1, keepdims=True)
                cost += np.sum((unit[:, m] - mu) ** 2, axis=1) / np.maximum(mu[:, 0] ** 2, 1e-300)
        cost = np.where(ok, cost, np.inf)
        j = int(np.argmin(cost))
        if cost[j] < best:
            best, arg = cost[j], (float(g), float(xs[j]))
    return arg


def fit(data: Dataset | pd.DataFrame, effects: Sequence[Effect] = (), *, bearing: Bearing = PAPER_BEARING,
        sigma_i: float | None = None, sigma_x: float | None = None, mask=None, start_from: FitResult | None = None,
        require_k: bool = False, max_condition: float = 1e8, max_relative_gap_std: float = 0.1,
        p_min: float = 1e-3, max_steps: int = 200, debias: int = 0, seed: int = 0, throw: bool = True) -> FitResult:
    """Weighted least squares of gap, origin (k with known loads, nuisance loads, effect parameters).

    Parameters
    ----------
    data : Dataset or DataFrame
        Contract table (any positions, biases, iterations, both axes).
    effects : sequence of Effect
        Unmodelled physics added to Eq. 4, their ``RANGES`` fields fitted under weak priors;
        ``()`` (default) is the paper's ideal law.
    bearing : Bearing
        The bearing description (pole angle, turns for flux densities, nominal gap for starts).
    sigma_i, sigma_x : float, optional
        Declared current [A] and position [m] noise std, overriding the std columns.
    mask : array[n], optional
        1 for rows to fit, 0 for rows held out (cross-validation); their residuals are still reported.
    start_from : FitResult, optional
        Start at this fit's gap, origin, k and loads (an extended fit starts at the ideal one;
        default: fit the ideal law first).
    require_k : bool
        Raise if ``k`` cannot be identified on a present axis (no known load).
    max_condition, max_relative_gap_std : float
        Identifiability thresholds: condition number of the column-scaled Jacobian, and the
        relative standard error above which a gap counts as not identified.
    p_min : float
        The model is ``adequate`` when χ² has a p-value of at least this (only when the noise
        levels are known, not estimated from the residuals).
    max_steps : int
        Levenberg-Marquardt step budget per reweighting round.  A first solve takes at
        most ``FIRST_STEPS`` per round; if it has not converged, a second one gets ``max_steps``.
    debias : int
        Number of synthetic data sets for the parametric-bootstrap bias correction
        (:mod:`ambfit.estimation.debias`, ideal law only); 0 (default) reports the plain estimate.
    seed : int
        Seed of the bootstrap.
    throw : bool
        Raise :class:`FitError` when the fit did not converge or the design does not identify
        the parameters (default, as optimistix does); with False the result carries the failed
        health flags and their messages instead.

    Raises
    ------
    FitError
        Not identifiable (checked first: an unidentifiable valley is what makes LM
        run out of steps) or not converged; the message says why and what to do.

    Examples
    --------
    >>> from ambfit.rig import protocol, virtual as rig
    >>> sim = rig.simulate(rig.PAPER_RIG, protocol.paper_table2(center=(-33.3e-6, 11.3e-6)), seed=1)
    >>> res = fit(sim.data)
    >>> abs(res.value("g_v0") - 775e-6) < 4 * res.error("g_v0")
    True
    """
    df = data.frame if isinstance(data, Dataset) else data
    df = df.reset_index(drop=True)
    model = Model.of(effects, bearing)
    if debias and model.n:
        raise ValueError("the bootstrap bias correction (debias) is implemented for the ideal law only")
    prob, meta = build_problem(df, sigma_i=sigma_i, sigma_x=sigma_x, mask=mask)
    if require_k:
        _require_k(meta)
    if start_from is None and model.n:
        start_from = fit(df, bearing=bearing, sigma_i=sigma_i, sigma_x=sigma_x, mask=mask, max_steps=max_steps,
                         throw=False)
    theta0, how = _initial(prob, meta, df, model, start_from)
    # The ideal law from a closed-form seed needs a few steps; a second solve (another compilation) only when
    # that was not enough.  Extended fits start further away (effects at their prior centre): one solve.
    first = max_steps if model.n else min(FIRST_STEPS, max_steps)
    theta, result, steps, edm, jac, z = solve_and_measure(jnp.asarray(theta0), prob, model, max_steps=first)
    if not edm < EDM_MAX and max_steps > first:  # a far start: give Levenberg-Marquardt room
        theta, result, more, edm, jac, z = solve_and_measure(theta, prob, model, max_steps=max_steps)
        steps = steps + more
    lm = "successful" if result == optx.RESULTS.successful else str(result)
    theta = np.asarray(theta)
    correction = None
    if debias and edm < EDM_MAX:
        from ambfit.estimation.debias import bootstrap_bias

        correction = bootstrap_bias(theta, prob, prob.bias, n=debias, seed=seed, model=model)
        theta = theta - correction.bias
        jac, z = jacobian(jnp.asarray(theta), prob, model), standardized(jnp.asarray(theta), prob, model)
    thresholds = Thresholds(max_condition=max_condition, max_relative_gap_std=max_relative_gap_std, p_min=p_min,
                            max_steps=max_steps)
    res = _finish(theta, np.asarray(jac), np.asarray(z), float(edm), lm, int(steps), prob, meta, model, how,
                  thresholds)
    if correction is not None:
        res = _with_correction(res, correction, prob, meta)
    if throw:
        res.raise_for_health()
    return res


def _require_k(meta: Meta):
    missing = [ax for a, ax in enumerate(AXES) if meta.axes_present[a] and not meta.k_free[a]]
    if missing:
        raise FitError(f"k is not identifiable on axis {', '.join(missing)}: no row of that axis has a known "
                       "load (load_N). Hang known masses (or give the rotor weight share) to calibrate it; "
                       "the gap and origin do not need it")


def _with_correction(res: FitResult, correction, prob: Problem, meta: Meta) -> FitResult:
    """The result with the bootstrap's subtracted bias recorded per parameter (SI units)."""
    free = free_mask(prob, meta)
    scale = si_scale(prob)[0][free]
    return dataclasses.replace(res, bias_correction={
        "n": correction.n, "converged_fraction": correction.converged_fraction,
        **{n: {"subtracted": float(b), "mc_error": float(e)}
           for n, b, e in zip(res.names, correction.bias[free] * scale, correction.mc_error[free] * scale)}})


def _initial(prob, meta, df, model, start_from):
    """The scaled start vector and how it was found: a given fit's estimate (effects at their prior centre)
    or the closed form / grid."""
    if start_from is None:
        theta, how = start(prob, meta, df, model.bearing)
        return np.concatenate([theta, np.zeros(model.n)]), how
    vals = dict(zip(start_from.names, start_from.values))
    nominal = model.bearing.nominal_gap
    theta = to_theta([vals.get("g_v0", nominal), vals.get("g_w0", nominal)], [vals.get("v0", 0.0), vals.get("w0", 0.0)],
                     [vals.get("k_v", K_REFERENCE), vals.get("k_w", K_REFERENCE)],
                     [vals.get(f"load[{g}]", 0.0) for g in meta.load_groups])
    if not meta.load_groups:
        theta = seed_loads_and_k(theta, prob, Model.of((), model.bearing))
    return np.concatenate([theta, np.zeros(model.n)]), f"from the {start_from.model} fit"


def _finish(theta, jac, z, edm, lm, steps, prob, meta, model, how, thresholds) -> FitResult:
    """Covariance, conditioning and the result record from the Jacobian ``jac`` and standardized residuals ``z``
    at the solution ``theta``."""
    free = free_mask(prob, meta, model)
    names = free_names(meta, free, model)
    used = np.asarray(prob.mask) > 0
    j = jac[:, free]
    dof = int(used.sum()) - int(free.sum())
    if dof < 1:
        raise FitError(f"the design does not identify the parameters: {int(used.sum())} readings for "
                       f"{int(free.sum())} parameters (no redundancy); add positions, biases or repetitions")
    norms = np.linalg.norm(j, axis=0)
    js = j / np.where(norms > 0, norms, 1.0)
    _, sv, vt = np.linalg.svd(js, full_matrices=False)
    cond = float(sv[0] / sv[-1]) if sv[-1] > 0 else np.inf
    scale, offset = si_scale(prob, model)
    chi2 = float(np.sum(z[used] ** 2))
    if cond < 1e15:
        cov_s = np.linalg.pinv(js.T @ js) / np.outer(norms, norms)
    else:
        cov_s = np.full((len(names), len(names)), np.inf)
    if meta.noise_estimated:
        cov_s = cov_s * chi2 / dof
    cov = cov_s * np.outer(scale[free], scale[free])
    std = np.sqrt(np.abs(np.diag(cov)))
    with np.errstate(invalid="ignore", divide="ignore"):
        corr = cov / np.outer(std, std)
    noise = meta.noise_source
    if meta.noise_estimated:
        noise += f" (current noise estimate {np.sqrt(chi2 / dof):.3g} mA)"
    fitted = model.build(jnp.asarray(theta[len(theta) - model.n:]))
    return FitResult(
        names=names, values=offset[free] + theta[free] * scale[free], std=std, cov=cov, corr=corr, chi2=chi2,
        dof=dof, residuals=z, edm=edm, optimistix=lm, num_steps=steps, condition=cond,
        weak_direction=describe_weakness(names, corr, vt[-1]), noise_source=noise, noise_estimated=meta.noise_estimated,
        start=how, k_free=meta.k_free, n_rows=meta.n_rows, n_fit_rows=int(used.sum()), effects=fitted,
        model=model.name, bearing=model.bearing, theta=theta, thresholds=thresholds)


def fit_by(data: Dataset | pd.DataFrame, column: str = "experiment", **kw) -> dict:
    """:func:`fit` on each value of ``column`` separately (a table like the paper's Tables 1-4).

    Returns ``{value: FitResult or FitError}`` so one failing group does not hide the others.
    """
    df = data.frame if isinstance(data, Dataset) else data
    if column not in df.columns:
        raise FitError(f"no column {column!r} to split the data by")
    out = {}
    for key, grp in df.groupby(df[column].astype(str), sort=False):
        try:
            out[key] = fit(grp.reset_index(drop=True), **kw)
        except FitError as exc:
            out[key] = exc
    return out
