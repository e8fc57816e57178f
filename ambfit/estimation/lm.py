"""The least-squares solve: Levenberg-Marquardt over the effective-variance residuals of one data set.

:func:`solve` runs ``reweightings`` rounds (default :data:`REWEIGHTINGS`) of Levenberg-Marquardt, each with the
effective-variance weights held at its start, then measures the solution (every row's Jacobian and standardized
residual) with the same evaluation of the model, and returns a :class:`Solution`.  It is jit- and vmap-safe; many
data sets are solved together by :mod:`ambfit.estimation.batches`.

The iteration is optimistix's ``LevenbergMarquardt`` written out (damped Newton steps with step size
``1/lambda`` by QR, its ``ClassicalTrustRegion``: accept when the loss falls by 1 % of the predicted reduction,
step size x3.5 above 99 %, x0.25 on rejection; Cauchy termination at ``rtol = atol``, default :data:`RTOL`; its
first step evaluates the start), plus a stop of ours when the round's EDM is below ``edm_round`` (default
:data:`EDM_ROUND`).  The three settings are arguments of :func:`solve`, traced like the step budget: any values run
the same compiled program.  Written out so that one place in the program evaluates the model (force, noise and
Jacobian, :func:`ambfit.estimation.core.measured_from`): a round's start, each trial point and the solution; each
further place is traced and compiled again.  A model that solves per reading (the magnetic circuit's fluxes) starts
each trial's solve from the accepted point's solution, which takes Newton's method about half the steps of a start
from zero flux and gives the same force.
"""

from __future__ import annotations

import contextlib
import contextvars
from collections.abc import Sequence
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ambfit._arrays import traced
from ambfit._recent import Recent
from ambfit.estimation.core import EDM_MAX, IDEAL, Model, Problem, measured_from, weighted

REWEIGHTINGS = 2
"""Rounds of solving with the effective-variance weights held fixed, then re-evaluated at the estimate.

Holding the weights fixed within a round gives Levenberg-Marquardt a consistent objective (its trust-region ratio
test otherwise rejects steps when the weights move); a second round at the first round's estimate reproduces the
fully reweighted solution to 9 digits on the rig designs (a third changes nothing)."""

EDM_ROUND = 1e-2 * EDM_MAX
"""A round also stops once its estimated distance to the minimum (with the round's weights) is below this: every
parameter within 1e-4 standard errors of the round's optimum.  Near the optimum the Cauchy test waits for a step
that changes neither theta nor the residuals by 1e-6 relative while the trust region rejects steps on round-off;
the estimates it gives are the same to 1e-8 relative."""

FIRST_STEPS = 3
"""Steps per round of the ideal law's first solve from a closed-form or grid start: enough for every one of 60 rig
data sets (three designs, random gaps and origins) to reach ``EDM_MAX``; 2 left 23 of them short.  A data set not
there yet gets a second solve of ``max_steps``."""

RTOL = 1e-6
"""Levenberg-Marquardt's own stopping tolerance (relative and absolute, on the step and on the residuals).
Convergence is judged by ``EDM_MAX``; a tighter tolerance only adds steps rejected on round-off near the optimum."""


class RESULTS(eqx.Enumeration):
    """A solve's outcome: the values of optimistix's ``RESULTS`` that the iteration written out here can reach,
    with optimistix's messages.  Defined here so that a fit imports neither optimistix nor lineax, whose import
    every command would wait for."""

    successful = ""
    nonlinear_max_steps_reached = (
        "The maximum number of steps was reached in the nonlinear solver. The problem may not be solveable (e.g., a "
        "root-find on a function that has no roots), or you may need to increase `max_steps`.")


def succeeded(result) -> np.ndarray:
    """Whether a concrete outcome (or each of a batch's) is ``successful``, read in NumPy: comparing two outcomes
    would run a JAX operation.  One outcome may be given as text (:func:`ambfit.estimation.batches.solve_sets`):
    ``"successful"`` or a message."""
    if isinstance(result, str):
        return np.asarray(result == "successful")
    (value,), (ok,) = jax.tree.leaves(result), jax.tree.leaves(RESULTS.successful)
    return np.asarray(value) == np.asarray(ok)


