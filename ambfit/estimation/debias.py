"""Bias corrections of the least-squares estimates: second order by the delta method (the default), or by a
parametric bootstrap.

Currents enter the force law squared and every reading is noisy, so the estimator of :mod:`ambfit.estimation.fit`
has a bias of second order in the noise (an errors-in-variables effect: a row's Jacobian and weight correlate with
its own noise).  ``benchmarks/ls_bias.py`` measures it on the paper's protocols: about +0.1 standard deviations on
the origins at 0.6 mA, three times that at 1.8 mA, and several standard deviations with the current channels' zeros
free: enough to put a study of a few hundred data sets many standard errors off.

Second order (:func:`second_order_biases`)
------------------------------------------
The estimate solves ``psi(theta, m) = sum_j w_j (F_j - L_j) dF_j/dtheta + q = 0`` for the readings ``m``
(``w = 1 / s_eff^2`` at ``theta``, as the reweighting's fixed point has them; ``q`` the effect priors').
Expanding the implicit function ``theta(m)`` to second order about the noise-free readings, with independent
noise of variance ``sigma_k^2`` on each reading ``k``,

    E[theta] - theta(m_true) = -1/2 A^-1 sum_k sigma_k^2 (psi_mm,kk + 2 psi_theta,m_k v_k + psi_theta,theta[v_k, v_k]),
    A = d psi / d theta,   v_k = -A^-1 psi_m_k,

the same expansion as Cox and Snell's (J. R. Stat. Soc. B 30, 248, 1968) for an estimating equation, here in the
readings instead of the responses (Amemiya and Fuller, Ann. Stat. 16, 147, 1988, for errors in variables).
``theta(m_true)`` is the truth for the ideal law; with effects under priors it is the noise-free estimate, so the
priors' pull towards their centres stays (it is not noise).  The derivatives are differences of the model
(:func:`_moments`, and :func:`_mixed` for the middle term); evaluated at the estimate and the measured readings
instead of the unknown truth, the expansion leaves an error of third order.  The force of a row depends only on
that row's readings, so one difference per kind of reading (top current, bottom current, position) gives every
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

import contextlib
import contextvars
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
    measured,
    si_scale,
    target,
    unpack,
)
from ambfit.estimation.covariance import result_at
from ambfit.estimation.lm import measure, solve
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
    # measured at the corrected estimate; the solve's record is the fit's
    sol = measure(theta, prob, model)._replace(result=res.optimistix, steps=res.num_steps, edm=res.edm)
    res = result_at(sol, prob, meta, model, res.start, thresholds)
    free = free_mask(prob, meta)
    scale = si_scale(prob)[0][free]
    return dataclasses.replace(res, bias_correction={
        "method": "bootstrap", "n": correction.n, "converged_fraction": correction.converged_fraction,
        **{n: {"subtracted": float(b), "mc_error": float(e)}
           for n, b, e in zip(res.names, correction.bias[free] * scale, correction.mc_error[free] * scale)}})


# --- second order ------------------------------------------------------------------------------------------

MAX_ROWS = 8192
"""A data set of more rows has its bias's sums over rows taken over an evenly spaced subset of this many, scaled
up: their sampling error is about ``MAX_ROWS^-1/2`` of the bias (a per cent), where the whole set would cost many
times the fit and its memory."""

MAX_SHIFT = 1.0
"""The correction is applied only where it moves the estimate by at most this many standard errors of a fit of
as many readings as parameters (``sqrt(b^T C^-1 b p / n)``, ``C`` the estimate's covariance, ``p`` parameters,
``n`` readings): the expansion is a series in each reading's noise, whose first term as large as one reading's
own scatter says the next terms are not negligible.  (The joint shift in standard errors of the fit itself grows
as ``sqrt(n)`` where the expansion holds as well as ever.)  Measured: the ideal law 0.04-0.11 (Table 2 at 0.6 and
1.8 mA, 80 to 32000 readings), the current channels' zeros fitted 0.5 (a correction a Monte Carlo confirms,
``benchmarks/ls_bias.py``), the magnetic circuit on the finite-element bearing 1.2."""

THETA_STEP = 0.01
"""Differences along theta step this fraction of a standard error (along each square root of the covariance).
Steps of a whole standard error put the derivatives of the estimating equation up to 6 % off on Table 2 at 1.8 mA
(against nested forward derivatives); a hundredth of one, below 0.1 %.  Each row's difference is taken before the
sum over rows, so round-off stays far below that."""


def _scores(prob: Problem, model: Model, free):
    """Each row's share of the estimating equation ``psi`` [rows, p] at ``(theta, readings)`` (the effect priors
    add ``q``, linear in theta)."""
    weight = jnp.asarray(prob.mask, dtype=float) ** 2

    def scores(th, readings):
        f, s, jac = measured(th, prob.with_readings(readings.i_top, readings.i_bottom, readings.x), model)
        return (weight * f / s**2)[:, None] * jac * free

    return scores


def _readings(prob: Problem, share, xp):
    """The seven readings of every row at which :func:`_moments` differences the scores ([7, 3, rows]: the
    measured, then each kind of reading (top current, bottom current, position) one noise std up, then down), the
    steps ``h`` [3, rows] (1e-9 for a reading without noise) and the noise variances ``var`` [3, rows] scaled by
    ``share``."""
    r = prob.readings
    sigma = xp.stack([xp.broadcast_to(xp.asarray(s, dtype=float), r.x.shape)
                      for s in (prob.s_top, prob.s_bottom, prob.s_x)])              # [3, rows]
    base = xp.stack((r.i_top, r.i_bottom, r.x))
    h = xp.where(sigma > 0, sigma, 1e-9)
    var = sigma**2 * xp.asarray(share, dtype=float)[:, None]
    eye = xp.eye(3)[:, :, None]
    return xp.concatenate([base[None], base[None] + eye * h[None], base[None] - eye * h[None]]), h, var


def _sums(at, off, h, var, xp):
    """The sums :func:`_moments` returns, from the scores ``at`` [7, rows, p] at theta and the seven readings of
    :func:`_readings`, and ``off`` [2q, rows, p] at theta + u_j then theta - u_j and the measured readings."""
    q = off.shape[0] // 2
    d1 = (at[1:4] - at[4:7]) / (2.0 * h[:, :, None])
    d2 = at[1:4] - 2.0 * at[0][None] + at[4:7]
    a_u = (off[:q] - off[q:]).sum(axis=1) / 2.0           # (the rows' share: the priors' is added by the caller)
    h_uu = (off[:q] + off[q:] - 2.0 * at[0][None]).sum(axis=1)
    t1 = xp.einsum("cn,cna->a", var / h**2, d2)
    b = xp.einsum("cn,cna,cnb->ab", var, d1, d1)
    return a_u, h_uu, t1, b, d1


def _points(theta, steps, xp):
    """theta, then theta + u_j, then theta - u_j for the columns ``u_j`` of ``steps`` [p, q]: [2q + 1, p]."""
    return xp.concatenate([theta[None], theta[None] + steps.T, theta[None] - steps.T])


def _moments(theta, steps, prob: Problem, model: Model, free, share):
    """What the second-order bias needs from the model but its mixed derivatives, by differences along the columns
    ``u_j`` of ``steps`` (scaled, [p, q]) and along the readings:

    - ``a_u[j] = (psi(theta + u_j) - psi(theta - u_j)) / 2`` [q, p], i.e. ``A u_j`` (the rows' share);
    - ``h_uu[j] = psi(theta + u_j) + psi(theta - u_j) - 2 psi(theta)`` [q, p], i.e. ``psi_theta,theta[u_j, u_j]``;
    - at ``theta``, ``t1 = sum_k sigma_k^2 psi_mm,kk`` [p] and ``B = sum_k sigma_k^2 psi_m_k psi_m_k^T`` [p, p];
    - ``d1`` [3, rows, p], each row's score differentiated by each kind of its readings (top current, bottom
      current, position), for :func:`_mixed` (the mixed term, along directions these fix).

    Along the readings: central differences of one noise std (a reading without noise gets a step of 1e-9 and no
    weight); along theta: central differences of ``u_j``, each row's before the sum (``psi`` is a sum of large
    terms that cancel at the estimate).  One vmapped evaluation of the model at theta and the seven readings of
    each row, one at the ``2q`` points off it.  ``share[3]`` scales the noise variance of each kind of reading in the
    sums, not in the weights.  :func:`_measured_moments` gives these and the mixed term from the solve's own
    compiled program.
    """
    free = jnp.asarray(free, dtype=float)
    n = prob.readings.x.shape[0]
    readings, h, var = _readings(prob, share, jnp)
    # the seven readings of every row as one problem of 7 x rows rows (a row's force is its own): one evaluation
    # of the model, not one per reading
    tiled = jax.tree.map(lambda a: jnp.tile(a, (7,) + (1,) * (a.ndim - 1)) if a.ndim else a, prob)
    tiled = eqx.tree_at(lambda t: t.k_free, tiled, prob.k_free)        # (per axis, not per row)
    tiled = tiled.with_readings(*readings.transpose(1, 0, 2).reshape(3, 7 * n))
    at = _scores(tiled, model, free)(theta, tiled.readings).reshape(7, n, -1)          # [7, rows, p]
    off = jax.vmap(lambda th: _scores(prob, model, free)(th, prob.readings))(_points(theta, steps, jnp)[1:])
    return _sums(at, off, h, var, jnp)


def _mixed(theta, steps, per, prob: Problem, model: Model, free, share):
    """``sum_k sigma_k^2 (d/dv_k) psi_m_k`` [p]: each reading's score differentiated by that reading and along a
    direction of theta of its own, ``v_k``.

    By central differences in both: ``steps`` [3, rows, p] (scaled) is each reading's step along theta, ``per``
    [3, rows] its ``v_k`` per unit of that step (0 for a reading without a direction: a held-out row's; a reading
    without noise has a direction but no variance).  Four evaluations per kind of reading (top current, bottom
    current, position), each row at its own theta (the rows evaluated one by one under ``vmap``)."""
    free = jnp.asarray(free, dtype=float)
    n = prob.readings.x.shape[0]
    readings, h, var = _readings(prob, share, jnp)
    # the four corners of each kind: (theta + step, reading + h), (+, - h), (-, + h), (-, - h)
    sign = jnp.asarray([1.0, 1.0, -1.0, -1.0])
    picks = jnp.asarray([1, 4, 1, 4])                     # the reading one step up, one step down (_readings' order)
    thetas = theta + sign[None, :, None, None] * steps[:, None]                           # [3, 4, rows, p]
    corner = readings[jnp.arange(3)[:, None] + picks[None, :]]                            # [3, 4, 3, rows]
    # every field one entry per row (a value for all rows broadcast to them; the per-axis k_free set after), the
    # rows twelve times over
    per_row = eqx.tree_at(lambda t: t.k_free, prob, jnp.zeros(n))
    rows = jax.tree.map(lambda a: jnp.tile(a if a.ndim else jnp.broadcast_to(a, (n,)),
                                           (12,) + (1,) * max(a.ndim - 1, 0))[:, None], per_row)
    rows = eqx.tree_at(lambda t: t.k_free, rows, jnp.broadcast_to(prob.k_free, (12 * n,) + prob.k_free.shape))
    rows = rows.with_readings(*corner.transpose(2, 0, 1, 3).reshape(3, 12 * n, 1))

    def one(th, row):
        f, s, jac = measured(th, row, model)
        return ((row.mask**2 * f / s**2)[:, None] * jac * free)[0]

    g = jax.vmap(one)(thetas.reshape(12 * n, -1), rows).reshape(3, 4, n, -1)
    mixed = (g[:, 0] - g[:, 1] - g[:, 2] + g[:, 3]) / (4.0 * h[:, :, None])
    return jnp.einsum("cn,cna->a", var * per, mixed)


def _measured_moments(theta, steps, prob: Problem, model: Model, free, share):
    """:func:`_moments` and the mixed term of one data set from :func:`ambfit.estimation.lm.measure`: the program
    its fit already compiled for this problem's shape, called at each of the ``(2q + 1) x 7`` points and readings
    (``a_u, h_uu, t1, B`` and ``cross[a, j, d] = sum_k sigma_k^2 (d psi_m_k,a / d u_j) psi_m_k,d`` [p, q, p]).
    Costs those calls where :func:`_moments` and :func:`_mixed` cost compilations of their own."""
    free = np.asarray(free, dtype=float)
    n = np.shape(prob.readings.x)[0]
    readings, h, var = _readings(jax.tree.map(np.asarray, prob), share, np)
    weight = np.asarray(prob.mask, dtype=float) ** 2

    def scores(th, reading):            # as _scores: mask^2 (F - L) / s^2 d(F - L)/d theta (z = (F - L) / s, and
        sol = measure(th, prob.with_readings(*reading), model)       # jac_all the Jacobian / s, every row at 1)
        return (weight * np.asarray(sol.z))[:, None] * np.asarray(sol.jac_all)[:n] * free

    g = np.stack([np.stack([scores(th, reading) for reading in readings])
                  for th in _points(np.asarray(theta, dtype=float), np.asarray(steps), np)])   # [2q + 1, 7, rows, p]
    a_u, h_uu, t1, b, d1 = _sums(g[0], g[1:, 0], h, var, np)
    # each reading's derivative at theta +- u_j, differenced along u_j
    moved = (g[1:, 1:4] - g[1:, 4:7]) / (2.0 * h[None, :, :, None])                  # [2q, 3, rows, p]
    q = len(moved) // 2
    cross = np.einsum("cn,jcna,cnd->ajd", var, (moved[:q] - moved[q:]) / 2.0, d1)
    return a_u, h_uu, t1, b, cross


def _inverse(a, xp):
    """``a``'s inverse; NaN where ``a`` is singular (NumPy's raises, JAX's gives non-finite entries)."""
    if xp is not np:
        return jnp.linalg.inv(a)
    try:
        return np.linalg.inv(a)
    except np.linalg.LinAlgError:
        return np.full_like(a, np.nan)


