"""Bias corrections of the least-squares estimates: second order by the delta method (the default), or by a
parametric bootstrap.

Currents enter the force law squared and every reading is noisy, so the estimator of :mod:`ambfit.estimation.fit`
has a bias of second order in the noise (an errors-in-variables effect: a row's Jacobian and weight correlate with
its own noise).  On the paper's Table 2 design at 0.6 mA it is about +0.1 standard deviations on the origins and
-0.04 on k, and it grows with the square of the noise: enough to put a study of a few hundred data sets several
standard errors off.

Second order (:func:`second_order_bias`)
----------------------------------------
The estimate solves ``psi(theta, m) = sum_j w_j (F_j - L_j) dF_j/dtheta = 0`` (weights ``w = 1 / s_eff^2`` held, the
effect priors added) for the readings ``m``.  Expanding the implicit function ``theta(m)`` to second order about
the true readings, with independent noise of variance ``sigma_k^2`` on each reading ``k``,

    E[theta] - theta = -1/2 A^-1 sum_k sigma_k^2 (psi_mm,kk + 2 psi_theta,m_k v_k + psi_theta,theta[v_k, v_k]),
    A = d psi / d theta,   v_k = -A^-1 psi_m_k,

the same expansion as Cox and Snell's (J. R. Stat. Soc. B 30, 248, 1968) for an estimating equation, here in the
readings instead of the responses (Amemiya and Fuller, Ann. Stat. 16, 147, 1988, for errors in variables).
Every term is an exact derivative (forward mode through :func:`ambfit.estimation.core.measured`); evaluated at the
estimate and the measured readings instead of the unknown truth it leaves an error of third order.  It costs
about one more evaluation of the Jacobian's derivatives, less than the solve.  The force of a row depends only
on that row's readings, so one tangent per kind of reading (top current, bottom current, position) gives every
row's derivative at once.

Bootstrap (:func:`bootstrap_bias`)
----------------------------------
Simulates the *model* (not the rig) at the estimate: for each row the control current that balances its load
(known or fitted) at its bias and measured position, plus fresh noise of the declared levels; every synthetic set
is refitted (one vmapped solve) and the mean shift is subtracted.  With ``n`` synthetic sets the correction
carries a Monte Carlo error of ``std / sqrt(n)``, reported alongside.  A check of the second-order term, not a
default: it costs ``n`` fits.
"""

from __future__ import annotations

import dataclasses

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ambfit.estimation.core import (
    IDEAL,
    Meta,
    Model,
    Problem,
    free_mask,
    jacobian,
    measured,
    si_scale,
    standardized,
    target,
    unpack,
)
from ambfit.estimation.covariance import result_at
from ambfit.estimation.lm import Solution, solve
from ambfit.estimation.results import FitResult, Thresholds
from ambfit.physics.model import pole_gaps


def model_currents(theta, prob: Problem, bias, model: Model = IDEAL):
    """Noise-free ``(i_top, i_bottom)`` [A] that carry each row's load at its bias and position under ``theta``.

    Solves ``k ((b + c)^2 / g_t^2 - (b - c)^2 / g_b^2) = L`` for the control current ``c``
    (the root continuous with ``c = 0`` at zero load).
    """
    p = unpack(theta, prob, model)
    a = prob.ax
    gt, gb = pole_gaps(p.params.g0[a], p.params.x0[a], prob.x, model.bearing.cos_alpha)
    load = target(prob, p.loads) / p.params.k[a]
    p, q = 1.0 / gt**2, 1.0 / gb**2
    qa = p - q
    qb = 2.0 * bias * (p + q)
    qc = bias**2 * (p - q) - load
    disc = jnp.sqrt(qb**2 - 4.0 * qa * qc)
    c = -2.0 * qc / (qb + disc)   # the stable form of the root near c = -qc / qb
    return bias + c, bias - c


@dataclasses.dataclass(frozen=True)
class Correction:
    """Bias of the scaled parameter vector estimated by the bootstrap, with its Monte Carlo error."""

    bias: np.ndarray
    mc_error: np.ndarray
    n: int
    converged_fraction: float


@eqx.filter_jit
def _bootstrap(theta, prob: Problem, bias, key, n: int, model: Model):
    it0, ib0 = model_currents(theta, prob, bias, model)

    def one(key):
        k1, k2, k3 = jax.random.split(key, 3)
        shape = prob.x.shape
        synth = prob.with_readings(it0 + prob.s_top * jax.random.normal(k1, shape),
                                   ib0 + prob.s_bottom * jax.random.normal(k2, shape),
                                   prob.x + prob.s_x * jax.random.normal(k3, shape))
        sol = solve(theta, synth, model)
        return sol.theta, sol.edm

    return jax.vmap(one)(jax.random.split(key, n))