class Solution(NamedTuple):
    """What a solve returns (a pytree: jit- and vmap-safe; leading batch axes under ``vmap``).

    Attributes
    ----------
    theta : array[p]
        The scaled parameter vector at the solution (:mod:`ambfit.estimation.core`).
    result : RESULTS or str
        The last round's outcome: ``successful`` when the Cauchy test or :data:`EDM_ROUND` stopped it, else
        ``nonlinear_max_steps_reached``; :func:`ambfit.estimation.batches.solve_sets` gives it as text.
    steps : int
        Levenberg-Marquardt steps of all rounds.
    edm : float
        Estimated distance to the minimum (:func:`distance`); convergence is ``edm < EDM_MAX``.
    jac : array[rows + priors, p]
        Jacobian of the weighted residuals (rows weighted by the problem's mask), noise held.
    jac_all : array[rows + priors, p]
        The same with every row at weight 1 (outlier tests and leverages of held-out rows need it).
    z : array[rows]
        ``(F - L) / s_eff`` of every row.
    s : array[rows]
        ``s_eff`` [N] of every row (the effective noise std the solution's weights hold).
    """

    theta: jnp.ndarray
    result: RESULTS | str
    steps: jnp.ndarray
    edm: jnp.ndarray
    jac: jnp.ndarray
    jac_all: jnp.ndarray
    z: jnp.ndarray
    s: jnp.ndarray

    @property
    def converged(self):
        return self.edm < EDM_MAX


class _State(NamedTuple):
    """The solver's state between two evaluations of the model."""

    y: jnp.ndarray              # the accepted point
    r: jnp.ndarray              # its weighted residuals
    jac: jnp.ndarray            # and Jacobian
    s: jnp.ndarray              # the round's effective noise std (held within a round)
    step_size: jnp.ndarray      # 1 / lambda
    steps: jnp.ndarray          # steps of this round
    y_eval: jnp.ndarray         # the next point to evaluate
    start: jnp.ndarray          # y_eval starts a round
    round: jnp.ndarray
    total: jnp.ndarray          # steps of all rounds
    result: RESULTS
    final: jnp.ndarray          # the solution's measurement is done
    at: tuple                   # the measurement at y: (F - L, s_eff, d(F - L)/d theta)
    have: jnp.ndarray           # ``at`` holds it (every point but the start was measured when accepted)
    flux: jnp.ndarray | None    # the model's solve per row at y, the next trial's start (None: the model has none)


# --- one compiled solve for a set of models ------------------------------------------------------------------
#
# A diagnosis fits a dozen models; traced and compiled one by one, the Levenberg-Marquardt machinery is built
# again for each and dominates a cold start.  Within :func:`compiled_together` the models of a set share one
# compiled solve: theta is padded to the widest model's effect parameters (the padding's prior residuals hold
# it at 0), the model's evaluation is a ``lax.switch`` over the members, and only the member fitted runs.

_TOGETHER: contextvars.ContextVar[tuple] = contextvars.ContextVar("ambfit_models_together", default=())


@contextlib.contextmanager
def compiled_together(models: Sequence[Model]):
    """Within this block, a solve of any model shaped like one of ``models`` runs the one compiled solve of
    the whole set (one compilation instead of one per model; the fit is the same).  Blocks nest: a model not in
    the inner block's set is looked up in the outer ones (a diagnosis' pairs, known only once its singles are
    scored, are compiled as a set of their own while the singles keep theirs)."""
    models = tuple(models)
    token = _TOGETHER.set(_TOGETHER.get() + ((models, [_shape(m) for m in models]),))   # shapes, once per block
    try:
        yield
    finally:
        _TOGETHER.reset(token)


def _shape(model: Model):
    leaves, tree = jax.tree_util.tree_flatten(model)
    return tree, tuple(np.shape(x) for x in leaves)


def _members(model: Model) -> tuple[tuple, int]:
    """The set ``model`` is solved in and its index there (itself alone outside :func:`compiled_together`)."""
    key = _shape(model)
    for group, shapes in reversed(_TOGETHER.get()):        # the innermost block first
        if key in shapes:
            i = shapes.index(key)
            return group[:i] + (model,) + group[i + 1:], i
    return (model,), 0


