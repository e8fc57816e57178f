"""From a solution to a result: covariance, conditioning and χ² of the least-squares estimate.

The covariance is the inverse of the information ``J^T J`` of the standardized residuals (the Cramér-Rao bound of
:mod:`ambfit.estimation.information` at the estimate), scaled by the reduced χ² when the noise levels were
estimated from the residuals.  Conditioning is judged on the column-scaled Jacobian (its SVD), since
Levenberg-Marquardt reports success on problems that do not identify their parameters.  :func:`results_at` works
on a whole batch at once: the data sets of a study that share a design share one stacked SVD.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from ambfit.estimation.core import FitError, Meta, Model, Problem, free_mask, free_names, si_scale
from ambfit.estimation.lm import Solution
from ambfit.estimation.results import FitResult, Thresholds


def describe_weakness(names: Sequence[str], corr: np.ndarray, vt_last: np.ndarray) -> str:
    """The least-determined direction in words: the most correlated pair and the weakest singular vector."""
    return describe_weaknesses(names, np.asarray(corr)[None], np.asarray(vt_last)[None])[0]


def describe_weaknesses(names: Sequence[str], corr: np.ndarray, vt_last: np.ndarray) -> list[str]:
    """:func:`describe_weakness` of many fits of the same parameters: ``corr[sets, p, p]``, ``vt_last[sets, p]``."""
    corr, vt_last = np.asarray(corr), np.asarray(vt_last)
    sets, p = vt_last.shape
    top = np.argsort(-np.abs(vt_last), axis=1)[:, :2]
    pair = None
    if p > 1:
        c = np.nan_to_num(np.abs(corr), nan=0.0) - np.eye(p)
        flat = np.argmax(c.reshape(sets, -1), axis=1)
        pair = np.unravel_index(flat, (p, p))
    out = []
    for b in range(sets):
        text = []
        if pair is not None:
            i, j = pair[0][b], pair[1][b]
            r = corr[b, i, j]
            if np.isfinite(r) and abs(r) <= 1.0 + 1e-9:
                text.append(f"{names[i]} and {names[j]} are {100 * abs(r):.1f} % {'anti-' if r < 0 else ''}correlated")
        text.append("weakest direction mostly " + " and ".join(names[t] for t in top[b]))
        out.append("; ".join(text))
    return out


def result_at(sol: Solution, prob: Problem, meta: Meta, model: Model, how: str, thresholds: Thresholds) -> FitResult:
    """The :class:`FitResult` of the solution ``sol`` of ``prob`` (NumPy leaves, ``result`` as text).

    Raises
    ------
    FitError
        Fewer readings than parameters, or a force law that is not finite at the estimate.
    """
    out = results_at([sol], [prob], [meta], model, [how], thresholds)[0]
    if isinstance(out, FitError):
        raise out
    return out


def _problems(used: np.ndarray, n_free: int, z: np.ndarray, jac: np.ndarray, theta: np.ndarray, file_rows) -> list:
    """Why each of a group of alike solutions has no result (``used[sets, rows]``, ``z``, ``jac`` and ``theta``
    stacked): fewer readings than parameters, or values that are not finite; None where there is a result.
    ``file_rows``: each set's data rows as messages count them (None: its rows from 1)."""
    rows = used.shape[1]
    dof = used.sum(axis=1) - n_free
    bad = (~np.isfinite(z[:, :rows]) | ~np.all(np.isfinite(jac[:, :rows]), axis=2)) & used
    theta_bad = ~np.all(np.isfinite(theta), axis=1)
    out: list = [None] * len(used)
    for b in np.nonzero((dof < 1) | bad.any(axis=1) | theta_bad)[0]:
        if dof[b] < 1:
            out[b] = FitError(f"the design does not identify the parameters: {int(used[b].sum())} readings for "
                              f"{n_free} parameters (no redundancy); add positions, biases or repetitions")
            continue
        count = int(bad[b].sum())
        j = int(np.argmax(bad[b]))
        row = int(file_rows[b][j]) if file_rows[b] is not None else j + 1
        where = f" on {count} row(s), the first data row {row}" if count else ""
        out[b] = FitError(f"the force law gives non-finite values{where} at the estimate (a pole gap closed, or "
                          "currents and positions the law cannot use); check those rows' units and values "
                          "(ambfit check)")
    return out


