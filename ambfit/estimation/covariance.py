"""From a solution to a result: covariance, conditioning and χ² of the least-squares estimate.

The covariance is the inverse of the information ``J^T J`` of the standardized residuals (the Cramér-Rao bound of
:mod:`ambfit.estimation.information` at the estimate), scaled by the reduced χ² when the noise levels were
estimated from the residuals.  Conditioning is judged on the column-scaled Jacobian (its SVD), since
Levenberg-Marquardt reports success on problems that do not identify their parameters.
"""

from __future__ import annotations

import numpy as np

from ambfit.estimation.core import FitError, Meta, Model, Problem, free_mask, free_names, si_scale
from ambfit.estimation.lm import Solution
from ambfit.estimation.results import FitResult, Thresholds, describe_weakness


def result_at(sol: Solution, prob: Problem, meta: Meta, model: Model, how: str, thresholds: Thresholds) -> FitResult:
    """The :class:`FitResult` of the solution ``sol`` of ``prob`` (NumPy leaves, ``result`` as text).

    Raises
    ------
    FitError
        Fewer readings than parameters, or a force law that is not finite at the estimate.
    """
    theta, jac, z = np.asarray(sol.theta), np.asarray(sol.jac), np.asarray(sol.z)
    free = free_mask(prob, meta, model)
    names = free_names(meta, free, model)
    mask = np.asarray(prob.mask, dtype=float)
    used = mask > 0
    j = jac[:, free]
    dof = int(used.sum()) - int(free.sum())
    if dof < 1:
        raise FitError(f"the design does not identify the parameters: {int(used.sum())} readings for "
                       f"{int(free.sum())} parameters (no redundancy); add positions, biases or repetitions")
    bad = (~np.isfinite(z[: len(used)]) | ~np.all(np.isfinite(jac[: len(used)]), axis=1)) & used
    if bad.any() or not np.all(np.isfinite(theta)):
        first = f", the first row {int(np.argmax(bad)) + 1}" if bad.any() else ""
        raise FitError(f"the force law gives non-finite values{f' on {int(bad.sum())} row(s)' if bad.any() else ''}"
                       f"{first} at the estimate (a pole gap closed, or currents and positions the law cannot use); "
                       "check those rows' units and values (ambfit check)")
    norms = np.linalg.norm(j, axis=0)
    js = j / np.where(norms > 0, norms, 1.0)
    try:
        _, sv, vt = np.linalg.svd(js, full_matrices=False)
    except np.linalg.LinAlgError:
        raise FitError("the fit's Jacobian could not be decomposed (SVD did not converge): the readings span "
                       "values the force law cannot handle; check units and extreme values (ambfit check)") from None
    cond = float(sv[0] / sv[-1]) if sv[-1] > 0 else np.inf
    scale, offset = si_scale(prob, model)
    weight = mask**2                     # 1, a robust loss's weight, or 0 for a left-out row
    chi2 = float(np.sum(weight[used] * z[used] ** 2))
    if cond < 1e15:
        # (J^T J)^-1 from the SVD of the column-scaled Jacobian: V diag(1/s^2) V^T, unscaled
        cov_s = (vt.T / sv**2) @ vt / np.outer(norms, norms)
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
    n_rows = len(mask)
    return FitResult(
        names=names, values=offset[free] + theta[free] * scale[free], std=std, cov=cov, corr=corr, chi2=chi2,
        dof=dof, residuals=z, edm=float(sol.edm), optimistix=str(sol.result), num_steps=int(sol.steps),
        condition=cond, weak_direction=describe_weakness(names, corr, vt[-1]), noise_source=noise,
        noise_estimated=meta.noise_estimated, start=how, k_free=meta.k_free, n_rows=meta.n_rows,
        n_fit_rows=int(used.sum()), effects=model.build(theta[len(theta) - model.n:]) if model.n else model.effects,
        model=model.name, bearing=model.bearing, theta=theta, thresholds=thresholds,
        jacobian_rows=np.asarray(sol.jac_all)[:n_rows][:, free])
