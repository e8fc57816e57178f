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

from ambfit.data import Dataset, file_rows, load_groups, zero_based
from ambfit.estimation import closed_form, plausibility, robust
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
    row_jacobian,
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
        p_min: float = 1e-3, max_steps: int = 200, loss: str = "auto", alpha: float = robust.ALPHA,
        debias: int = 0, seed: int = 0, held_noise=None, throw: bool = True) -> FitResult:
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
    loss : {"auto", "linear", "huber", "cauchy"}
        ``auto`` (default): least squares with an outlier test on the studentized residuals; readings
        beyond the Bonferroni bound (false-alarm probability ``alpha`` per data set) are named in
        ``outliers`` and left out.  ``linear``: plain least squares (outliers are still named, not
        left out).  ``huber``/``cauchy``: robust losses by reweighting (:mod:`ambfit.estimation.robust`).
    alpha : float
        False-alarm probability of the outlier test on clean data; 0: no test (a refit that leaves out the
        readings its model's fit of every row named, as cross-validation folds do).
    debias : int
        Number of synthetic data sets for the parametric-bootstrap bias correction
        (:mod:`ambfit.estimation.debias`, ideal law only); 0 (default) reports the plain estimate.
    seed : int
        Seed of the bootstrap.
    held_noise : array[n], optional
        Each row's effective force noise std [N], held instead of propagated through the model at each
        reweighting round: nested models compared by their χ² rise hold the full model's (the same weights for
        every model, and a plain least-squares objective for Levenberg-Marquardt).
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
    if loss not in robust.LOSSES:
        raise ValueError(f"loss must be one of {robust.LOSSES}, got {loss!r}")
    rows = file_rows(df)
    df = zero_based(df)
    model = Model.of(effects, bearing)
    if debias and model.n:
        raise ValueError("the bootstrap bias correction (debias) is implemented for the ideal law only")
    prob, meta = build_problem(df, sigma_i=sigma_i, sigma_x=sigma_x, mask=mask)
    if held_noise is not None:
        prob = prob.with_noise(held_noise)
    if require_k:
        _require_k(meta)
    inherited = ()
    if start_from is None and model.n:
        start_from = fit(df, bearing=bearing, sigma_i=sigma_i, sigma_x=sigma_x, mask=mask, max_steps=max_steps,
                         loss=loss, alpha=alpha, throw=False)
        if start_from.outliers and loss == "auto":     # the extended model starts without the ideal fit's outliers
            prob = prob.with_mask(np.asarray(prob.mask) * start_from.fitted_rows.astype(float))
            # (that fit numbered rows of the re-indexed table: back to file rows)
            inherited = tuple(dataclasses.replace(o, row=int(rows[o.row - 1])) for o in start_from.outliers)
    thresholds = Thresholds(max_condition=max_condition, max_relative_gap_std=max_relative_gap_std, p_min=p_min,
                            max_steps=max_steps)
    res = _fit_once(prob, meta, df, model, start_from, max_steps, thresholds, debias, seed)
    res = _robust(res, prob, meta, df, model, max_steps, thresholds, loss, alpha, rows)
    if inherited:       # left out before this model was fitted: still named (as the ideal fit judged them)
        res = dataclasses.replace(res, outliers=inherited + tuple(res.outliers))
    res = dataclasses.replace(res, implausible=tuple(plausibility.check_result(dict(zip(res.names, res.values)),
                                                                                bearing)))
    if throw:
        res.raise_for_health()
    return res


