"""Least squares over every reading: gap, origin and (with known loads) the force constant.

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
Cramér-Rao bound of :mod:`ambfit.information`.  We prefer it to *output error*
(predict the control current and compare) because it treats both coils and the
position sensor symmetrically and needs no root solve per reading; unbiasedness
and unit-variance pulls are checked on rig data in the tests and in
``benchmarks/ls_efficiency.py``.  ``s_eff`` is held fixed while Levenberg-Marquardt
runs and re-evaluated at its estimate (``REWEIGHTINGS`` rounds: iteratively
reweighted least squares), the usual choice that keeps the estimator consistent.

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

import equinox as eqx
import jax.numpy as jnp
import numpy as np
import optimistix as optx
import pandas as pd

from ambfit import closed_form
from ambfit.data import Dataset
from ambfit.likelihood import (  # noqa: F401  (re-exported: the fit's public vocabulary)
    EDM_MAX, FIRST_STEPS, HEAD_NAMES, K_REFERENCE, NOMINAL_GAP, REWEIGHTINGS, SCALE_HEAD, SCALE_LOAD, FitError, Meta,
    Problem, build_problem, free_mask, free_names, jacobian, param_scale, residuals, seed_loads_and_k, solve,
    to_theta, unpack,
)
from ambfit.model import ALPHA_DEFAULT, AXES


def start(prob: Problem, meta: Meta, data: pd.DataFrame, alpha: float = ALPHA_DEFAULT) -> tuple[np.ndarray, str]:
    """Starting point: the closed form (Eq. 7) where the design has two biases at two positions,
    else a coarse grid over gap and origin; nuisance loads from the model there.  Never the truth."""
    g, x, how = [NOMINAL_GAP, NOMINAL_GAP], [0.0, 0.0], []
    for a, ax in enumerate(AXES):
        if not meta.axes_present[a]:
            continue
        try:
            est = closed_form.identify(data[data["axis"] == ax]).estimates[("all", ax)]
            if np.isfinite(est.g0) and est.g0 > 0:
                g[a], x[a] = est.g0, est.x0
                how.append(f"{ax}: closed form")
                continue
        except closed_form.ClosedFormError:
            pass
        g[a], x[a] = _grid_start(prob, meta, a, alpha)
        how.append(f"{ax}: grid")
    theta = to_theta(g, x, K_REFERENCE, np.zeros(prob.n_loads))
    theta = seed_loads_and_k(theta, prob, alpha)
    return theta, ", ".join(how)


_residuals_jit = eqx.filter_jit(residuals)


def _grid_start(prob: Problem, meta: Meta, axis: int, alpha) -> tuple[float, float]:
    """Best (gap, origin) of a coarse grid (gap 0.5-1.5 x nominal, origin ±0.3 x nominal), loads profiled."""
    gs = np.linspace(0.5, 1.5, 41) * NOMINAL_GAP
    xs = np.linspace(-0.3, 0.3, 61) * NOMINAL_GAP
    sel = np.asarray(prob.ax) == axis
    best, arg = np.inf, (NOMINAL_GAP, 0.0)
    it, ib, x = (np.asarray(v)[sel] for v in (prob.i_top, prob.i_bottom, prob.x))
    gid = np.where(np.asarray(prob.known)[sel], -1, np.asarray(prob.gidx)[sel])
    load = np.asarray(prob.load)[sel]
    for g in gs:
        u = (xs[:, None] + x[None, :]) * np.cos(alpha)
        ok = np.all(np.abs(u) < 0.95 * g, axis=1)
        unit = it**2 / (g - u) ** 2 - ib**2 / (g + u) ** 2   # [origin, row]
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


@dataclasses.dataclass(frozen=True)
class FitResult:
    """Least-squares estimates with uncertainties and fit health (SI units).

    Attributes
    ----------
    names : list[str]
        Estimated parameters: ``g_v0``, ``g_w0``, ``v0``, ``w0``, ``k_v``/``k_w`` where
        known loads make them identifiable, then ``load[<group>]`` nuisances [N].
    values, std : array[p]
    cov, corr : array[p, p]
    chi2, dof, reduced_chi2 :
        Sum of squared standardized residuals; ``reduced_chi2 ≈ 1`` when the
        model and the noise levels are right.
    residuals : array[n]
        Standardized residuals of the rows, in file order.
    converged : bool
        The estimated distance to the minimum is below ``EDM_MAX``; ``message`` gives it and
        optimistix's own result.
    condition : float
        Condition number of the column-scaled Jacobian.
    weak_direction : str
        The least determined combination, in words.
    noise_source : str
        Where the noise levels came from; when estimated, ``cov`` is scaled by
        the reduced χ².
    start : str
        How the starting point was found.
    """

    names: list
    values: np.ndarray
    std: np.ndarray
    cov: np.ndarray
    corr: np.ndarray
    chi2: float
    dof: int
    residuals: np.ndarray
    converged: bool
    message: str
    num_steps: int
    condition: float
    weak_direction: str
    noise_source: str
    start: str
    k_identified: tuple
    n_rows: int
    bias_correction: dict | None = None

    @property
    def reduced_chi2(self) -> float:
        return self.chi2 / max(self.dof, 1)

    def value(self, name: str) -> float:
        return float(self.values[self.names.index(name)])

    def error(self, name: str) -> float:
        return float(self.std[self.names.index(name)])

    def params(self) -> dict:
        """Contract section 2 parameter block (µm, N m²/A²)."""
        out = {}
        for name, key, scale in (("g_v0", "g_v0_um", 1e6), ("v0", "v0_um", 1e6), ("g_w0", "g_w0_um", 1e6),
                                 ("w0", "w0_um", 1e6), ("k_v", "k_v_Nm2_per_A2", 1.0),
                                 ("k_w", "k_w_Nm2_per_A2", 1.0)):
            if name in self.names:
                out[key] = {"value": self.value(name) * scale, "std": self.error(name) * scale}
        return out

    def to_json(self) -> dict:
        """The contract record (plus fit health)."""
        head = [n for n in self.names if not n.startswith("load[")]
        return {
            "method": "least_squares", "params": self.params(), "converged": self.converged, "n_rows": self.n_rows,
            "reduced_chi2": self.reduced_chi2, "dof": self.dof, "condition": self.condition,
            "weak_direction": self.weak_direction, "noise_source": self.noise_source, "start": self.start,
            "k_identified": {"v": self.k_identified[0], "w": self.k_identified[1]},
            "correlations": {f"{a}|{b}": float(self.corr[self.names.index(a), self.names.index(b)])
                             for i, a in enumerate(head) for b in head[i + 1:]},
            "nuisance_loads_N": {n[5:-1]: {"value": self.value(n), "std": self.error(n)}
                                 for n in self.names if n.startswith("load[")},
            "bias_correction": self.bias_correction,
        }


def describe_weakness(names: Sequence[str], corr: np.ndarray, vt_last: np.ndarray) -> str:
    """The least-determined direction in words: the most correlated pair and the weakest singular vector."""
    p = len(names)
    text = []
    if p > 1:
        c = np.abs(np.asarray(corr)) - np.eye(p)
        i, j = np.unravel_index(np.argmax(c), c.shape)
        text.append(f"{names[i]} and {names[j]} are {100 * abs(corr[i, j]):.1f} % "
                    f"{'anti-' if corr[i, j] < 0 else ''}correlated")
    top = np.argsort(-np.abs(vt_last))[:2]
    text.append("weakest direction mostly " + " and ".join(names[t] for t in top))
    return "; ".join(text)


def fit(data: Dataset | pd.DataFrame, *, sigma_i: float | None = None, sigma_x: float | None = None,
        alpha: float = ALPHA_DEFAULT, require_k: bool = False, max_condition: float = 1e8,
        max_relative_gap_std: float = 0.1, max_steps: int = 200, debias: int = 0, seed: int = 0) -> FitResult:
    """Weighted least squares of gap, origin (and k with known loads) over all readings.

    Parameters
    ----------
    data : Dataset or DataFrame
        Contract table (any positions, biases, iterations, both axes).
    sigma_i, sigma_x : float, optional
        Declared current [A] and position [m] noise std, overriding the std columns.
    require_k : bool
        Raise if ``k`` cannot be identified on a present axis (no known load).
    max_condition : float
        Largest acceptable condition number of the column-scaled Jacobian.
    max_relative_gap_std : float
        A gap known to worse than this relative std counts as not identified.
    max_steps : int
        Levenberg-Marquardt step budget per reweighting round.  A first solve takes at
        most ``FIRST_STEPS`` per round; if it has not converged, a second one gets ``max_steps``.
    debias : int
        Number of synthetic data sets for the parametric-bootstrap bias correction
        (:mod:`ambfit.debias`); 0 (default) reports the plain least-squares estimate.
    seed : int
        Seed of the bootstrap.

    Raises
    ------
    FitError
        Not identifiable (checked first: an unidentifiable valley is what makes LM
        run out of steps) or not converged; the message says why and what to do.

    Examples
    --------
    >>> from ambfit import rig, protocol
    >>> sim = rig.simulate(rig.PAPER_RIG, protocol.paper_table2(center=(-33.3e-6, 11.3e-6)), seed=1)
    >>> res = fit(sim.data)
    >>> abs(res.value("g_v0") - 775e-6) < 4 * res.error("g_v0")
    True
    """
    df = data.frame if isinstance(data, Dataset) else data
    prob, meta = build_problem(df, sigma_i=sigma_i, sigma_x=sigma_x)
    if require_k:
        missing = [ax for a, ax in enumerate(AXES) if meta.axes_present[a] and not meta.k_free[a]]
        if missing:
            raise FitError(f"k is not identifiable on axis {', '.join(missing)}: no row of that axis has a known "
                           "load (load_N). Hang known masses (or give the rotor weight share) to calibrate it; "
                           "the gap and origin do not need it")
    theta0, how = start(prob, meta, df, alpha)
    theta, result, steps, edm = solve(jnp.asarray(theta0), prob, alpha, max_steps=min(FIRST_STEPS, max_steps))
    if not edm < EDM_MAX and max_steps > FIRST_STEPS:  # a far start: give Levenberg-Marquardt room
        theta, result, more, edm = solve(theta, prob, alpha, max_steps=max_steps)
        steps = steps + more
    ok = bool(edm < EDM_MAX)
    lm = "successful" if result == optx.RESULTS.successful else str(result)
    theta = np.asarray(theta)
    correction = None
    if debias and ok:
        from ambfit.debias import bootstrap_bias

        correction = bootstrap_bias(theta, prob, prob.bias, n=debias, seed=seed, alpha=alpha)
        theta = theta - correction.bias
    res = _finish(theta, ok, f"EDM {float(edm):.2g} (limit {EDM_MAX:g}); optimistix: {lm}", int(steps),
                  prob, meta, alpha, how, max_condition, max_relative_gap_std, max_steps)
    if correction is not None:
        free = free_mask(prob, meta)
        scale = param_scale(prob.n_loads)[free]
        res = dataclasses.replace(res, bias_correction={
            "n": correction.n, "converged_fraction": correction.converged_fraction,
            **{n: {"subtracted": float(b), "mc_error": float(e)}
               for n, b, e in zip(res.names, correction.bias[free] * scale, correction.mc_error[free] * scale)}})
    return res


def _finish(theta, ok, message, steps, prob, meta, alpha, how, max_condition, max_relative_gap_std, max_steps):
    free = free_mask(prob, meta)
    names = free_names(meta, free)
    r = np.asarray(_residuals_jit(jnp.asarray(theta), prob, alpha))
    j = np.asarray(jacobian(jnp.asarray(theta), prob, alpha))[:, free]
    dof = len(r) - int(free.sum())
    if dof < 1:
        raise FitError(f"the design does not identify the parameters: {len(r)} readings for {int(free.sum())} "
                       "parameters (no redundancy); add positions, biases or repetitions")
    norms = np.linalg.norm(j, axis=0)
    js = j / np.where(norms > 0, norms, 1.0)
    _, sv, vt = np.linalg.svd(js, full_matrices=False)
    cond = float(sv[0] / sv[-1]) if sv[-1] > 0 else np.inf
    scale = param_scale(prob.n_loads)[free]
    chi2 = float(r @ r)
    if cond < 1e15:
        cov_s = np.linalg.pinv(js.T @ js) / np.outer(norms, norms)
    else:
        cov_s = np.full((len(names), len(names)), np.inf)
    estimated = "estimated" in meta.noise_source
    if estimated:
        cov_s = cov_s * chi2 / dof
    cov = cov_s * np.outer(scale, scale)
    std = np.sqrt(np.abs(np.diag(cov)))
    with np.errstate(invalid="ignore", divide="ignore"):
        corr = cov / np.outer(std, std)
    weak = describe_weakness(names, corr, vt[-1])
    if not cond < max_condition:
        raise FitError(f"the design does not identify the parameters: condition number {cond:.3g} of the scaled "
                       f"Jacobian; {weak}")
    values = theta[free] * scale
    for name in ("g_v0", "g_w0"):
        if name in names:
            rel = std[names.index(name)] / values[names.index(name)]
            if not rel < max_relative_gap_std:
                raise FitError(f"the design does not identify the parameters: {name} has a relative standard "
                               f"error of {rel:.2g}; {weak}. Use two or more positions (the paper's symmetric "
                               "pairs) and two or more biases")
    if not ok:
        raise FitError(f"least squares did not converge within {max_steps} steps ({message}); check the data for "
                       "outliers or a wrong unit, or give a better start")

    noise = meta.noise_source + (f" (current noise estimate {np.sqrt(chi2 / dof):.3g} mA)" if estimated else "")
    return FitResult(names=names, values=values, std=std, cov=cov, corr=corr, chi2=chi2, dof=dof, residuals=r,
                     converged=ok, message=message, num_steps=steps, condition=cond, weak_direction=weak,
                     noise_source=noise, start=how, k_identified=meta.k_free, n_rows=meta.n_rows)


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
