"""The least-squares likelihood: data arrays, scaled parameters, residuals, solver core.

See :mod:`ambfit.fit` for the model of the noise (effective variance) and how the
pieces are used; this module holds the jit- and vmap-safe core that
:mod:`ambfit.fit`, :mod:`ambfit.batch`, :mod:`ambfit.information` and
:mod:`ambfit.debias` share.
"""

from __future__ import annotations

import dataclasses

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
import pandas as pd

from ambfit.data import Dataset, load_groups, readings
from ambfit.model import ALPHA_DEFAULT, gaps, ideal_force

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


def misfit(theta, prob: Problem, alpha):
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
    f, s = misfit(theta, prob, alpha)
    return f / jax.lax.stop_gradient(s)


def _fn(theta, args):
    prob, alpha = args
    return residuals(theta, prob, alpha)


def _fn_weighted(theta, args):
    prob, alpha, s = args
    return misfit(theta, prob, alpha)[0] / s


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
        s = misfit(theta, prob, alpha)[1]
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


def free_names(meta: Meta, free: np.ndarray) -> list[str]:
    """Names of the estimated entries of theta (``free_mask``): head parameters, then ``load[<group>]``."""
    return [n for n, f in zip(list(HEAD_NAMES) + [f"load[{g}]" for g in meta.load_groups], free) if f]


def free_mask(prob: Problem, meta: Meta) -> np.ndarray:
    """Which entries of theta are estimated: gap/origin of present axes, k where loads are known, loads."""
    p = meta.axes_present
    return np.array([p[0], p[1], p[0], p[1], meta.k_free[0] and p[0], meta.k_free[1] and p[1]]
                    + [True] * prob.n_loads)


@eqx.filter_jit
def _unit_force(theta, prob: Problem, alpha):
    """Eq. 4 with k = 1 at each row (one compiled call instead of many small eager ones)."""
    g0, x0, _, _ = unpack(theta, prob)
    return ideal_force(g0[prob.ax], x0[prob.ax], 1.0, prob.i_top, prob.i_bottom, prob.x, alpha)


def seed_loads_and_k(theta, prob: Problem, alpha=ALPHA_DEFAULT):
    """``theta`` with k (from the known loads) and the nuisance loads set to their best values at its gap and origin."""
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
