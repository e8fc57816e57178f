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
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
import pandas as pd

from ambfit import closed_form
from ambfit.data import Dataset, load_groups, readings
from ambfit.model import ALPHA_DEFAULT, AXES, gaps, ideal_force

K_REFERENCE = 3.445e-6
"""Force constant [N m^2/A^2] held on an axis without known loads (it cancels from gap and origin)."""

NOMINAL_GAP = 762e-6
"""Centre of the robust start's gap grid [m] (the paper's nominal gap)."""

# theta = (g_v0, g_w0) / 1 cm, (v0, w0) / 0.1 mm, (k_v, k_w) / 1e-4, loads / 100 N.  The units are coarse
# on purpose: every column of the standardized Jacobian is then >= ~1e3, so Levenberg-Marquardt's
# initial damping (lambda = 1) is negligible and it takes Gauss-Newton steps from a good seed, while
# keeping its trust region for a poor one.  (With units near the parameters' size the weakest
# eigenvalue of J^T J was ~10, and lambda = 1 cost ~8 extra steps per solve.)
SCALE_HEAD = np.array([1e-2, 1e-2, 1e-4, 1e-4, 1e-4, 1e-4])
SCALE_LOAD = 100.0


def param_scale(n_loads: int) -> np.ndarray:
    """SI value of one unit of each entry of theta."""
    return np.concatenate([SCALE_HEAD, np.full(n_loads, SCALE_LOAD)])


def to_theta(g0, x0, k, loads=()) -> np.ndarray:
    """The scaled parameter vector from SI values (pairs ``(v, w)`` and nuisance loads [N])."""
    si = np.concatenate([np.broadcast_to(g0, (2,)), np.broadcast_to(x0, (2,)), np.broadcast_to(k, (2,)),
                         np.asarray(loads, dtype=float)])
    return si / param_scale(len(loads))
HEAD_NAMES = ("g_v0", "g_w0", "v0", "w0", "k_v", "k_w")
UNITS = {"g_v0": "m", "g_w0": "m", "v0": "m", "w0": "m", "k_v": "N m^2/A^2", "k_w": "N m^2/A^2"}


class FitError(RuntimeError):
    """The fit did not converge or the design does not identify the parameters; the message says why."""


class Problem(eqx.Module):
    """Arrays of one data set, ready for the jitted residual (SI units, one entry per row).

    ``k_free[a]`` is whether axis ``a`` has a known load (so ``k`` is identifiable);
    ``gidx`` indexes the nuisance load of rows without a known load (-1 otherwise);
    ``bias`` is the commanded bias current [A] (used only to simulate the model).
    """

    ax: jnp.ndarray
    x: jnp.ndarray
    i_top: jnp.ndarray
    i_bottom: jnp.ndarray
    s_top: jnp.ndarray
    s_bottom: jnp.ndarray
    s_x: jnp.ndarray
    load: jnp.ndarray
    known: jnp.ndarray
    gidx: jnp.ndarray
    k_free: jnp.ndarray
    bias: jnp.ndarray

    @property
    def n_params(self) -> int:
        return 6 + self.n_loads

    @property
    def n_loads(self) -> int:
        return int(np.max(np.asarray(self.gidx), initial=-1)) + 1


@dataclasses.dataclass(frozen=True)
class Meta:
    """What :func:`build_problem` decided about a data set."""

    load_groups: list
    k_free: tuple
    axes_present: tuple
    noise_source: str
    n_rows: int