def bootstrap_bias(theta, prob: Problem, bias, *, n: int = 2000, seed: int = 0, model: Model = IDEAL,
                   edm_max: float = 1e-6) -> Correction:
    """Estimated bias of the estimator at ``theta`` (scaled parameters), from ``n`` synthetic data sets."""
    values, edm = _bootstrap(jnp.asarray(theta), prob, jnp.asarray(bias, dtype=float), jax.random.PRNGKey(seed), n,
                             model)
    values, ok = np.asarray(values), np.asarray(edm) < edm_max
    v = values[ok]
    return Correction(bias=v.mean(axis=0) - np.asarray(theta), mc_error=v.std(axis=0, ddof=1) / np.sqrt(len(v)),
                      n=int(ok.sum()), converged_fraction=float(ok.mean()))


def debiased(res: FitResult, prob: Problem, meta: Meta, model: Model, thresholds: Thresholds, n: int,
             seed: int) -> FitResult:
    """``res`` less its parametric-bootstrap bias (:func:`bootstrap_bias` from ``n`` synthetic data sets), with its
    covariance, conditioning and χ² measured again at the corrected estimate."""
    correction = bootstrap_bias(res.theta, prob, prob.bias, n=n, seed=seed, model=model)
    theta = res.theta - correction.bias
    t = jnp.asarray(theta)
    sol = Solution(theta=theta, result=res.optimistix, steps=res.num_steps, edm=res.edm,
                   jac=np.asarray(jacobian(t, prob, model)), z=np.asarray(standardized(t, prob, model)),
                   jac_all=np.asarray(jacobian(t, prob.with_mask(np.ones(len(prob.mask))), model)))
    res = result_at(sol, prob, meta, model, res.start, thresholds)
    free = free_mask(prob, meta)
    scale = si_scale(prob)[0][free]
    return dataclasses.replace(res, bias_correction={
        "method": "bootstrap", "n": correction.n, "converged_fraction": correction.converged_fraction,
        **{n: {"subtracted": float(b), "mc_error": float(e)}
           for n, b, e in zip(res.names, correction.bias[free] * scale, correction.mc_error[free] * scale)}})



# --- second order ------------------------------------------------------------------------------------------

THETA_STEP = 0.01
"""Differences along theta step this fraction of a standard error (along each square root of the covariance):
steps of one standard error put the derivatives of the estimating equation up to 6 % off (forward differences,
against nested forward derivatives on Table 2 at 1.8 mA); a hundredth of one leaves the truncation far below a per
cent, and each row's difference is taken before the sum, so round-off stays below it too."""


def _scores(prob: Problem, model: Model, free):
    """Each row's share of the estimating equation ``psi`` [rows, p] at ``(theta, readings)``, and the effect
    priors' share of it at ``theta``."""
    weight = jnp.asarray(prob.mask, dtype=float) ** 2

    def scores(th, readings):
        f, s, jac = measured(th, prob.with_readings(readings.i_top, readings.i_bottom, readings.x), model)
        return (weight * f / s**2)[:, None] * jac * free

    def prior(th):
        p = th.shape[0]
        return (jnp.zeros_like(th).at[p - model.n:].set(th[p - model.n:]) if model.n else jnp.zeros_like(th)) * free

    return scores, prior


