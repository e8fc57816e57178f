"""Least squares over every reading (work in progress for the least-squares issue).

Effective-variance weighting: each reading's force residual
``r = F(i_top, i_bottom, x; g0, x0, k) - L`` is divided by its propagated noise
``s^2 = (dF/di_top s_i)^2 + (dF/di_bottom s_i)^2 + (dF/dx s_x)^2`` evaluated at the
current parameters (Orear, Am. J. Phys. 50, 912 (1982); Clutton-Brock, Technometrics
9, 261 (1967)).  ``L`` is the known load of the row or, for rows without one, a
nuisance parameter per load group.  Without any known load on an axis ``k`` is not
identifiable (it trades off against the loads): it is held at a reference value and
not reported, and the gap and origin come from the current ratios alone.

Status: core fit and covariance only; the Cramér-Rao bound, batch fits, calibration
studies, CLI and benchmarks are still to come.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
import pandas as pd

from ambfit import closed_form
from ambfit.data import Dataset, load_groups, readings
from ambfit.model import ALPHA_DEFAULT, AXES, gaps, ideal_force

K_REFERENCE = 3.445e-6
"""Force constant [N m^2/A^2] held fixed on an axis without known loads (it cancels from gap and origin)."""

_UM = 1e-6
_KU = 1e-6


class FitError(RuntimeError):
    """The fit did not converge or the design does not identify the parameters; the message says why."""


@dataclasses.dataclass(frozen=True)
class FitResult:
    """Least-squares estimates (SI units) with their covariance and health flags."""

    names: list
    values: np.ndarray
    cov: np.ndarray
    chi2: float
    dof: int
    converged: bool
    message: str
    condition: float
    weak_direction: str
    k_identified: tuple
    residuals: np.ndarray
    n_rows: int

    @property
    def std(self) -> np.ndarray:
        return np.sqrt(np.diag(self.cov))

    @property
    def reduced_chi2(self) -> float:
        return self.chi2 / max(self.dof, 1)

    def value(self, name: str) -> float:
        return float(self.values[self.names.index(name)])

    def error(self, name: str) -> float:
        return float(self.std[self.names.index(name)])


def _problem(df: pd.DataFrame, sigma_i: float | None, sigma_x: float | None):
    r = readings(df)
    ax, x, it, ib = (np.asarray(a) for a in (r.axis, r.x, r.i_top, r.i_bottom))
    def column(name, fill):
        return df[name].to_numpy(float) if name in df else np.full(len(df), fill)
    st = column("i_top_std_A", np.nan) if sigma_i is None else np.full(len(df), sigma_i)
    sb = column("i_bottom_std_A", np.nan) if sigma_i is None else np.full(len(df), sigma_i)
    sx_col = (np.where(ax == 0, column("v_std_um", np.nan), column("w_std_um", np.nan)) * _UM
              if sigma_x is None else np.full(len(df), sigma_x))
    for name, a in (("current", st), ("current", sb), ("position", sx_col)):
        if np.isnan(a).any():
            raise FitError(f"no {name} noise level for some rows: give the std columns or declare a level")
    load = column("load_N", np.nan)
    groups = load_groups(df).to_numpy()
    unknown = sorted({g for g, l in zip(groups, load) if np.isnan(l)})
    gidx = np.array([unknown.index(g) if g in unknown else -1 for g in groups])
    k_known = tuple(bool(np.isfinite(load[ax == a]).any()) for a in range(2))
    return dict(ax=ax, x=x, it=it, ib=ib, st=st, sb=sb, sx=sx_col, load=np.nan_to_num(load), known=np.isfinite(load),
                gidx=gidx, n_unknown=len(unknown), unknown=unknown, k_known=k_known)


def _unpack(theta, prob):
    g0 = theta[0:2] * _UM * 100.0
    x0 = theta[2:4] * _UM
    k = jnp.where(jnp.asarray(prob["k_known"]), theta[4:6] * _KU, K_REFERENCE)
    loads = theta[6:]
    return g0, x0, k, loads


def _residuals(theta, prob, alpha):
    g0, x0, k, loads = _unpack(theta, prob)
    a = prob["ax"]
    c = np.cos(alpha)
    kk = k[a]
    gt, gb = gaps(g0[a], x0[a], prob["x"], alpha)
    it, ib = prob["it"], prob["ib"]
    f = kk * (it**2 / gt**2 - ib**2 / gb**2)
    target = jnp.where(prob["known"], prob["load"],
                       loads[jnp.maximum(prob["gidx"], 0)] if prob["n_unknown"] else 0.0)
    dfi_t = 2 * kk * it / gt**2
    dfi_b = -2 * kk * ib / gb**2
    dfx = 2 * kk * c * (it**2 / gt**3 + ib**2 / gb**3)
    s = jnp.sqrt((dfi_t * prob["st"]) ** 2 + (dfi_b * prob["sb"]) ** 2 + (dfx * prob["sx"]) ** 2)
    return (f - target) / jax.lax.stop_gradient(s)


def fit(data: Dataset | pd.DataFrame, *, sigma_i: float | None = None, sigma_x: float | None = None,
        alpha: float = ALPHA_DEFAULT, max_condition: float = 1e8, max_relative_gap_std: float = 0.1,
        max_steps: int = 256) -> FitResult:
    """Weighted least squares of gap, origin (and k with known loads) over all readings.

    Seeded by the closed form (Eq. 7) where the design allows it, otherwise at the
    nominal gap with zero origin.  Raises :class:`FitError` when the solver does not
    converge or the column-scaled Jacobian is singular to ``max_condition``.
    """
    df = data.frame if isinstance(data, Dataset) else data
    prob = _problem(df, sigma_i, sigma_x)
    try:
        cf = closed_form.identify(df)
        g_seed = [cf.estimates[("all", ax)].g0 if ("all", ax) in cf.estimates else 762e-6 for ax in AXES]
        x_seed = [cf.estimates[("all", ax)].x0 if ("all", ax) in cf.estimates else 0.0 for ax in AXES]
    except closed_form.ClosedFormError:
        g_seed, x_seed = [762e-6, 762e-6], [0.0, 0.0]
    theta0 = np.concatenate([np.asarray(g_seed) / (_UM * 100), np.asarray(x_seed) / _UM,
                             np.full(2, K_REFERENCE / _KU), np.zeros(prob["n_unknown"])])
    # Nuisance loads seeded by the model at the seed parameters (mean force of the group).
    if prob["n_unknown"]:
        f0 = _forces(theta0, prob, alpha)
        for j in range(prob["n_unknown"]):
            theta0[6 + j] = float(np.mean(f0[prob["gidx"] == j]))
    prob_j = {k: (jnp.asarray(v) if isinstance(v, np.ndarray) else v) for k, v in prob.items()}
    fn = lambda th, _: _residuals(th, prob_j, alpha)  # noqa: E731
    solver = optx.LevenbergMarquardt(rtol=1e-12, atol=1e-12)
    sol = optx.least_squares(fn, solver, jnp.asarray(theta0), max_steps=max_steps, throw=False)
    ok = bool(sol.result == optx.RESULTS.successful)
    theta = np.asarray(sol.value)
    jac = np.asarray(jax.jacfwd(fn)(jnp.asarray(theta), None))
    free = np.array([True, True, True, True, *prob["k_known"]] + [True] * prob["n_unknown"])
    present = np.array([(prob["ax"] == 0).any(), (prob["ax"] == 1).any()] * 2 + [True] * (2 + prob["n_unknown"]))
    free &= present
    j = jac[:, free]
    norms = np.linalg.norm(j, axis=0)
    js = j / np.where(norms > 0, norms, 1.0)
    _, sv, vt = np.linalg.svd(js, full_matrices=False)
    cond = float(sv[0] / sv[-1]) if sv[-1] > 0 else np.inf
    names_all = ["g_v0", "g_w0", "v0", "w0", "k_v", "k_w"] + [f"load[{u}]" for u in prob["unknown"]]
    names = [n for n, f in zip(names_all, free) if f]
    weak = vt[-1]
    top = np.argsort(-np.abs(weak))[:2]
    weak_txt = " and ".join(names[t] for t in top)
    r = np.asarray(fn(sol.value, None))
    chi2 = float(np.sum(r**2))
    dof = len(r) - int(free.sum())
    if dof < 1:
        raise FitError(f"the design does not identify the parameters: {len(r)} readings for {int(free.sum())} "
                       "parameters (no redundancy); add positions, biases or repetitions")
    if not cond < max_condition:
        raise FitError(f"the design does not identify the parameters: condition number {cond:.3g} of the scaled "
                       f"Jacobian; weakest direction mixes {weak_txt}")
    cov_s = np.linalg.inv(j.T @ j)
    scale = np.array([_UM * 100] * 2 + [_UM] * 2 + [_KU] * 2 + [1.0] * prob["n_unknown"])[free]
    values = theta[free] * scale
    cov = cov_s * np.outer(scale, scale)
    # The condition number alone misses a valley whose residual is merely small (LM stops on its floor):
    # a gap known to worse than max_relative_gap_std is not identified either.
    for name in ("g_v0", "g_w0"):
        if name in names:
            jn = names.index(name)
            rel = np.sqrt(cov[jn, jn]) / values[jn]
            if not rel < max_relative_gap_std:
                raise FitError(f"the design does not identify the parameters: {name} has a relative standard "
                               f"error of {rel:.2g}; weakest direction mixes {weak_txt} (use two or more "
                               "positions, as in the paper's symmetric pairs)")
    # Identifiability is checked first: an unidentifiable valley is the usual reason LM runs out of steps.
    if not ok:
        raise FitError(f"least squares did not converge within {max_steps} steps ({sol.result}); "
                       "check the data for outliers or give a better start")

    return FitResult(names=names, values=values, cov=cov, chi2=chi2, dof=dof, converged=ok,
                     message="successful", condition=cond, weak_direction=weak_txt, k_identified=prob["k_known"],
                     residuals=r, n_rows=len(df))


def _forces(theta, prob, alpha):
    g0, x0, k, _ = _unpack(jnp.asarray(theta), prob)
    a = prob["ax"]
    return np.asarray(ideal_force(g0[a], x0[a], k[a], prob["it"], prob["ib"], prob["x"], alpha))