def build_problem(data: Dataset | pd.DataFrame, *, sigma_i: float | None = None,
                  sigma_x: float | None = None) -> tuple[Problem, Meta]:
    """Arrays for :func:`residuals` from a contract table.

    ``sigma_i`` [A] and ``sigma_x`` [m] override the std columns; with neither
    columns nor declared levels the noise is marked for estimation (unit current
    weight of 1 mA, no position noise, rescaled by the fit's reduced χ²).
    """
    df = data.frame if isinstance(data, Dataset) else data
    r = readings(df)
    ax = np.asarray(r.axis)
    n = len(df)

    def column(name):
        return df[name].to_numpy(float) if name in df else np.full(n, np.nan)

    st, sb = column("i_top_std_A"), column("i_bottom_std_A")
    sx = np.where(ax == 0, column("v_std_um"), column("w_std_um")) * 1e-6
    sources = []
    if sigma_i is not None:
        st, sb = np.full(n, float(sigma_i)), np.full(n, float(sigma_i))
        sources.append(f"current {sigma_i * 1e3:g} mA declared")
    elif np.isnan(st).any() or np.isnan(sb).any():
        st, sb = np.full(n, 1e-3), np.full(n, 1e-3)
        sources.append("current estimated from the residuals")
    else:
        sources.append("current from the std columns")
    if sigma_x is not None:
        sx = np.full(n, float(sigma_x))
        sources.append(f"position {sigma_x * 1e6:g} µm declared")
    elif np.isnan(sx).any():
        sx = np.zeros(n)
        sources.append("position noise taken as 0 (no std column)")
    else:
        sources.append("position from the std columns")
    load = column("load_N")
    groups = load_groups(df).to_numpy()
    unknown = list(dict.fromkeys(g for g, l in zip(groups, load) if np.isnan(l)))
    gidx = np.array([unknown.index(g) if g in unknown else -1 for g in groups], dtype=int)
    known = np.isfinite(load)
    k_free = tuple(bool(known[ax == a].any()) for a in range(2))
    present = tuple(bool((ax == a).any()) for a in range(2))
    prob = Problem(
        ax=jnp.asarray(ax), x=r.x, i_top=r.i_top, i_bottom=r.i_bottom, s_top=jnp.asarray(st),
        s_bottom=jnp.asarray(sb), s_x=jnp.asarray(sx), load=jnp.asarray(np.nan_to_num(load)),
        known=jnp.asarray(known), gidx=jnp.asarray(gidx), k_free=jnp.asarray(k_free), bias=r.bias,
    )
    return prob, Meta(load_groups=unknown, k_free=k_free, axes_present=present, noise_source="; ".join(sources),
                      n_rows=n)


def unpack(theta, prob: Problem):
    """``(g0[2], x0[2], k[2], loads[m])`` in SI units from the scaled parameter vector."""
    g0 = theta[0:2] * SCALE_HEAD[0]
    x0 = theta[2:4] * SCALE_HEAD[2]
    k = jnp.where(prob.k_free, theta[4:6] * SCALE_HEAD[4], K_REFERENCE)
    return g0, x0, k, theta[6:] * SCALE_LOAD


def _misfit(theta, prob: Problem, alpha):
    """Force misfit ``F - L`` [N] of every row and its effective noise std ``s_eff`` [N]."""
    g0, x0, k, loads = unpack(theta, prob)
    a = prob.ax
    kk = k[a]
    gt, gb = gaps(g0[a], x0[a], prob.x, alpha)
    it, ib = prob.i_top, prob.i_bottom
    f = kk * (it**2 / gt**2 - ib**2 / gb**2)
    nuisance = loads[jnp.maximum(prob.gidx, 0)] if loads.shape[0] else jnp.zeros_like(f)
    target = jnp.where(prob.known, prob.load, nuisance)
    c = jnp.cos(alpha)
    s = jnp.sqrt((2 * kk * it / gt**2 * prob.s_top) ** 2 + (2 * kk * ib / gb**2 * prob.s_bottom) ** 2
                 + (2 * kk * c * (it**2 / gt**3 + ib**2 / gb**3) * prob.s_x) ** 2)
    return f - target, s


def residuals(theta, prob: Problem, alpha: float = ALPHA_DEFAULT):
    """Effective-variance residuals ``(F - L) / s_eff`` of every row (dimensionless)."""
    f, s = _misfit(theta, prob, alpha)
    return f / jax.lax.stop_gradient(s)


def _fn(theta, args):
    prob, alpha = args
    return residuals(theta, prob, alpha)


def _fn_weighted(theta, args):
    prob, alpha, s = args
    return _misfit(theta, prob, alpha)[0] / s


REWEIGHTINGS = 2
"""Rounds of solving with the effective-variance weights held fixed, then re-evaluated at the estimate.

Holding the weights fixed within a round gives Levenberg-Marquardt a consistent
objective (its trust-region ratio test otherwise rejects steps when the weights
move); a second round at the first round's estimate reproduces the fully
reweighted solution to 9 digits on the rig designs (a third changes nothing)."""

EDM_MAX = 1e-6
"""Convergence: the estimated distance to the minimum, ``EDM = r^T J (J^T J)^-1 J^T r`` (the χ² a
full Gauss-Newton step would still gain), must fall below this, i.e. every parameter is within
about 1e-3 standard errors of the optimum (iminuit's criterion).  Optimistix's own test is
reported too, but near the optimum its trust region rejects steps on round-off and it can
stop late or never while the solution is already exact."""