def _fit_once(prob, meta, df, model, start_from, max_steps, thresholds, debias=0, seed=0) -> FitResult:
    """One weighted least-squares fit of ``prob`` (its mask as row weights)."""
    theta0, how = _initial(prob, meta, df, model, start_from)
    # The ideal law from a closed-form seed needs a few steps; a second solve (another compilation) only when
    # that was not enough.  Extended fits start further away (effects at their prior centre): one solve.
    first = max_steps if model.n else min(FIRST_STEPS, max_steps)
    theta, result, steps, edm, jac, z, rows = solve_and_measure(jnp.asarray(theta0), prob, model, max_steps=first,
                                                                every_row=True)
    if not edm < EDM_MAX and max_steps > first:  # a far start: give Levenberg-Marquardt room
        theta, result, more, edm, jac, z, rows = solve_and_measure(theta, prob, model, max_steps=max_steps,
                                                                   every_row=True)
        steps = steps + more
    if not edm < EDM_MAX and model.n and steps < max_steps:
        # the effective-variance weights moved after the last round (strongly nonlinear models): one more
        # solve with the same compiled function settles them
        theta, result, more, edm, jac, z, rows = solve_and_measure(theta, prob, model, max_steps=max_steps,
                                                                   every_row=True)
        steps = steps + more
    lm = "successful" if result == optx.RESULTS.successful else str(result)
    theta = np.asarray(theta)
    correction = None
    if debias and edm < EDM_MAX:
        from ambfit.estimation.debias import bootstrap_bias

        correction = bootstrap_bias(theta, prob, prob.bias, n=debias, seed=seed, model=model)
        theta = theta - correction.bias
        jac, z = jacobian(jnp.asarray(theta), prob, model), standardized(jnp.asarray(theta), prob, model)
        rows = row_jacobian(theta, prob, meta, model)
    else:
        rows = np.asarray(rows)[: len(prob.mask)][:, free_mask(prob, meta, model)]
    res = _finish(theta, np.asarray(jac), np.asarray(z), float(edm), lm, int(steps), prob, meta, model, how,
                  thresholds)
    res = dataclasses.replace(res, jacobian_rows=rows)
    if correction is not None:
        res = _with_correction(res, correction, prob, meta)
    return res


def _studentized(res: FitResult, prob: Problem, meta: Meta, model: Model) -> np.ndarray:
    """Studentized residuals of every row at ``res`` (fit weights from ``prob.mask``)."""
    # measured with the solve (same theta, same model)
    jac = res.jacobian_rows if res.jacobian_rows is not None else row_jacobian(res.theta, prob, meta, model)
    w = np.asarray(prob.mask) ** 2
    return robust.studentized(jac, res.residuals, w > 0, w, known_noise=not meta.noise_estimated)


def _reweighted(res, prob, meta, df, model, max_steps, thresholds, loss, base):
    """Iteratively reweighted least squares with the robust ``loss`` from ``res``: ``(result, weights)``."""
    w = base.copy()
    for _ in range(robust.MAX_ROUNDS):
        t = _studentized(res, prob.with_mask(np.sqrt(w)), meta, model)
        new = base * robust.weights(t, loss)
        if np.max(np.abs(new - w)) < 1e-3:
            break
        w = new
        res = _fit_once(prob.with_mask(np.sqrt(w)), meta, df, model, res, max_steps, thresholds)
    return res, w


def _robust(res, prob, meta, df, model, max_steps, thresholds, loss, alpha, rows) -> FitResult:
    """The outlier test (``auto``, ``linear``) or the robust loss's reweighting, starting from the plain fit ``res``.

    The test judges each reading against a fit the outliers cannot drag (Cauchy reweighting; one reading 17 σ
    off pulls plain least squares so far that its neighbours look off too), then leaves the outliers out and
    refits by plain least squares, repeating until no new reading is beyond the bound.
    """
    base = np.asarray(prob.mask, dtype=float)
    if not np.all(np.isfinite(res.residuals[base > 0])):
        return res
    # (a plain fit dragged by gross outliers may not converge within its step budget; the robust rounds start
    # from it and are judged by their own convergence)
    plain = res
    if loss in ("huber", "cauchy"):
        res, w = _reweighted(res, prob, meta, df, model, max_steps, thresholds, loss, base)
        return dataclasses.replace(res, loss=loss, weights=w, rows=rows, plain_shift=_shift(plain, res))
    if alpha <= 0:                                     # no outlier test
        return dataclasses.replace(res, loss=loss, rows=rows, weights=base)
    fitted = base > 0
    limit = robust.threshold(int(fitted.sum()), alpha)
    if not np.any(np.abs(_studentized(res, prob, meta, model)[fitted]) > limit):
        return dataclasses.replace(res, loss=loss, rows=rows, weights=base)          # clean: plain least squares
    anchor, _ = _reweighted(res, prob, meta, df, model, max_steps, thresholds, "cauchy", base)
    out = (np.abs(_studentized(anchor, prob.with_mask(base), meta, model)) > limit) & fitted
    cur = prob
    for _ in range(robust.MAX_ROUNDS):
        if out.sum() > robust.MAX_FRACTION * fitted.sum():
            return dataclasses.replace(plain, loss=loss, rows=rows, weights=base, outlier_note=(
                f"{int(out.sum())} readings lie beyond the outlier bound |t| > {limit:.2f}: more than "
                f"{robust.MAX_FRACTION:.0%} of the data, so not a few bad readings but a model that does not fit "
                "them (none was left out); run ambfit diagnose"))
        if loss == "linear" or not out.any():
            break
        cur = prob.with_mask(base * ~out)
        res = _fit_once(cur, meta, df, model, res, max_steps, thresholds)
        # judged again against the fit without them (a left-out reading is tested as a prediction)
        new = (np.abs(_studentized(res, cur, meta, model)) > limit) & fitted
        if np.array_equal(new, out):
            break
        out = new
    if loss == "linear":
        res, cur = plain, prob
    t = _studentized(res, cur, meta, model)
    found = tuple(_outlier(j, t[j], df, res, prob, rows) for j in np.nonzero(out)[0])
    return dataclasses.replace(res, loss=loss, rows=rows, weights=np.asarray(cur.mask) ** 2, outliers=found,
                               plain_shift=_shift(plain, res) if found and loss == "auto" else None)