def _linear_parts(a_u, h_uu, b, roots, u_inv, free, n_effects: int, xp):
    """From one data set's sums (:func:`_moments`, over its rows) and the covariance's square roots ``U`` [p, q] with
    their pseudo-inverse ``U^+`` [q, p]: ``A^-1`` [p, p], ``W = U^+ A^-1`` [q, p] and the third term
    ``t3 = psi_theta,theta`` contracted with ``C`` [p] (:func:`second_order_biases`' notes)."""
    p = roots.shape[0]
    prior = (xp.arange(p) >= p - n_effects) * free         # the priors' share of A u_j: the steps' entries of q
    a_u = a_u + THETA_STEP * roots.T * prior[None, :]
    a = (a_u / THETA_STEP).T @ u_inv * free[:, None] * free[None, :] + xp.diag(1.0 - free)
    a_inv = _inverse(a, xp)
    c = u_inv @ a_inv @ b @ a_inv.T @ u_inv.T
    return a_inv, u_inv @ a_inv, xp.diagonal(c) @ (h_uu / THETA_STEP**2)


def _bias(a_inv, t1, t2, t3, free, xp):
    """``-1/2 A^-1 (t1 + t2 + t3)`` over the free entries; NaN where ``A`` is singular."""
    bias = -0.5 * a_inv @ ((t1 + t2 + t3) * free)
    return xp.where(xp.all(xp.isfinite(a_inv)), bias, xp.nan)