FIRST_STEPS = 3
"""Levenberg-Marquardt steps per round of the first solve: enough for every one of 60 rig data sets
(three designs, random gaps and origins, closed-form or grid starts) to reach ``EDM_MAX``; 2 left
23 of them short.  Near the optimum further steps are mostly rejected on round-off, so a
small fixed budget plus the EDM check is both faster and safer than waiting for
optimistix's own termination."""


def _edm(theta, prob, alpha):
    j = jax.jacfwd(_fn)(theta, (prob, alpha))
    g = j.T @ _fn(theta, (prob, alpha))
    h = j.T @ j
    # Held parameters (k without a known load) have zero columns: unit diagonal, zero gradient.
    h = h + jnp.diag(jnp.where(jnp.diag(h) == 0, 1.0, 0.0))
    # g^T (J^T J)^-1 g; a singular J^T J otherwise gives inf/nan, i.e. "not converged", and the
    # identifiability checks then say why.
    return g @ jnp.linalg.solve(h, g)


@eqx.filter_jit
def solve(theta0, prob: Problem, alpha: float = ALPHA_DEFAULT, max_steps: int = 3, rtol: float = 1e-8,
          atol: float = 1e-8):
    """Levenberg-Marquardt from ``theta0``; returns ``(theta, result, num_steps, edm)`` (jit- and vmap-safe).

    ``num_steps`` counts the steps of all reweighting rounds; ``result`` is the last round's
    optimistix result; ``edm`` decides convergence (see ``EDM_MAX``).
    """
    def round_(_, carry):
        theta, steps, _ = carry
        s = _misfit(theta, prob, alpha)[1]
        sol = optx.least_squares(_fn_weighted, optx.LevenbergMarquardt(rtol=rtol, atol=atol), theta,
                                 args=(prob, alpha, s), max_steps=max_steps, throw=False)
        return sol.value, steps + sol.stats["num_steps"], sol.result

    # A loop rather than unrolled rounds: the solver is traced and compiled once (cold start).
    theta, steps, result = jax.lax.fori_loop(
        0, REWEIGHTINGS, round_, (theta0, jnp.asarray(0), optx.RESULTS.successful))
    return theta, result, steps, _edm(theta, prob, alpha)


@eqx.filter_jit
def jacobian(theta, prob: Problem, alpha: float = ALPHA_DEFAULT):
    """Jacobian ``d r / d theta`` of the residuals [rows, params] (scaled parameters)."""
    return jax.jacfwd(_fn)(theta, (prob, alpha))


def free_mask(prob: Problem, meta: Meta) -> np.ndarray:
    """Which entries of theta are estimated: gap/origin of present axes, k where loads are known, loads."""
    p = meta.axes_present
    return np.array([p[0], p[1], p[0], p[1], meta.k_free[0] and p[0], meta.k_free[1] and p[1]]
                    + [True] * prob.n_loads)


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
    theta = _seed_loads_and_k(theta, prob, alpha)
    return theta, ", ".join(how)


@eqx.filter_jit
def _unit_force(theta, prob: Problem, alpha):
    """Eq. 4 with k = 1 at each row (one compiled call instead of many small eager ones)."""
    g0, x0, _, _ = unpack(theta, prob)
    return ideal_force(g0[prob.ax], x0[prob.ax], 1.0, prob.i_top, prob.i_bottom, prob.x, alpha)


_residuals_jit = eqx.filter_jit(residuals)


def _seed_loads_and_k(theta, prob: Problem, alpha):
    a = np.asarray(prob.ax)
    unit = np.asarray(_unit_force(jnp.asarray(theta), prob, alpha))
    known, load, gidx = np.asarray(prob.known), np.asarray(prob.load), np.asarray(prob.gidx)
    theta = np.array(theta)
    for ax in range(2):
        sel = known & (a == ax)
        if sel.any() and np.sum(unit[sel] ** 2) > 0:
            theta[4 + ax] = np.sum(load[sel] * unit[sel]) / np.sum(unit[sel] ** 2) / SCALE_HEAD[4]
    k_used = np.where(np.asarray(prob.k_free), theta[4:6] * SCALE_HEAD[4], K_REFERENCE)
    for j in range(prob.n_loads):
        sel = gidx == j
        theta[6 + j] = float(np.mean(k_used[a[sel]] * unit[sel])) / SCALE_LOAD
    return theta


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
    names = [n for n, f in zip(list(HEAD_NAMES) + [f"load[{g}]" for g in meta.load_groups], free) if f]
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