def _shift(plain: FitResult, res: FitResult) -> dict:
    """How far plain least squares sits from ``res``, per head parameter, in ``res``'s standard errors."""
    return {n: (plain.value(n) - res.value(n)) / res.error(n) for n in ("g_v0", "v0", "g_w0", "w0", "k_v", "k_w")
            if n in res.names and n in plain.names and res.error(n) > 0}


def _outlier(j: int, t: float, df: pd.DataFrame, res: FitResult, prob: Problem, rows) -> robust.Outlier:
    """The record of row ``j`` (0-based in ``df``): its reading and the values that would make it fit."""
    r = df.iloc[j]
    ax = str(r["axis"])
    own = f"{ax}_um"
    reading = {"i_top_A": float(r["i_top_A"]), "i_bottom_A": float(r["i_bottom_A"]), own: float(r[own])}
    if "load_N" in df.columns and np.isfinite(r["load_N"]):
        reading["load_N"] = float(r["load_N"])
    vals = dict(zip(res.names, res.values))
    g0, x0 = vals.get(f"g_{ax}0", np.nan), vals.get(f"{ax}0", 0.0)
    k = vals.get(f"k_{ax}", K_REFERENCE)
    load = float(np.asarray(prob.load)[j]) if bool(np.asarray(prob.known)[j]) else \
        vals.get(f"load[{load_groups(df).iloc[j]}]", np.nan)
    alt = {}
    if np.isfinite(g0) and np.isfinite(load):
        alt = robust.fits_with(reading["i_top_A"], reading["i_bottom_A"], reading[own] * 1e-6, load, g0, x0, k,
                               res.bearing.cos_alpha)
        if "x_um" in alt:
            alt[own] = alt.pop("x_um")
    return robust.Outlier(row=int(rows[j]), axis=ax, t=float(t), reading=reading, fits_with=alt)


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
    if start_from.model == model.name and len(start_from.theta) == len(si_scale(prob, model)[0]):
        return np.asarray(start_from.theta), start_from.start      # a refit of the same model (robust rounds)
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
    bad = (~np.isfinite(z[: len(used)]) | ~np.all(np.isfinite(jac[: len(used)]), axis=1)) & used
    if bad.any() or not np.all(np.isfinite(theta)):
        first = int(np.argmax(bad)) + 1 if bad.any() else None
        raise FitError(f"the force law gives non-finite values{f' on {int(bad.sum())} row(s), the first row {first}' if first else ''}"
                       " at the estimate (a pole gap closed, or currents and positions the law cannot use); check "
                       "those rows' units and values (ambfit check)")
    norms = np.linalg.norm(j, axis=0)
    js = j / np.where(norms > 0, norms, 1.0)
    try:
        _, sv, vt = np.linalg.svd(js, full_matrices=False)
    except np.linalg.LinAlgError:
        raise FitError("the fit's Jacobian could not be decomposed (SVD did not converge): the readings span "
                       "values the force law cannot handle; check units and extreme values (ambfit check)") from None
    cond = float(sv[0] / sv[-1]) if sv[-1] > 0 else np.inf
    scale, offset = si_scale(prob, model)
    weight = np.asarray(prob.mask, dtype=float) ** 2     # 1, a robust loss's weight, or 0 for a left-out row
    chi2 = float(np.sum(weight[used] * z[used] ** 2))
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