def _moments(theta, steps, prob: Problem, model: Model, free):
    """What the second-order bias needs from the model, by differences along the columns ``u_j`` of ``steps``
    (scaled, [p, q]) and along the readings:

    - ``a_u[j] = (psi(theta + u_j) - psi(theta - u_j)) / 2`` [q, p], i.e. ``A u_j``;
    - ``h_uu[j] = psi(theta + u_j) + psi(theta - u_j) - 2 psi(theta)`` [q, p], i.e. ``psi_theta,theta[u_j, u_j]``;
    - at ``theta``, ``t1 = sum_k sigma_k^2 psi_mm,kk`` [p] and ``B = sum_k sigma_k^2 psi_m_k psi_m_k^T`` [p, p];
    - ``K[a, j, d] = sum_k sigma_k^2 (d psi_m_k,a / d u_j) psi_m_k,d`` [p, q, p].

    Along the readings: central differences of one noise std (a reading without noise gets a step of 1e-9 and no
    weight); along theta: central differences of ``u_j``, each row's before the sum (``psi`` is a sum of large
    terms that cancel at the estimate).  One vmapped program of the model: nested forward derivatives compile
    several times slower.
    """
    free = jnp.asarray(free, dtype=float)
    r = prob.readings
    n = r.x.shape[0]
    sigma = jnp.stack([jnp.broadcast_to(jnp.asarray(s, dtype=float), r.x.shape)
                       for s in (prob.s_top, prob.s_bottom, prob.s_x)])              # [3, rows]
    base = jnp.stack((r.i_top, r.i_bottom, r.x))
    h = jnp.where(sigma > 0, sigma, 1e-9)
    var = sigma**2
    eye = jnp.eye(3)[:, :, None]
    readings = jnp.concatenate([base[None], base[None] + eye * h[None], base[None] - eye * h[None]])   # [7, 3, rows]
    # the seven readings of every row as one problem of 7 x rows rows (a row's force is its own): one evaluation
    # of the model, where a vmap over the readings would compile twice as long
    tiled = jax.tree.map(lambda a: jnp.tile(a, (7,) + (1,) * (a.ndim - 1)) if a.ndim and a.shape[0] == n else a,
                         prob)
    tiled = tiled.with_readings(*readings.transpose(1, 0, 2).reshape(3, 7 * n))
    scores, prior = _scores(tiled, model, free)
    q = steps.shape[1]
    points = jnp.concatenate([theta[None], theta[None] + steps.T, theta[None] - steps.T])           # [2q + 1, p]

    def at(th):
        g = scores(th, tiled.readings).reshape(7, n, -1)                             # [7, rows, p]
        return g[0], (g[1:4] - g[4:7]) / (2.0 * h[:, :, None]), (g[1:4] - 2.0 * g[0][None] + g[4:7])

    g, d1, d2 = jax.vmap(at)(points)
    up, down = slice(1, q + 1), slice(q + 1, 2 * q + 1)
    a_u = (g[up] - g[down]).sum(axis=1) / 2.0 + jax.vmap(prior)(steps.T)
    h_uu = (g[up] + g[down] - 2.0 * g[0][None]).sum(axis=1)
    t1 = jnp.einsum("cn,cna->a", var / h**2, d2[0])
    b = jnp.einsum("cn,cna,cnb->ab", var, d1[0], d1[0])
    k = jnp.einsum("cn,jcna,cnd->ajd", var, (d1[up] - d1[down]) / 2.0, d1[0])
    return a_u, h_uu, t1, b, k


moments_of_sets = eqx.filter_jit(eqx.filter_vmap(_moments, in_axes=(0, 0, 0, None, 0)))
""":func:`_moments` of a batch of data sets (leading axis of theta, steps, problems and free masks)."""


def second_order_biases(thetas, probs: Problem, model: Model, free, cov):
    """Second-order bias of each estimate (module docstring), stacked: ``thetas[sets, p]`` (scaled), ``probs`` a
    batch of problems (leading axis ``sets``; their masks the fits' row weights), ``free[sets, p]`` 1 for the
    estimated entries, ``cov[sets, p, p]`` the scaled covariance of the estimate (0 outside the free entries),
    whose square roots ``U`` (``cov = U U^T``) set the steps along theta.  Returns ``bias[sets, p]`` (scaled, 0
    outside the free entries; not finite where the covariance or the estimating equation is singular).

    ``A = d psi / d theta`` is ``(A U) U^+``; ``psi_theta,theta`` contracted with ``M = A^-1 B A^-T`` is
    ``sum_jl C_jl psi_theta,theta[u_j, u_l]`` with ``C = U^+ M U^+T``, of which the diagonal is measured.  ``M`` is
    the covariance the noise gives the estimate and ``U U^T`` the covariance the fit reports, so ``C`` is the
    identity but for the residuals' share of ``A`` and ``B``, of relative order ``n^-1/2``: the off-diagonal
    terms it leaves out are that small a share of a term that is itself a share of the bias (the whole stays within
    2 % of the exact expansion on the tests' data).
    """
    free = np.asarray(free, dtype=float)
    thetas = np.asarray(thetas, dtype=float)
    lam, vec = np.linalg.eigh(cov)
    roots = vec * np.sqrt(np.maximum(lam, 0.0))[:, None, :]               # [sets, p, p]: cov = roots roots^T
    a_u, h_uu, t1, b, k = (np.asarray(a) for a in moments_of_sets(thetas, THETA_STEP * roots, probs, model, free))
    p = free.shape[1]
    u_inv = np.linalg.pinv(roots)
    a = (np.einsum("sja,sjb->sab", a_u / THETA_STEP, u_inv) * free[:, :, None] * free[:, None, :]
         + (1.0 - free)[:, :, None] * np.eye(p))
    with np.errstate(all="ignore"):
        a_inv = np.linalg.inv(a)
        c = u_inv @ a_inv @ b @ np.swapaxes(a_inv, 1, 2) @ np.swapaxes(u_inv, 1, 2)
        t3 = np.einsum("sj,sja->sa", np.diagonal(c, axis1=1, axis2=2), h_uu / THETA_STEP**2)
        cross = -2.0 * np.einsum("sajd,sjd->sa", k / THETA_STEP, u_inv @ a_inv)
        bias = -0.5 * np.einsum("sab,sb->sa", a_inv, (t1 + cross + t3) * free)
    return np.where(np.isfinite(a_inv).all(axis=(1, 2))[:, None], bias, np.nan)