def _normal(jac, r):
    """The normal equations ``J^T J x = J^T r`` with the columns scaled to unit norm: ``(H, b, d)`` with
    ``H = D J^T J D`` (unit diagonal), ``b = D J^T r``, ``D = diag(1 / d)`` and ``d`` the column norms.  A zero column
    (a held parameter: k without a known load, a load no used row sees) gets unit diagonal and zero gradient."""
    h, g = jac.T @ jac, jac.T @ r
    norm = jnp.sqrt(jnp.diag(h))
    zero = norm == 0
    d = jnp.where(zero, 1.0, norm)
    return h / jnp.outer(d, d) + jnp.diag(jnp.where(zero, 1.0, 0.0)), g / d, d


def _damped_step(jac, r, step_size):
    """The Levenberg-Marquardt step from ``(J, r)``: ``(J^T J + I / step_size) x = J^T r`` (optimistix's
    ``DampedNewtonDescent``; the step is ``-x``), by Cholesky of the column-scaled system.

    The normal equations square the condition number of the column-scaled Jacobian; the fits judged
    well-conditioned have it below ``1e8``, and a relative ridge of 1e-13 keeps the factorization defined in
    directions beyond that (an unidentifiable valley), where the step is then as the damping alone makes it.
    """
    ok = step_size > jnp.finfo(step_size.dtype).eps
    damping = jnp.where(ok, 1.0 / jnp.where(ok, step_size, 1.0), 1e100)
    h, b, d = _normal(jac, r)
    a = h + jnp.diag(damping / d**2 + 1e-13)
    return jax.scipy.linalg.cho_solve(jax.scipy.linalg.cho_factor(a), b) / d


def distance(jac, r):
    """``g^T (J^T J)^-1 g`` with ``g = J^T r``: the χ² a full Gauss-Newton step would still gain (by Cholesky of the
    column-scaled normal equations).  Held parameters have zero columns: unit diagonal, zero gradient; a singular
    ``J^T J`` otherwise gives nan, i.e. "not converged", and the identifiability checks then say why."""
    h, b, _ = _normal(jac, r)
    return b @ jax.scipy.linalg.cho_solve(jax.scipy.linalg.cho_factor(h), b)


def _cauchy(y, y_diff, f, f_diff, rtol):
    """Optimistix's Cauchy termination: both the step and the change of the residuals are small (max norm)."""
    y_done = jnp.max(jnp.abs(y_diff) / (rtol + rtol * jnp.abs(y))) < 1
    return y_done & (jnp.max(jnp.abs(f_diff) / (rtol + rtol * jnp.abs(f))) < 1)