def _directions(theta, roots, u_inv, prob: Problem, model: Model, free, share, row_scale):
    """One data set's :func:`_moments` and linear algebra: ``A^-1``, ``t1``, ``t3`` and the directions along which
    :func:`_mixed` takes the middle term (``roots`` [p, q]: square roots of the covariance along which theta is
    differenced, ``u_inv`` their pseudo-inverse; ``row_scale``: the rows stand for this many times as many)."""
    free = jnp.asarray(free, dtype=float)
    *sums, d1 = _moments(theta, THETA_STEP * roots, prob, model, free, share)
    a_u, h_uu, t1, b = (row_scale * a for a in sums)
    a_inv, w, t3 = _linear_parts(a_u, h_uu, b, roots, u_inv, free, model.n, jnp)
    # sum_j cross[a, j, d] w[j, d] is each reading's score differentiated along v_k = U w psi_m_k: one direction per
    # reading, stepped THETA_STEP along it in the covariance's square roots
    coords = jnp.einsum("jd,cnd->cnj", w, d1)
    size = jnp.sqrt(jnp.sum(coords**2, axis=-1))                                      # [3, rows]
    per = jnp.where(size > 0, size / THETA_STEP, 0.0)
    steps = THETA_STEP * jnp.einsum("pj,cnj->cnp", roots, coords / jnp.where(size > 0, size, 1.0)[..., None])
    return a_inv, t1, t3, jnp.nan_to_num(steps), jnp.nan_to_num(per)


