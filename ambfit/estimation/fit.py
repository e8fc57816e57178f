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
position sensor symmetrically and needs no root solve per reading.  Its bias of
second order in the noise (errors in variables: a row's Jacobian and weight correlate
with its own noise) is subtracted by default (:mod:`ambfit.estimation.debias`);
unbiasedness, spread at the bound and unit-variance pulls are checked on rig data in the
tests and in ``benchmarks/ls_bias.py`` and ``benchmarks/ls_efficiency.py``.  ``s_eff`` is held fixed while Levenberg-Marquardt
runs and re-evaluated at its estimate (``REWEIGHTINGS`` rounds: iteratively
reweighted least squares), the usual choice that keeps the estimator consistent.

The model is the ideal law (Eq. 4) extended by any tuple of
:mod:`ambfit.physics.effects`; the ideal model is ``effects=()``.

One pipeline
------------
:func:`fit_many` is the only fit; :func:`fit` is ``fit_many([data])[0]``, raising what it holds.  For every data
set, in order: its arrays (:mod:`ambfit.estimation.problem`, many tables built as one), its start
(:mod:`ambfit.estimation.seeds`: Eq. 7 or a grid, ``k`` and loads profiled; or another fit's estimate), the solve
(:mod:`ambfit.estimation.batches`: alone at its own shape, or padded and vmapped with the others), the result
(:mod:`ambfit.estimation.covariance`), the outlier test (:mod:`ambfit.estimation.outliers`) and the plausibility
flags.  A study of thousands of data sets and one fit take the same steps.

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

import numpy as np
import pandas as pd

from ambfit.data import DataError, Dataset, file_rows, zero_based
from ambfit.estimation import plausibility, robust, seeds
from ambfit.estimation.batches import bias_sets, measure_sets, solve_sets
from ambfit.estimation.core import (
    EDM_MAX,
    K_REFERENCE,
    FitError,
    Meta,
    Model,
    Problem,
    free_mask,
    si_scale,
    to_theta,
)
from ambfit.estimation.covariance import results_at
from ambfit.estimation.debias import MAX_SHIFT, debiased
from ambfit.estimation.identification import prior_shares
from ambfit.estimation.outliers import Screening, run_screens, screening, studentized
from ambfit.estimation.problem import build_problems
from ambfit.estimation.results import FitResult, Thresholds
from ambfit.estimation.units import FORCE_CONSTANTS, GAPS, ORIGINS
from ambfit.physics.bearing import AXES, PAPER_BEARING, Bearing
from ambfit.physics.effects import Effect

_FAILURES = (FitError, DataError, ValueError, KeyError)
"""What a data set's own fit can raise; :func:`fit_many` returns it in that data set's place."""


def fit(data: Dataset | pd.DataFrame, effects: Sequence[Effect] = (), *, bearing: Bearing = PAPER_BEARING,
        sigma_i: float | None = None, sigma_x: float | None = None, mask=None, start_from: FitResult | None = None,
        require_k: bool = False, max_condition: float = 1e8, max_relative_gap_std: float = 0.1,
        p_min: float = 1e-3, max_steps: int = 200, loss: str = "auto", alpha: float = robust.ALPHA,
        debias: int | str = "second-order", seed: int = 0, held_noise=None, throw: bool = True) -> FitResult:
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
        Levenberg-Marquardt step budget per reweighting round (:func:`ambfit.estimation.batches.solve_sets`).  Each
        round starts its trust region afresh (step size 1, quartered on each rejected step): a fit continued from
        ``start_from`` a few steps at a time may not move at all in a narrow valley (on the finite-element
        bearing's circuit, 5 steps a round do not; 20 do).
    loss : {"auto", "linear", "huber", "cauchy"}
        ``auto`` (default): least squares with an outlier test on the studentized residuals; readings
        beyond the Bonferroni bound (false-alarm probability ``alpha`` per data set) are named in
        ``outliers`` and left out.  ``linear``: plain least squares (outliers are still named, not
        left out).  ``huber``/``cauchy``: robust losses by reweighting (:mod:`ambfit.estimation.robust`).
    alpha : float
        False-alarm probability of the outlier test on clean data; 0: no test (a refit that leaves out the
        readings its model's fit of every row named, as cross-validation folds do).
    debias : "second-order", "none" or int
        The estimator's bias of second order in the noise, subtracted from the estimate
        (:mod:`ambfit.estimation.debias`): ``"second-order"`` (default) by the delta method, from differences of
        the model at a few dozen points around the estimate (one vmapped program); an integer ``n`` by a parametric bootstrap of ``n``
        synthetic data sets (ideal law only); ``"none"`` (or 0): the plain least-squares estimate.  The result
        is measured at the corrected estimate (residuals, χ², covariance; the shift is a fraction of a standard
        error) and ``bias_correction`` says what was subtracted; the outlier test is the minimum's.  Not applied
        to a fit that did not converge, is not identified, or uses a robust loss (``bias_correction`` then says
        why).
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
        Not identifiable (checked first: an unidentifiable valley is what makes LM run out of steps) or not
        converged; the message says why and what to do; its ``result`` is the fit's :class:`FitResult`, if any.

    Examples
    --------
    >>> from ambfit.rig import protocol, virtual as rig
    >>> sim = rig.simulate(rig.PAPER_RIG, protocol.paper_table2(center=(-33.3e-6, 11.3e-6)), seed=1)
    >>> res = fit(sim.data)
    >>> abs(res.value("g_v0") - 775e-6) < 4 * res.error("g_v0")
    True
    """
    out = fit_many([data], effects, bearing=bearing, sigma_i=sigma_i, sigma_x=sigma_x,
                   mask=None if mask is None else [mask], start_from=None if start_from is None else [start_from],
                   held_noise=None if held_noise is None else [held_noise], require_k=require_k,
                   max_condition=max_condition, max_relative_gap_std=max_relative_gap_std, p_min=p_min,
                   max_steps=max_steps, loss=loss, alpha=alpha, debias=debias, seed=seed)[0]
    if isinstance(out, BaseException):
        raise out
    if throw:
        out.raise_for_health()
    return out


def _each(value, n: int, name: str) -> list:
    """``value`` per data set: None for all, or a sequence of one entry per data set."""
    if value is None:
        return [None] * n
    value = list(value)
    if len(value) != n:
        raise ValueError(f"{name}: one entry per data set ({n}), got {len(value)}")
    return value


def fit_many(datasets: Sequence[Dataset | pd.DataFrame], effects: Sequence[Effect] = (), *,
             bearing: Bearing | Sequence[Bearing] = PAPER_BEARING, sigma_i: float | None = None,
             sigma_x: float | None = None, mask: Sequence | None = None,
             start_from: Sequence[FitResult | None] | None = None, held_noise: Sequence | None = None,
             require_k: bool = False, max_condition: float = 1e8, max_relative_gap_std: float = 0.1,
             p_min: float = 1e-3, max_steps: int = 200, loss: str = "auto", alpha: float = robust.ALPHA,
             debias: int | str = "second-order", seed: int = 0, name_outliers: bool = True) -> list:
    """:func:`fit` of every data set (health as data, as with ``throw=False``), solved together.

    The data sets may differ in length, axes, biases, set-points, iterations, load groups and bearing; each
    result is the one :func:`fit` gives for that data set alone (it is this function on one data set).  Their
    solves are bucketed by padded length and number of loads and vmapped (:func:`ambfit.estimation.batches.solve_sets`),
    so thousands of data sets cost a few compilations and little more than their solve.

    Parameters
    ----------
    datasets : sequence of Dataset or DataFrame
        Contract tables.
    effects, sigma_i, sigma_x, require_k, max_condition, max_relative_gap_std, p_min, max_steps, loss, alpha, debias, seed
        As in :func:`fit`, for every data set.
    bearing : Bearing or sequence of Bearing
        One bearing for all, or one per data set.
    mask, start_from, held_noise : sequence, optional
        As in :func:`fit`, one entry per data set (None in a place: that data set's default).
    name_outliers : bool
        Run the outlier test (default); False: least squares of every row of every data set with no test (a Monte
        Carlo study's estimates: what ``loss="linear"`` gives, without naming the readings beyond the bound; the
        bias correction as ``debias`` says).

    Returns
    -------
    list of FitResult or Exception
        One entry per data set, in order: its result, or the :class:`FitError` / :class:`ambfit.data.DataError` its
        fit raised.
    """
    if loss not in robust.LOSSES:
        raise ValueError(f"loss must be one of {robust.LOSSES}, got {loss!r}")
    frames = [d.frame if isinstance(d, Dataset) else d for d in datasets]
    n = len(frames)
    bearings = list(bearing) if isinstance(bearing, (list, tuple)) else [bearing] * n
    if len(bearings) != n:
        raise ValueError(f"bearing: one for all data sets or one per data set ({n}), got {len(bearings)}")
    masks, froms, helds = _each(mask, n, "mask"), _each(start_from, n, "start_from"), _each(held_noise, n, "held_noise")
    second_order, debias = _debias_mode(debias)
    if debias and tuple(effects):
        raise ValueError("the bootstrap bias correction (debias) is implemented for the ideal law only")
    thresholds = Thresholds(max_condition=max_condition, max_relative_gap_std=max_relative_gap_std, p_min=p_min,
                            max_steps=max_steps)
    opts = dict(sigma_i=sigma_i, sigma_x=sigma_x, require_k=require_k, max_condition=max_condition,
                max_relative_gap_std=max_relative_gap_std, p_min=p_min, max_steps=max_steps, loss=loss, alpha=alpha)
    if n == 0:
        return []
    rows = [file_rows(df) for df in frames]
    dfs = [zero_based(df) for df in frames]
    out: list = [None] * n
    table, built, offsets = build_problems(dfs, sigma_i=sigma_i, sigma_x=sigma_x)
    probs: list = [None] * n
    for s in range(n):
        if isinstance(built[s], BaseException):
            out[s] = built[s]
            continue
        prob, meta = built[s]
        try:
            if not meta.n_rows:
                raise FitError("the data set has no readings")
            if masks[s] is not None:
                prob = prob.with_mask(_checked(masks[s], len(dfs[s]), "mask"))
            if helds[s] is not None:
                prob = prob.with_noise(_checked(helds[s], len(dfs[s]), "held_noise"))
            if require_k:
                _require_k(meta)
        except _FAILURES as exc:
            out[s] = exc
            continue
        probs[s] = prob
    models = {b: Model.of(effects, b) for b in dict.fromkeys(bearings)}
    inherited: list = [()] * n
    if tuple(effects):
        # an extended model starts from the ideal law's fit, without that fit's outliers
        todo = [s for s in range(n) if out[s] is None and froms[s] is None]
        ideal = fit_many([dfs[s] for s in todo], (), bearing=[bearings[s] for s in todo],
                         mask=[masks[s] for s in todo], debias="none", **opts)
        for s, res in zip(todo, ideal):
            if isinstance(res, BaseException):
                out[s] = res
                continue
            froms[s] = res
            if res.outliers and loss == "auto":
                probs[s] = probs[s].with_mask(np.asarray(probs[s].mask) * res.fitted_rows.astype(float))
                # (that fit numbered the rows of the re-indexed table: back to file rows)
                inherited[s] = tuple(dataclasses.replace(o, row=int(rows[s][o.row - 1])) for o in res.outliers)
    live = [s for s in range(n) if out[s] is None]
    starts: dict = {}
    need = [s for s in live if froms[s] is None]
    if need:
        if len(need) < n:     # the needed data sets' rows of the table
            table = table.iloc[np.concatenate([np.arange(offsets[s], offsets[s + 1]) for s in need])]
            table = table.reset_index(drop=True)
        thetas, how = seeds.starts(table, [probs[s] for s in need], [built[s][1] for s in need],
                                   np.cumsum([0] + [len(dfs[s]) for s in need]), [bearings[s] for s in need])
        starts.update({s: (np.concatenate([t, np.zeros(models[bearings[s]].n)]), h)
                       for s, t, h in zip(need, thetas, how)})
    for s in live:
        if froms[s] is not None:
            starts[s] = _initial(probs[s], built[s][1], models[bearings[s]], froms[s])
    for b, model in models.items():
        members = [s for s in live if bearings[s] == b]
        if not members:
            continue
        sols = solve_sets([starts[s][0] for s in members], [probs[s] for s in members], model, max_steps)
        extras = [dict(loss=loss, rows=rows[s], weights=np.asarray(probs[s].mask, dtype=float)) for s in members]
        for s, res in zip(members, results_at(sols, [probs[s] for s in members], [built[s][1] for s in members],
                                              model, [starts[s][1] for s in members], thresholds, extras)):
            out[s] = res
    fitted = [s for s in live if not isinstance(out[s], BaseException)]
    t: dict = {}
    if name_outliers and loss in ("auto", "linear") and alpha > 0 and not debias:
        # the outlier test's residuals of every fit at once (the fits with outliers then refit together)
        t = {s: v for s, v in zip(fitted, studentized([out[s] for s in fitted], [probs[s] for s in fitted],
                                                      [built[s][1] for s in fitted])) if v is not None}
    finishing = {}
    for s in fitted:
        res = out[s]
        base = np.asarray(probs[s].mask, dtype=float)
        used = base > 0
        if s in t and not inherited[s] and np.all(np.isfinite(res.residuals[used])) and \
                not np.any(np.abs(t[s][used]) > robust.threshold(int(used.sum()), alpha, built[s][1].noise_estimated)):
            # clean (the common case of a study): plain least squares, as screening finds it, without a refit
            # (its loss, rows and weights were set as it was made)
            flags = plausibility.check_result(dict(zip(res.names, res.values)), models[bearings[s]].bearing)
            if flags:
                out[s] = dataclasses.replace(res, implausible=tuple(flags))
            continue
        finishing[s] = _finishing(out[s], probs[s], built[s][1], dfs[s], models[bearings[s]], rows[s], loss=loss,
                                  alpha=alpha if name_outliers else 0.0, debias=debias, seed=seed,
                                  thresholds=thresholds, inherited=inherited[s], name_outliers=name_outliers,
                                  t=t.get(s))

    def refits(asked: dict) -> list:
        """The refits the screens ask for in one round, those of one bearing solved together (a batch that fails
        fails each of its data sets, as their refits alone would)."""
        done = {}
        for b, model in models.items():
            firsts = {}
            for s in (s for s in asked if bearings[s] == b):
                try:
                    firsts[s] = _initial(asked[s].prob, built[s][1], model, asked[s].start)
                except _FAILURES as exc:
                    done[s] = exc
            if not firsts:
                continue
            mine = list(firsts)
            try:
                sols = solve_sets([firsts[s][0] for s in mine], [asked[s].prob for s in mine], model, max_steps)
                done.update(zip(mine, results_at(sols, [asked[s].prob for s in mine], [built[s][1] for s in mine],
                                                 model, [firsts[s][1] for s in mine], thresholds)))
            except _FAILURES as exc:
                done.update(dict.fromkeys(mine, exc))
        return [done[s] for s in asked]

    for s, res in run_screens(finishing, refits, errors=_FAILURES).items():
        out[s] = res
    if second_order:
        _subtract_bias(out, fitted, probs, {s: built[s][1] for s in fitted}, models, bearings, thresholds)
    for s in fitted:    # an effect these data do not determine makes the solver wander: say which, from the start
        res = out[s]
        if models[bearings[s]].n and isinstance(res, FitResult) and not res.converged and froms[s] is not None \
                and froms[s].model == "ideal":
            out[s] = dataclasses.replace(res, effect_identification=prior_shares(probs[s], built[s][1],
                                                                                 models[bearings[s]], froms[s]))
    return out


DEBIAS = ("second-order", "none")
"""The named bias corrections of :func:`fit` (an integer asks for the bootstrap)."""


def _debias_mode(debias) -> tuple[bool, int]:
    """``(second order, bootstrap sets)`` from :func:`fit`'s ``debias``."""
    if isinstance(debias, str):
        if debias not in DEBIAS:
            raise ValueError(f"debias must be one of {DEBIAS} or a number of bootstrap sets, got {debias!r}")
        return debias == "second-order", 0
    if isinstance(debias, bool) or not isinstance(debias, (int, np.integer)) or debias < 0:
        raise ValueError(f"debias must be one of {DEBIAS} or a number of bootstrap sets (>= 0), got {debias!r}")
    return False, int(debias)


def _not_corrected(res: FitResult) -> str | None:
    """Why the second-order correction does not apply to ``res`` (None: it does)."""
    if res.loss not in ("auto", "linear"):
        return f"the {res.loss} loss' estimate is not the least-squares one the expansion describes"
    if not res.edm < EDM_MAX:
        return "the fit did not converge"
    if not (res.well_conditioned and np.all(np.isfinite(res.cov))):
        return "the design does not identify the parameters"
    return None


def _subtract_bias(out: list, fitted: list, probs: list, metas: dict, models: dict, bearings: list,
                   thresholds: Thresholds):
    """Each fitted least-squares result of ``out`` less its second-order bias (:func:`ambfit.estimation.debias.
    second_order_biases`), in place, measured again at the corrected estimate (residuals, χ², covariance); the
    solve's record (steps, EDM, outcome) and the outlier test stay as they were.  A fit the correction does not
    apply to (:func:`_not_corrected`) keeps its estimate, and its ``bias_correction`` says why."""
    def skipped(s, why):
        out[s] = dataclasses.replace(out[s], bias_correction={"method": "second-order", "skipped": why})

    for b, model in models.items():
        mine = [s for s in fitted if bearings[s] == b and isinstance(out[s], FitResult) and not out[s].bias_correction]
        for s in mine:
            why = _not_corrected(out[s])
            if why:
                skipped(s, why)
        todo = [s for s in mine if not out[s].bias_correction]
        if not todo:
            continue
        # the rows each fit used, at the caller's weights (an outlier test records its own as 0 or 1)
        ps = [_used_rows(probs[s], out[s].weights) for s in todo]
        frees = [free_mask(p, metas[s], model) for p, s in zip(ps, todo)]
        scales = [si_scale(p, model)[0] for p in ps]
        covs = [out[s].cov / np.outer(sc[f], sc[f]) for s, f, sc in zip(todo, frees, scales)]
        # the bias grows with the noise variance: a current noise estimated from the residuals is the unit
        # weights' times the reduced χ² (the position noise is then declared, or none)
        shares = [(out[s].reduced_chi2,) * 2 + (1.0,) if out[s].noise_estimated else (1.0, 1.0, 1.0) for s in todo]
        biases = bias_sets([out[s].theta for s in todo], ps, model, frees, covs, shares)
        keep = []
        for j, (s, bias, free, cov) in enumerate(zip(todo, biases, frees, covs)):
            if not np.all(np.isfinite(bias)):
                skipped(s, "the estimating equation does not determine the estimate (a singular derivative)")
                continue
            joint = float(max(bias[free] @ np.linalg.lstsq(cov, bias[free], rcond=None)[0], 0.0))
            shift = np.sqrt(joint * free.sum() / max(out[s].n_fit_rows, 1))
            if shift > MAX_SHIFT:
                skipped(s, f"the second-order term moves the estimate by {shift:.2g} standard errors of a fit of as "
                           f"many readings as parameters (more than {MAX_SHIFT:g}): the expansion's higher orders "
                           "are not negligible")
                continue
            keep.append(j)
        thetas = [np.asarray(out[todo[j]].theta) - biases[j] for j in keep]
        again = results_at(measure_sets(thetas, [ps[j] for j in keep], model), [ps[j] for j in keep],
                           [metas[todo[j]] for j in keep], model, [out[todo[j]].start for j in keep], thresholds)
        for j, new in zip(keep, again):
            s, res, free, scale = todo[j], out[todo[j]], frees[j], scales[j]
            if isinstance(new, BaseException):
                skipped(s, f"the corrected estimate cannot be measured: {new}")
                continue
            moved = {f: getattr(new, f) for f in _AT_ESTIMATE}
            subtracted = biases[j][free] * scale[free]
            out[s] = dataclasses.replace(
                res, **moved,
                bias_correction={"method": "second-order",
                                 **{n: {"subtracted": float(v)} for n, v in zip(res.names, subtracted)}},
                implausible=tuple(plausibility.check_result(dict(zip(res.names, new.values)), model.bearing)))


def _used_rows(prob: Problem, weights) -> Problem:
    """``prob`` with the rows a fit gave no weight to masked out (itself when that changes nothing)."""
    if weights is None:
        return prob
    mask = np.asarray(prob.mask)
    used = mask * (np.asarray(weights) > 0)
    return prob if np.array_equal(used, mask) else prob.with_mask(used)


_AT_ESTIMATE = ("values", "std", "cov", "corr", "chi2", "dof", "residuals", "condition", "weak_direction",
                "noise_source", "theta", "effects", "jacobian_rows", "row_noise")
"""What a result measures at its estimate (the rest is the solve's record, the outlier test and the flags)."""


def _finishing(res, prob, meta, df, model, rows, *, loss, alpha, debias, seed, thresholds, inherited, name_outliers,
               t=None) -> Screening:
    """A data set's result after its solve: the bias correction, the outlier test (or the robust loss; ``t`` its
    studentized residuals when measured with the other data sets') and the plausibility flags.  A generator of the
    refits and residuals the test asks for (:func:`ambfit.estimation.outliers.run_screens`: a study's measured
    together)."""
    if debias and res.edm < EDM_MAX:
        res = debiased(res, prob, meta, model, thresholds, debias, seed)
    if name_outliers:
        res = yield from screening(res, prob, meta, df, model, loss, alpha, rows, t)
        more = {}
    else:
        more = dict(loss="linear", rows=rows, weights=np.asarray(prob.mask, dtype=float))
    if inherited:       # left out before this model was fitted: still named (as the ideal fit judged them)
        more["outliers"] = inherited + tuple(res.outliers)
    flags = plausibility.check_result(dict(zip(res.names, res.values)), model.bearing)
    return dataclasses.replace(res, implausible=tuple(flags), **more)


def _checked(values, n: int, name: str) -> np.ndarray:
    values = np.asarray(values, dtype=float)
    if values.shape != (n,):
        raise ValueError(f"{name} needs one value per row ({n}), got shape {values.shape}")
    return values


def _require_k(meta: Meta):
    missing = [ax for a, ax in enumerate(AXES) if meta.axes_present[a] and not meta.k_free[a]]
    if missing:
        raise FitError(f"k is not identifiable on axis {', '.join(missing)}: no row of that axis has a known "
                       "load (load_N). Hang known masses (or give the rotor weight share) to calibrate it; "
                       "the gap and origin do not need it")


def _initial(prob: Problem, meta: Meta, model: Model, start_from: FitResult) -> tuple[np.ndarray, str]:
    """The scaled start vector from another fit's estimate (effects at their prior centre) and how it was found."""
    if start_from.model == model.name and len(start_from.theta) == len(si_scale(prob, model)[0]):
        return np.asarray(start_from.theta), start_from.start      # a refit of the same model (robust rounds)
    vals = dict(zip(start_from.names, start_from.values))
    nominal = model.bearing.nominal_gap
    theta = to_theta([vals.get(n, nominal) for n in GAPS], [vals.get(n, 0.0) for n in ORIGINS],
                     [vals.get(n, K_REFERENCE) for n in FORCE_CONSTANTS],
                     [vals.get(f"load[{g}]", 0.0) for g in meta.load_groups])
    if not meta.load_groups:
        theta = seeds.seed_loads_and_k(theta, prob, model.bearing)
    return np.concatenate([theta, np.zeros(model.n)]), f"from the {start_from.model} fit"


def fit_by(data: Dataset | pd.DataFrame, column: str = "experiment", *, throw: bool = True, **kw) -> dict:
    """:func:`fit` on each value of ``column`` separately (a table like the paper's Tables 1-4), the groups solved
    together (:func:`fit_many`).

    Returns ``{value: FitResult or FitError}`` so one failing group does not hide the others.
    """
    df = data.frame if isinstance(data, Dataset) else data
    if column not in df.columns:
        raise FitError(f"no column {column!r} to split the data by")
    groups = [(key, grp.reset_index(drop=True)) for key, grp in df.groupby(df[column].astype(str), sort=False)]
    out = {}
    for (key, _), res in zip(groups, fit_many([g for _, g in groups], **kw)):
        if not isinstance(res, BaseException) and throw:
            try:
                res.raise_for_health()
            except FitError as exc:
                res = exc
        if isinstance(res, BaseException) and not isinstance(res, FitError):
            raise res
        out[key] = res
    return out