@eqx.filter_jit
def _solve_in(theta0, prob, models, index, budget, reweightings, edm_round, rtol) -> Solution:
    """``reweightings`` rounds of at most ``budget`` steps, each stopped by the Cauchy test at ``rtol`` or an EDM
    below ``edm_round`` (traced numbers: every value runs the same program), then the measurements at the solution;
    see the module docstring."""
    n = max(m.n for m in models)
    p = theta0.shape[0]
    width = max(m.flux_width for m in models)

    def branch(m):
        # a model that solves per row (the magnetic circuit) starts from the accepted point's solution; the others
        # pass the start on
        def measure_one(theta, start):
            f, s, jf, flux = measured_from(theta, prob, m, p - n + m.n, flux_start=start if m.flux_width else None)
            return f, s, jf, flux if m.flux_width else start
        return measure_one

    branches = [branch(m) for m in models]

    def measure(theta, start):
        return branches[0](theta, start) if len(models) == 1 else jax.lax.switch(index, branches, theta, start)

    def body(c: _State) -> _State:
        # a round starts at the accepted point, measured when it was accepted: only trial points are evaluated
        f, s_now, jf, flux = jax.lax.cond(c.start & c.have, lambda: c.at + (c.flux,),
                                          lambda: measure(c.y_eval, c.flux))
        start, final = c.start, c.start & (c.round == reweightings)
        s = jnp.where(start, s_now, c.s)                    # a round holds the weights of its start
        r_e, j_e = weighted(c.y_eval, (f, s, jf), prob.mask, n)
        # the trust region (a round's start is always accepted, its step size reset to 1)
        r, y = jnp.where(start, 0.0, c.r), jnp.where(start, c.y_eval, c.y)
        loss_diff = 0.5 * (r_e @ r_e - r @ r)
        predicted = 0.5 * (jnp.sum((c.jac @ (c.y_eval - y) + r) ** 2) - r @ r)
        accept = start | (loss_diff <= 0.01 * predicted)
        good = ~start & (loss_diff < 0.99 * predicted) & (predicted < 0)
        step_size = jnp.where(start, 1.0, jnp.where(accept, jnp.where(good, 3.5, 1.0), 0.25) * c.step_size)
        done = accept & _cauchy(c.y_eval, c.y_eval - y, r_e, r_e - r, rtol)
        y, r, jac = (jnp.where(accept, new, old) for new, old in ((c.y_eval, y), (r_e, r), (j_e, c.jac)))
        done = done | (accept & (distance(jac, r) < edm_round))
        steps = jnp.where(start, 1, c.steps + 1)
        over = done | (steps >= budget)
        outcome = RESULTS.where(done, RESULTS.successful, RESULTS.nonlinear_max_steps_reached)
        # the accepted point's measurement and its solve per row, kept for the solution and the next trial
        at, flux = jax.tree.map(lambda new, old: jnp.where(accept, new, old), ((f, s_now, jf), flux), (c.at, c.flux))
        return _State(y=y, r=r, jac=jac, s=s, step_size=step_size, steps=steps,
                      y_eval=jnp.where(over, y, y - _damped_step(jac, r, step_size)), start=over,
                      round=c.round + over.astype(int), total=c.total + jnp.where(final, 0, 1),
                      result=RESULTS.where(over & ~final, outcome, c.result),
                      # the loop ends at the solution's measurement (the accepted point's, kept in ``at``)
                      final=final, at=at, have=c.have | accept, flux=flux)

    rows = prob.readings.x.shape[0]
    start = jnp.zeros((rows, width)) if width else None           # the first point's solve: from zero
    blank = jax.tree_util.tree_map(lambda a: jnp.zeros(a.shape, a.dtype), jax.eval_shape(measure, theta0, start))[:3]
    m = blank[0].shape[0] + n
    init = _State(y=theta0, r=jnp.zeros(m), jac=jnp.zeros((m, p)), s=blank[1], step_size=jnp.asarray(1.0),
                  steps=jnp.asarray(0), y_eval=theta0, start=jnp.asarray(True), round=jnp.asarray(0),
                  total=jnp.asarray(0), result=RESULTS.successful, final=jnp.asarray(False), at=blank,
                  have=jnp.asarray(False), flux=start)
    c = jax.lax.while_loop(lambda c: ~c.final, body, init)
    # the Jacobian with the noise held at the solution's: weighted as the fit weighs its rows, and every row at 1
    r, j = weighted(c.y, c.at, prob.mask, n)
    j_all = weighted(c.y, c.at, jnp.ones_like(prob.mask), n)[1]
    f, s, _ = c.at
    return Solution(theta=c.y, result=c.result, steps=c.total, edm=distance(j, r), jac=j, jac_all=j_all, z=f / s, s=s)


_PARTS = Recent(64)
"""Each set of models solved lately, by the identities of its members: its array leaves and the id of its static
rest.  Models are immutable, so a set's identity fixes both; the split costs more than the solve's dispatch."""

_PROGRAMS: dict = {}
"""The jitted solve per problem structure and static part of a set of models (``jax.jit`` then keys on shapes)."""

_STATICS: dict = {}
"""Each static part of a set of models seen, by equality: equal parts are one object, so a program is found by its
identity without hashing the part at every call, and sets alike but for their arrays share one program."""