def _finished(theta, parts, prob: Problem, model: Model, free, share, row_scale):
    """The bias from :func:`_directions`' ``parts`` and the middle term (:func:`_mixed`) along their directions."""
    a_inv, t1, t3, steps, per = parts
    free = jnp.asarray(free, dtype=float)
    t2 = -2.0 * row_scale * _mixed(theta, steps, per, prob, model, free, share)
    return _bias(a_inv, t1, t2, t3, free, jnp)


def _bias_one(theta, roots, u_inv, prob: Problem, model: Model, free, share, row_scale):
    """:func:`_directions` then :func:`_finished`: one data set's bias (scaled) in one program."""
    parts = _directions(theta, roots, u_inv, prob, model, free, share, row_scale)
    return _finished(theta, parts, prob, model, free, share, row_scale)


bias_of_one = eqx.filter_jit(eqx.filter_vmap(_bias_one, in_axes=(0, 0, 0, 0, None, 0, 0, 0)))
""":func:`_bias_one` of a batch of one data set (leading axis of every argument but the model): one dispatch where
the two programs below cost two."""

directions_of_sets = eqx.filter_jit(eqx.filter_vmap(_directions, in_axes=(0, 0, 0, 0, None, 0, 0, 0)))
""":func:`_directions` of a batch of data sets.  A program of its own: compiled into one program with
:func:`_finished`, XLA builds a batch's middle term poorly (one data set's well)."""