def results_at(sols: Sequence[Solution], probs: Sequence[Problem], metas: Sequence[Meta], model: Model,
               hows: Sequence[str], thresholds: Thresholds, extras: Sequence[dict] | None = None) -> list:
    """:func:`result_at` of every solution: a :class:`FitResult`, or the :class:`FitError` saying why there is none.
    ``extras``: more fields of each result (how its fit treats outliers, its file rows), set as it is made.

    Solutions whose problems have the same rows, free parameters and load groups are measured together: one
    stacked SVD of their column-scaled Jacobians gives conditioning and covariance.
    """
    out: list = [None] * len(sols)
    groups: dict = {}
    frees: dict = {}
    for s, (sol, prob, meta) in enumerate(zip(sols, probs, metas)):
        shape = (meta.axes_present, meta.k_free, len(meta.load_groups))
        if shape not in frees:
            frees[shape] = free_mask(prob, meta, model)
        free = frees[shape]
        key = (free.tobytes(), np.shape(sol.jac), tuple(meta.load_groups), meta.noise_source, meta.k_free)
        groups.setdefault(key, []).append((s, free, np.asarray(prob.mask, dtype=float)))
    for members in groups.values():
        idx = np.array([s for s, _, _ in members])
        free = members[0][1]
        masks = np.stack([m for _, _, m in members])
        theta, z, jac = (np.stack([np.asarray(getattr(sols[s], f)) for s in idx]) for f in ("theta", "z", "jac"))
        why = _problems(masks > 0, int(free.sum()), z, jac, theta,
                        [extras[s].get("rows") if extras is not None else None for s in idx])
        for s, problem in zip(idx, why):
            out[s] = problem
        ok = np.array([problem is None for problem in why])
        if ok.any():
            _measure([int(s) for s in idx[ok]], free, masks[ok], theta[ok], z[ok], jac[ok][:, :, free], sols, probs, metas, model,
                     hows, thresholds, out, extras)
    return out


def _measure(idx, free, masks, theta, z, j, sols, probs, metas, model, hows, thresholds, out, extras=None):
    """Covariance, conditioning and χ² of a group of alike solutions (see :func:`results_at`), into ``out``:
    solutions ``idx`` with their stacked row weights, estimates, standardized residuals and free Jacobian columns
    ``j[sets, rows + priors, free]``."""
    meta = metas[idx[0]]
    names = free_names(meta, free, model)
    used = masks > 0
    norms = np.linalg.norm(j, axis=1)
    js = j / np.where(norms > 0, norms, 1.0)[:, None, :]
    try:
        _, sv, vt = np.linalg.svd(js, full_matrices=False)
    except np.linalg.LinAlgError:
        if len(idx) > 1:                           # one data set's SVD failed: measure the others without it
            for b, s in enumerate(idx):
                one = slice(b, b + 1)
                _measure([s], free, masks[one], theta[one], z[one], j[one], sols, probs, metas, model, hows,
                         thresholds, out, extras)
            return
        out[idx[0]] = FitError("the fit's Jacobian could not be decomposed (SVD did not converge): the readings "
                               "span values the force law cannot handle; check units and extreme values (ambfit check)")
        return
    with np.errstate(divide="ignore", invalid="ignore"):
        cond = np.where(sv[:, -1] > 0, sv[:, 0] / sv[:, -1], np.inf)
        # (J^T J)^-1 from the SVD of the column-scaled Jacobian: V diag(1/s^2) V^T, unscaled
        cov_s = np.einsum("bki,bk,bkj->bij", vt, 1.0 / sv**2, vt) / (norms[:, :, None] * norms[:, None, :])
    cov_s = np.where((cond < 1e15)[:, None, None], cov_s, np.inf)
    weight = masks**2                              # 1, a robust loss's weight, or 0 for a left-out row
    chi2 = np.sum(np.where(used, weight * z**2, 0.0), axis=1)
    # (a parameter no used reading depends on, an effect's law the data never exercise, is held by its prior alone
    # and takes no degree of freedom)
    seen = np.any((j[:, :masks.shape[1]] != 0) & used[:, :, None], axis=1)
    dof = used.sum(axis=1) - seen.sum(axis=1)
    if meta.noise_estimated:
        cov_s = cov_s * (chi2 / dof)[:, None, None]
    scale, offset = si_scale(probs[idx[0]], model)
    cov = cov_s * np.outer(scale[free], scale[free])
    std = np.sqrt(np.abs(np.diagonal(cov, axis1=1, axis2=2)))
    with np.errstate(invalid="ignore", divide="ignore"):
        corr = cov / (std[:, :, None] * std[:, None, :])
    values = offset[free] + theta[:, free] * scale[free]
    weak = describe_weaknesses(names, corr, vt[:, -1])
    n_rows = masks.shape[1]
    rows_all = np.stack([np.asarray(sols[s].jac_all)[:n_rows] for s in idx])[:, :, free]
    effects, model_name, bearing = model.effects, model.name, model.bearing
    for b, s in enumerate(idx):
        sol = sols[s]
        noise = meta.noise_source
        if meta.noise_estimated:
            noise += f" (current noise estimate {np.sqrt(chi2[b] / dof[b]):.3g} mA)"
        out[s] = FitResult(
            names=list(names), values=values[b], std=std[b], cov=cov[b], corr=corr[b], chi2=float(chi2[b]),
            dof=int(dof[b]), residuals=z[b], edm=float(sol.edm), optimistix=str(sol.result),
            num_steps=int(sol.steps), condition=float(cond[b]), weak_direction=weak[b],
            noise_source=noise, noise_estimated=meta.noise_estimated, start=hows[s], k_free=meta.k_free,
            n_rows=metas[s].n_rows, n_fit_rows=int(used[b].sum()),
            effects=model.build(theta[b, theta.shape[1] - model.n:]) if model.n else effects, model=model_name,
            bearing=bearing, theta=theta[b], thresholds=thresholds,
            jacobian_rows=rows_all[b], row_noise=np.asarray(sol.s)[:n_rows],
            **(extras[s] if extras is not None else {}))