def _compiled(prob: Problem, models: tuple):
    """The jitted solve for ``prob``'s structure and ``models``, with their array leaves: what ``eqx.filter_jit``
    does (arrays traced, everything else static), without partitioning the models and hashing their static part at
    every call (a diagnosis solves a hundred times, and a warm solve of 900 readings takes half a millisecond)."""
    key = tuple(map(id, models))
    hit = _PARTS.get(key)
    if hit is None:
        dynamic, static = eqx.partition(models, eqx.is_array)
        leaves, tree = jax.tree_util.tree_flatten(dynamic)
        static = _STATICS.setdefault(static, static)
        hit = (models, leaves, tree, static)        # (holding the models keeps their identities theirs)
        _PARTS.put(key, hit)
    _, m_leaves, m_tree, static = hit
    p_leaves, p_tree = jax.tree_util.tree_flatten(prob)
    program_key = (p_tree, m_tree, id(static))
    program = _PROGRAMS.get(program_key)
    if program is None:
        raw = _solve_in.__wrapped__

        def program(theta0, p_leaves, m_leaves, index, *settings):
            ms = eqx.combine(jax.tree_util.tree_unflatten(m_tree, m_leaves), static)
            return raw(theta0, jax.tree_util.tree_unflatten(p_tree, p_leaves), ms, index, *settings)

        program = _PROGRAMS.setdefault(program_key, jax.jit(program))
    return program, p_leaves, m_leaves


def _settings(xp, max_steps, reweightings, edm_round, rtol) -> tuple:
    """The solve's step budget and settings as arrays of ``xp`` (NumPy or JAX), of one dtype whatever the caller
    passed, so that every value runs the same compiled program."""
    return (xp.asarray(max_steps), xp.asarray(reweightings, dtype=int), xp.asarray(edm_round, dtype=float),
            xp.asarray(rtol, dtype=float))


def solve(theta0, prob: Problem, model: Model = IDEAL, max_steps: int = FIRST_STEPS, *,
          reweightings: int = REWEIGHTINGS, edm_round: float = EDM_ROUND, rtol: float = RTOL) -> Solution:
    """Levenberg-Marquardt from ``theta0`` (scaled), at most ``max_steps`` steps per round (jit- and vmap-safe).

    ``reweightings`` rounds, each with the effective-variance weights of its start, stopped by optimistix's Cauchy
    test at ``rtol`` or when its EDM is below ``edm_round`` (the defaults are the module's constants, with the
    evidence that set them).  The step budget and these three are traced: any values run one compiled program.

    The solve of ``model`` runs in its set (see :func:`compiled_together`) and is cut back to the model's own
    entries.  Called with concrete values, the padding and the cutting are done in NumPy (each eager JAX operation
    is a dispatch, and a diagnosis solves a hundred times); under ``jit`` or ``vmap`` in JAX.
    """
    models, index = _members(model)
    pad = max(m.n for m in models) - model.n
    settings = (max_steps, reweightings, edm_round, rtol)
    if traced(theta0, prob):
        if pad:
            theta0 = jnp.concatenate([jnp.asarray(theta0), jnp.zeros(pad)])
        sol = _solve_in(theta0, prob, models, jnp.asarray(index), *_settings(jnp, *settings))
    else:
        theta0 = np.asarray(theta0, dtype=float)
        if pad:
            theta0 = np.concatenate([theta0, np.zeros(pad)])
        program, p_leaves, m_leaves = _compiled(prob, models)
        sol = program(theta0, p_leaves, m_leaves, np.asarray(index), *_settings(np, *settings))
        sol = sol._replace(**{k: np.asarray(getattr(sol, k)) for k in ("theta", "steps", "edm", "jac", "jac_all", "z", "s")})
    if pad:
        width, rows = sol.theta.shape[-1] - pad, sol.jac.shape[-2] - pad
        sol = sol._replace(theta=sol.theta[..., :width], jac=sol.jac[..., :rows, :width],
                           jac_all=sol.jac_all[..., :rows, :width])
    return sol


def measure(theta, prob: Problem, model: Model = IDEAL) -> Solution:
    """The problem measured at ``theta`` as a solve ends (its weights, residuals, Jacobians and noise there), without
    a step: the solve's own compiled program with no step budget and no reweighting round, so that a model already
    fitted at this shape compiles nothing more."""
    return solve(theta, prob, model, 0, reweightings=0)