finished_of_sets = eqx.filter_jit(eqx.filter_vmap(_finished, in_axes=(0, 0, 0, None, 0, 0, 0)))
""":func:`_finished` of a batch of data sets."""


_BY_SOLVE: contextvars.ContextVar[bool] = contextvars.ContextVar("ambfit_bias_by_solve", default=False)


@contextlib.contextmanager
def by_solve():
    """Within this context a data set's second-order bias, computed alone, is evaluated with its solve's compiled
    program (``second_order_biases(via_solve=True)``) instead of programs of its own: for a process that fits a
    data set or two and ends (a command), where compiling those programs would cost more than the fits.  The two
    routes take the same differences (the mixed term along other directions) and agree to round-off and the
    differences' own error (``tests/test_bias.py``)."""
    token = _BY_SOLVE.set(True)
    try:
        yield
    finally:
        _BY_SOLVE.reset(token)


def bias_by_solve() -> bool:
    """Whether :func:`by_solve` is in effect."""
    return _BY_SOLVE.get()


def second_order_biases(thetas, probs: Problem, model: Model, free, cov, share=(1.0, 1.0, 1.0),
                        row_scale=1.0, *, via_solve: bool = False) -> np.ndarray:
    """Second-order bias of each of a batch of estimates (module docstring).

    Parameters
    ----------
    thetas : array[sets, p]
        The estimates (scaled parameter vectors, :mod:`ambfit.estimation.core`).
    probs : Problem
        Their problems stacked (leading axis ``sets``), each masked to the rows its fit used.
    model : Model
        The model fitted.
    free : array[sets, p]
        1 for the estimated entries of theta.
    cov : array[sets, p, p]
        The scaled covariance of each estimate (0 outside its free entries); its square roots ``U``
        (``cov = U U^T``) set the steps along theta.
    share : array[3] or array[sets, 3]
        Scales each kind of reading's noise variance (top current, bottom current, position) in the bias but not in
        the fit's weights: ``(1, 1, 0)`` is the bias the current noise alone causes; a noise estimated from the
        residuals enters as its ratio to the problem's unit weights.
    row_scale : float or array[sets]
        Each problem's rows stand for this many times as many (an evenly spaced subset of a long data set's rows:
        the sums over rows scaled up, :data:`MAX_ROWS`).
    via_solve : bool
        Evaluate the model with the solve's compiled program, a set at a time (:func:`_measured_moments`): for a
        data set or two whose fit compiled that program at their shape.  The default runs a batch in two programs
        of their own (:func:`_directions`, then :func:`_finished`; one data set in one), compiled once per batch
        shape.

    Returns
    -------
    array[sets, p]
        The biases (scaled; 0 outside the free entries; NaN where the estimating equation's derivative is
        singular).

    Notes
    -----
    ``A = d psi / d theta`` is ``(A U) U^+``.  ``psi_theta,theta`` contracted with ``M = A^-1 B A^-T`` is ``sum_jl
    C_jl psi_theta,theta[u_j, u_l]`` with ``C = U^+ M U^+T``, of which the diagonal is measured: ``M`` is the
    covariance the noise gives the estimate and ``U U^T`` the one the fit reports, so ``C`` is the identity but for
    the residuals' share of ``A`` and ``B``, of relative order ``rows^-1/2``.

    Examples
    --------
    >>> import jax, numpy as np
    >>> from ambfit.estimation import core, fit
    >>> from ambfit.rig import protocol, virtual as rig
    >>> data = rig.simulate(rig.PAPER_RIG, protocol.paper_table2(center=(-33.3e-6, 11.3e-6)), seed=1).data
    >>> res = fit.fit(data, debias="none")
    >>> prob, meta = core.build_problem(data)
    >>> free = core.free_mask(prob, meta)
    >>> scale = core.si_scale(prob)[0][free]
    >>> bias = second_order_biases(res.theta[None], jax.tree.map(lambda a: np.asarray(a)[None], prob), core.IDEAL,
    ...                            free[None], (res.cov / np.outer(scale, scale))[None])[0]
    >>> bool(0.05 < bias[2] * scale[2] / res.error("v0") < 0.2)       # the origin's bias in its standard errors
    True
    """
    free = np.asarray(free, dtype=float)
    thetas = np.asarray(thetas, dtype=float)
    sets, p = thetas.shape
    lam, vec = np.linalg.eigh(cov)                                        # (ascending)
    roots = vec * np.sqrt(np.maximum(lam, 0.0))[:, None, :]               # [sets, p, p]: cov = roots roots^T
    # only the directions an estimate moves along: held entries and a batch's padded loads have none (their
    # eigenvalues are round-off of either sign), and a step of zero would evaluate the model for nothing.  As many
    # as the batch's most estimated entries: a count the data fix, so one batch shape compiles once
    moving = max(int(free.sum(axis=1).max(initial=0)), 1)
    roots = roots[:, :, p - moving:]                                       # [sets, p, moving]
    # their pseudo-inverse from the eigenvectors, as an SVD's would be (a root below 1e-15 of the largest inverts
    # to 0), here where the decomposition is at hand
    size = np.sqrt(np.maximum(lam[:, p - moving:], 0.0))
    kept = size > 1e-15 * size.max(axis=1, keepdims=True)
    u_inv = np.swapaxes(vec[:, :, p - moving:] * np.where(kept, 1.0 / np.where(kept, size, 1.0), 0.0)[:, None], 1, 2)
    share = np.broadcast_to(np.asarray(share, dtype=float), (sets, 3))
    rows = np.broadcast_to(np.asarray(row_scale, dtype=float), (sets,))
    if not via_solve:
        if sets == 1:
            return np.asarray(bias_of_one(thetas, roots, u_inv, probs, model, free, share, rows))
        parts = directions_of_sets(thetas, roots, u_inv, probs, model, free, share, rows)
        return np.asarray(finished_of_sets(thetas, parts, probs, model, free, share, rows))
    out = np.zeros((sets, p))
    for s in range(sets):
        a_u, h_uu, t1, b, cross = (rows[s] * a for a in _measured_moments(
            thetas[s], THETA_STEP * roots[s], jax.tree.map(lambda a, s=s: np.asarray(a)[s], probs), model, free[s],
            share[s]))
        with np.errstate(all="ignore"):
            a_inv, w, t3 = _linear_parts(a_u, h_uu, b, roots[s], u_inv[s], free[s], model.n, np)
            t2 = -2.0 * np.einsum("ajd,jd->a", cross / THETA_STEP, w)
            out[s] = _bias(a_inv, t1, t2, t3, free[s], np)
    return out
