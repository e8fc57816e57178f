"""The one least-squares core: data arrays, the model (force law plus effects), residuals and the solve.

Every fit in ambfit runs through here: :func:`ambfit.fit` (ideal or extended), the
batch and bootstrap solves, the posterior's likelihood, the Fisher information, the
design and the diagnosis.  The ideal model is the case ``Model.of(())``.

Parameter vector (scaled, dimensionless)::

    theta = [g_v0, g_w0, v0, w0, k_v, k_w, loads[m], q[n_effect_params]]

with SI values ``theta * param_scale`` for the head and the loads, and
``centre + width * q`` for each free effect parameter (a weak Gaussian prior
``q ~ N(0, 1)`` enters as a residual, so an effect the data cannot see stays at its
prior centre instead of wandering).

Residual of a reading (effective variance, see :mod:`ambfit.estimation.fit`)::

    r = mask * (F(measured; theta) - L) / s_eff,
    s_eff^2 = (dF/di_t s_t)^2 + (dF/di_b s_b)^2 + (dF/dx s_x)^2

with ``F`` from :func:`ambfit.physics.model.evaluate` and its derivatives with
respect to the readings taken by forward-mode automatic differentiation (exact,
so the ideal law needs no separate hand-written copy).  ``mask`` is 0 for rows
held out of a fit (cross-validation keeps one compiled shape for every fold).
The data arrays themselves come from :mod:`ambfit.estimation.problem`.
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
import optimistix as optx

from ambfit._recent import Recent
from ambfit.estimation.problem import Meta, Problem, build_problem  # noqa: F401  (build_problem: the core's entry)
from ambfit.physics.bearing import AXES, PAPER_BEARING, Bearing
from ambfit.physics.effects import Effect
from ambfit.physics.model import BearingParams, evaluate, horseshoe_force, ideal_force, pole_gaps

K_REFERENCE = PAPER_BEARING.force_constant()
"""Force constant [N m^2/A^2] held on an axis without known loads (it cancels from gap and origin)."""

# theta = (g_v0, g_w0) / 1 cm, (v0, w0) / 0.1 mm, (k_v, k_w) / 1e-4, loads / 100 N.  The units are coarse
# on purpose: every column of the standardized Jacobian is then >= ~1e3, so Levenberg-Marquardt's
# initial damping (lambda = 1) is negligible and it takes Gauss-Newton steps from a good seed, while
# keeping its trust region for a poor one.  (With units near the parameters' size the weakest
# eigenvalue of J^T J was ~10, and lambda = 1 cost ~8 extra steps per solve.)
SCALE_HEAD = np.array([1e-2, 1e-2, 1e-4, 1e-4, 1e-4, 1e-4])
SCALE_LOAD = 100.0
HEAD_NAMES = ("g_v0", "g_w0", "v0", "w0", "k_v", "k_w")

REWEIGHTINGS = 2
"""Rounds of solving with the effective-variance weights held fixed, then re-evaluated at the estimate.

Holding the weights fixed within a round gives Levenberg-Marquardt a consistent
objective (its trust-region ratio test otherwise rejects steps when the weights
move); a second round at the first round's estimate reproduces the fully
reweighted solution to 9 digits on the rig designs (a third changes nothing)."""

EDM_MAX = 1e-6
"""Convergence: the estimated distance to the minimum, ``EDM = r^T J (J^T J)^-1 J^T r`` (the χ² a
full Gauss-Newton step would still gain), must fall below this, i.e. every parameter is within
about 1e-3 standard errors of the optimum (iminuit's criterion).  The solver's own Cauchy test (optimistix's,
in :func:`_solve_in`) is reported too, but near the optimum its trust region rejects steps on round-off and it
can stop late or never while the solution is already exact."""

EDM_ROUND = 1e-2 * EDM_MAX
"""A round of Levenberg-Marquardt also stops once its estimated distance to the minimum (with the round's weights)
is below this: every parameter within 1e-4 standard errors of the round's optimum.  Near the optimum the Cauchy
test waits for a step that changes neither theta nor the residuals by 1e-6 relative, and the trust region rejects
steps on round-off meanwhile.  A rig diagnosis (840 readings): 2244 -> 1390 steps, its estimates within 1e-8
relative; its cost, one more P x P solve per step, is ~7 % of a three-step ideal solve (0.84 -> 0.90 ms at best
on 936 readings, measured with the written-out loop)."""

FIRST_STEPS = 3
"""Levenberg-Marquardt steps per round of the first solve: enough for every one of 60 rig data sets
(three designs, random gaps and origins, closed-form or grid starts) to reach ``EDM_MAX``; 2 left
23 of them short.  Near the optimum further steps are mostly rejected on round-off, so a
small fixed budget plus the EDM check is both faster and safer than waiting for
the solver's own termination.  A fit that is not there yet gets a second solve."""


RTOL = 1e-6
"""Levenberg-Marquardt's own stopping tolerance (relative and absolute, on the step and on the residuals).
Convergence is judged by ``EDM_MAX``; with 1e-8 the solver spent about half of its steps near the optimum
having steps rejected on round-off (840 rig readings: 27 steps against 5 for the ideal law, 54 against 30 for
fringing, the estimate and its EDM the same)."""


class FitError(RuntimeError):
    """The fit did not converge or the design does not identify the parameters; the message says why."""


def param_scale(n_loads: int) -> np.ndarray:
    """SI value of one unit of each head and load entry of theta."""
    return np.concatenate([SCALE_HEAD, np.full(n_loads, SCALE_LOAD)])


def to_theta(g0, x0, k, loads=(), q=()) -> np.ndarray:
    """The scaled parameter vector from SI values (pairs ``(v, w)``, nuisance loads [N], effect coordinates)."""
    si = np.concatenate([np.broadcast_to(g0, (2,)), np.broadcast_to(x0, (2,)), np.broadcast_to(k, (2,)),
                         np.asarray(loads, dtype=float)])
    return np.concatenate([si / param_scale(len(loads)), np.asarray(q, dtype=float)])


# --- the model: force law plus effects with free parameters ------------------------------------------------

_MODELS = Recent(64)
"""The last models built, by their effects' identities and bearing: a diagnosis builds the same dozen models a
hundred times, 1 ms each.  Effects are immutable modules, so an instance's identity fixes what the model is."""


class Model(eqx.Module):
    """What is fitted beyond gap, origin, k and loads: effects whose ``RANGES`` fields are free.

    ``fields`` lists ``(effect index, field name, shared)``; each free field is a ``(v, w)`` pair, or one
    value for both axes when the effect class sets ``SHARED`` (a property of the whole stator), with
    prior centre and width from the effect's ``RANGES`` (zero-centred for signed parameters).
    """

    effects: tuple
    fields: tuple = eqx.field(static=True)
    centre: jnp.ndarray
    width: jnp.ndarray
    bearing: Bearing = eqx.field(static=True)

    @classmethod
    def of(cls, effects: Sequence[Effect] = (), bearing: Bearing = PAPER_BEARING) -> Model:
        """The model of ``effects`` (their ``ranges()`` fields free) on ``bearing``."""
        effects = tuple(effects)
        key = (tuple(map(id, effects)), bearing)
        hit = _MODELS.get(key)
        if hit is not None:
            return hit[1]
        model = cls._of(effects, bearing)
        _MODELS.put(key, (effects, model))      # holding the effects: their identities stay theirs while keyed
        return model

    @classmethod
    def _of(cls, effects: tuple, bearing: Bearing) -> Model:
        fields, centre, width = [], [], []
        effects = list(effects)
        for i, e in enumerate(effects):
            shared = getattr(type(e), "SHARED", False)
            for name, (lo, hi) in e.ranges().items():
                if lo == hi:
                    continue
                fields.append((i, name, shared))
                # a free field's value comes from q (build): one shape for every instance, so that a model of
                # fitted effects runs the compiled solve of the same model with default ones
                effects[i] = eqx.tree_at(lambda ef, f=name: getattr(ef, f), effects[i],
                                         jnp.broadcast_to(jnp.asarray(getattr(e, name), dtype=float), (2,)))
                signed = name in type(e).SIGNED
                c = 0.0 if signed else 0.5 * (lo + hi)
                wd = hi if signed else max(hi - lo, 1e-12)
                centre += [c] if shared else [c, c]
                width += [wd] if shared else [wd, wd]
        return cls(tuple(effects), tuple(fields), jnp.asarray(centre, dtype=float).reshape(-1),
                   jnp.asarray(width, dtype=float).reshape(-1), bearing)

    @property
    def n(self) -> int:
        """Number of free effect parameters (entries of ``q``)."""
        return int(self.centre.shape[0])

    @property
    def name(self) -> str:
        """``ideal`` or the effect names joined with ``+`` (contract section 3)."""
        return "+".join(type(e).name for e in self.effects) or "ideal"

    def names(self) -> list[str]:
        """``effect.field[axis]`` per axis, or ``effect.field`` for a field both axes share (one stator)."""
        out = []
        for i, f, shared in self.fields:
            base = f"{type(self.effects[i]).name}.{f}"
            out += [base] if shared else [f"{base}[{ax}]" for ax in AXES]
        return out

    def build(self, q) -> tuple:
        """Effects with their free fields set from the scaled vector ``q`` (value = centre + width * q)."""
        vals = self.centre + self.width * q
        effects = list(self.effects)
        j = 0
        for i, f, shared in self.fields:
            v = jnp.broadcast_to(vals[j:j + 1], (2,)) if shared else vals[j:j + 2]
            effects[i] = eqx.tree_at(lambda e, f=f: getattr(e, f), effects[i], v)
            j += 1 if shared else 2
        return tuple(effects)


IDEAL = Model.of(())
"""The paper's Eq. 4 with no effects, on the paper rig."""


# --- parameters, force, residuals --------------------------------------------------------------------------

class Unpacked(NamedTuple):
    """Theta in SI units: the bearing parameters, the nuisance loads [N] and the effects at their values."""

    params: BearingParams
    loads: jnp.ndarray
    effects: tuple
    q: jnp.ndarray


def unpack(theta, prob: Problem, model: Model = IDEAL) -> Unpacked:
    """Split the scaled parameter vector (see the module docstring); held ``k`` is ``K_REFERENCE``."""
    n_head = theta.shape[0] - model.n
    g0 = theta[0:2] * SCALE_HEAD[0]
    x0 = theta[2:4] * SCALE_HEAD[2]
    k = jnp.where(prob.k_free, theta[4:6] * SCALE_HEAD[4], K_REFERENCE)
    q = theta[n_head:]
    return Unpacked(BearingParams(g0, x0, k), theta[6:n_head] * SCALE_LOAD, model.build(q), q)


def target(prob: Problem, loads) -> jnp.ndarray:
    """The load each row's force must equal: the known load, else its group's nuisance load [N]."""
    nuisance = loads[jnp.maximum(prob.gidx, 0)] if loads.shape[0] else jnp.zeros(prob.x.shape)
    return jnp.where(prob.known, prob.load, nuisance)


def force_misfit(theta, prob: Problem, model: Model = IDEAL):
    """Force misfit ``F - L`` [N] of every row, without the noise (what Levenberg-Marquardt differentiates: the
    effective-variance weights are held within a round, so tracing their derivatives there would only be
    thrown away, and a cold diagnosis is dominated by tracing and compiling)."""
    p = unpack(theta, prob, model)
    return _force(p.params, p.effects, prob, model) - target(prob, p.loads)


def _force(params: BearingParams, effects: tuple, prob: Problem, model: Model):
    """Each row's force [N]: Eq. 4 for the ideal model (a small program to trace), else the effect pipeline."""
    if not model.effects:
        a, r = prob.ax, prob.readings
        return ideal_force(params.g0[a], params.x0[a], params.k[a], r.i_top, r.i_bottom, r.x, model.bearing.cos_alpha)
    return evaluate(params, prob.readings, effects, bearing=model.bearing)[0]


def misfit(theta, prob: Problem, model: Model = IDEAL):
    """Force misfit ``F - L`` [N] of every row and its effective noise std ``s_eff`` [N].

    The derivatives of the force with respect to the readings come from forward-mode automatic
    differentiation through the effect pipeline; for the ideal law (no effects) they are Eq. 4's
    closed-form derivatives (the same numbers, and a much smaller program for JAX to trace: a cold
    ``ambfit identify`` is dominated by tracing).
    """
    p = unpack(theta, prob, model)
    if not model.effects:
        return _ideal_misfit(p, prob, model.bearing.cos_alpha)
    r = prob.readings

    def force(it, ib, x):
        rr = eqx.tree_at(lambda z: (z.i_top, z.i_bottom, z.x), r, (it, ib, x))
        return evaluate(p.params, rr, p.effects, bearing=model.bearing)[0]

    ones, zeros = jnp.ones_like(r.x), jnp.zeros_like(r.x)
    # one linearization, three tangents: the effect pipeline is traced once, not four times (cold starts are
    # dominated by tracing)
    f, lin = jax.linearize(force, r.i_top, r.i_bottom, r.x)
    dt, db, dx = lin(ones, zeros, zeros), lin(zeros, ones, zeros), lin(zeros, zeros, ones)
    return f - target(prob, p.loads), _effective_noise(prob, dt, db, dx)


def _effective_noise(prob: Problem, dt, db, dx):
    """``s_eff`` from the force's derivatives with respect to the top and bottom currents and the position
    (effective variance), or the problem's held noise where it gives one (:meth:`Problem.with_noise`)."""
    s = jnp.sqrt((dt * prob.s_top) ** 2 + (db * prob.s_bottom) ** 2 + (dx * prob.s_x) ** 2)
    return jnp.where(prob.s_held > 0, prob.s_held, s)


def _ideal_misfit(p: Unpacked, prob: Problem, cos_alpha: float):
    """Eq. 4 and its closed-form derivatives ``dF/di_t = 2 k i_t / g_t^2``, ``dF/di_b = -2 k i_b / g_b^2``,
    ``dF/dx = 2 k cos(alpha) (i_t^2 / g_t^3 + i_b^2 / g_b^3)``."""
    a, r = prob.ax, prob.readings
    k = p.params.k[a]
    g_top, g_bottom = pole_gaps(p.params.g0[a], p.params.x0[a], r.x, cos_alpha)
    f = horseshoe_force(k, r.i_top, g_top, k, r.i_bottom, g_bottom)
    dt = 2 * k * r.i_top / g_top**2
    db = 2 * k * r.i_bottom / g_bottom**2
    dx = 2 * k * cos_alpha * (r.i_top**2 / g_top**3 + r.i_bottom**2 / g_bottom**3)
    return f - target(prob, p.loads), _effective_noise(prob, dt, db, dx)


def _with_priors(theta, r, n: int):
    """The rows' residuals ``r``, then the priors' of the last ``n`` entries of theta (``q ~ N(0, 1)``)."""
    return jnp.concatenate([r, theta[theta.shape[0] - n:]]) if n else r


def residuals(theta, prob: Problem, model: Model = IDEAL):
    """Standardized residuals of every row (held-out rows masked to 0), then the effect priors' residuals."""
    f, s = misfit(theta, prob, model)
    return _with_priors(theta, prob.mask * f / jax.lax.stop_gradient(s), model.n)


@eqx.filter_jit
def noise_std(theta, prob: Problem, model: Model = IDEAL):
    """Each row's effective force noise std ``s_eff`` [N] (:func:`misfit`, compiled once per model)."""
    return misfit(theta, prob, model)[1]


@eqx.filter_jit
def standardized(theta, prob: Problem, model: Model = IDEAL):
    """``(F - L) / s_eff`` of every row, held-out rows included (dimensionless)."""
    f, s = misfit(theta, prob, model)
    return f / s


# --- one compiled solve for a set of models ------------------------------------------------------------------
#
# A diagnosis fits a dozen models; traced and compiled one by one, the Levenberg-Marquardt machinery is built
# again for each and dominates a cold start.  Within :func:`compiled_together` the models of a set share one
# compiled solve: theta is padded to the widest model's effect parameters (the padding's prior residuals hold
# it at 0), force, noise and Jacobian (:func:`_measured`) are a ``lax.switch`` over the members, and only the
# member fitted runs.

_TOGETHER: contextvars.ContextVar[tuple] = contextvars.ContextVar("ambfit_models_together", default=())


@contextlib.contextmanager
def compiled_together(models: Sequence[Model]):
    """Within this block, a solve of any model shaped like one of ``models`` runs the one compiled solve of
    the whole set (one compilation instead of one per model; the fit is the same)."""
    models = tuple(models)
    token = _TOGETHER.set((models, [_shape(m) for m in models]))      # the members' shapes, once per block
    try:
        yield
    finally:
        _TOGETHER.reset(token)


def _shape(model: Model):
    leaves, tree = jax.tree_util.tree_flatten(model)
    return tree, tuple(np.shape(x) for x in leaves)


def _members(model: Model) -> tuple[tuple, int]:
    """The set ``model`` is solved in and its index there (itself alone outside :func:`compiled_together`)."""
    if _TOGETHER.get():
        group, shapes = _TOGETHER.get()
        key = _shape(model)
        if key in shapes:
            i = shapes.index(key)
            return group[:i] + (model,) + group[i + 1:], i
    return (model,), 0


def _weighted(theta, measured, mask, n: int):
    """Residuals ``mask (F - L) / s`` then the effect priors' (the last ``n`` entries of theta), and their Jacobian
    with the noise ``s`` held, from ``measured = (F - L, s, d(F - L)/d theta)`` (:func:`_measured`)."""
    f, s, jac = measured
    return (_with_priors(theta, mask * f / s, n),
            jnp.concatenate([mask[:, None] * jac / s[:, None], jnp.eye(theta.shape[0])[theta.shape[0] - n:]]))


def _measured(theta, prob: Problem, model: Model, width: int):
    """``F - L``, the effective noise std ``s_eff`` and ``d(F - L)/d theta`` of ``model`` at the padded
    ``theta`` (its first ``width`` entries are the model's; the padding's columns are zero), from one batched
    forward pass: a tangent per entry of theta, then one per reading (top current, bottom current, position)."""
    r = prob.readings

    def force(th, it, ib, x):
        return force_misfit(th[:width], prob.with_readings(it, ib, x), model)

    p, n = theta.shape[0], r.x.shape[0]
    basis = jnp.concatenate([jnp.eye(p), jnp.zeros((3, p))])
    rows = [jnp.zeros((p + 3, n)).at[p + k].set(1.0) for k in range(3)]
    f, d = jax.vmap(lambda *t: jax.jvp(force, (theta, r.i_top, r.i_bottom, r.x), t), out_axes=(None, 1))(
        basis, *rows)
    dt, db, dx = d[:, p], d[:, p + 1], d[:, p + 2]
    return f, _effective_noise(prob, dt, db, dx), d[:, :p]


def _edm(theta, measured, prob, n: int):
    """Estimated distance to the minimum, the Jacobian it was computed from, the same Jacobian with every row at
    weight 1 (held-out rows too: what studentized residuals and leverages need) and ``(F - L) / s_eff``, from
    ``measured = (F - L, s_eff, d(F - L)/d theta)`` at ``theta`` (:func:`_measured`); ``n``: the priors' rows."""
    # the Jacobian with the noise held at the solution's, every row at weight 1; the mask multiplies each row's
    # residual and the weights are held: its rows scale likewise
    r, j = _weighted(theta, measured, prob.mask, n)
    j_all = _weighted(theta, measured, jnp.ones_like(prob.mask), n)[1]
    f, s, _ = measured
    return _distance(j, r), j, j_all, f / s


def _damped_step(jac, r, step_size):
    """The Levenberg-Marquardt step from ``(J, r)``: the least-squares solution of ``[J; sqrt(1/step_size) I] x =
    [r; 0]`` by QR (optimistix's ``DampedNewtonDescent`` with lineax's QR; the step is ``-x``)."""
    ok = step_size > jnp.finfo(step_size.dtype).eps
    damping = jnp.where(ok, 1.0 / jnp.where(ok, step_size, 1.0), jnp.finfo(step_size.dtype).max)
    p = jac.shape[1]
    q, upper = jnp.linalg.qr(jnp.concatenate([jac, jnp.sqrt(damping) * jnp.eye(p)]), mode="reduced")
    return jax.scipy.linalg.solve_triangular(upper, q.T @ jnp.concatenate([r, jnp.zeros(p)]), lower=False)


def _distance(jac, r):
    """``g^T (J^T J)^-1 g`` with ``g = J^T r``: the χ² a full Gauss-Newton step would still gain.  Held parameters
    (k without a known load, loads of held-out groups) have zero columns: unit diagonal, zero gradient; a singular
    ``J^T J`` otherwise gives inf/nan, i.e. "not converged", and the identifiability checks then say why."""
    g, h = jac.T @ r, jac.T @ jac
    return g @ jnp.linalg.solve(h + jnp.diag(jnp.where(jnp.diag(h) == 0, 1.0, 0.0)), g)


def _cauchy(y, y_diff, f, f_diff):
    """Optimistix's Cauchy termination: both the step and the change of the residuals are small (max norm)."""
    y_done = jnp.max(jnp.abs(y_diff) / (RTOL + RTOL * jnp.abs(y))) < 1
    return y_done & (jnp.max(jnp.abs(f_diff) / (RTOL + RTOL * jnp.abs(f))) < 1)


@eqx.filter_jit
def _solve_in(theta0, prob, models, index, budget):
    """``REWEIGHTINGS`` rounds of Levenberg-Marquardt, then the measurements at the solution.

    The iteration is optimistix's ``LevenbergMarquardt`` written out (damped Newton steps with step size
    ``1/lambda``, its ``ClassicalTrustRegion``: accept when the loss falls by 1 % of the predicted reduction,
    step size x3.5 above 99 %, x0.25 on rejection; Cauchy termination at ``rtol = atol = RTOL``; its first step
    evaluates the start), plus a stop of ours when the round's EDM is below :data:`EDM_ROUND`, with the
    effective-variance weights held within a round and at most ``budget`` steps per round (a traced number: every budget runs the same compiled solve).  Written out so that one place in
    the program evaluates the model (force, noise and Jacobian, :func:`_measured`): a round's start, each trial
    point and the solution.  Each place the models are traced and compiled again, and a cold diagnosis is
    dominated by compiling (optimistix added a second, its linearization).
    """
    n = max(m.n for m in models)
    p = theta0.shape[0]
    branches = [lambda th, m=m: _measured(th, prob, m, p - n + m.n) for m in models]

    def measure(theta):
        return branches[0](theta) if len(models) == 1 else jax.lax.switch(index, branches, theta)

    def body(c):
        f, s_now, jf = measure(c["y_eval"])
        start, final = c["start"], c["start"] & (c["round"] == REWEIGHTINGS)
        s = jnp.where(start, s_now, c["s"])                  # a round holds the weights of its start
        r_e, j_e = _weighted(c["y_eval"], (f, s, jf), prob.mask, n)
        # the trust region (a round's start is always accepted, its step size reset to 1)
        r, y = jnp.where(start, 0.0, c["r"]), jnp.where(start, c["y_eval"], c["y"])
        loss_diff = 0.5 * (r_e @ r_e - r @ r)
        predicted = 0.5 * (jnp.sum((c["jac"] @ (c["y_eval"] - y) + r) ** 2) - r @ r)
        accept = start | (loss_diff <= 0.01 * predicted)
        good = ~start & (loss_diff < 0.99 * predicted) & (predicted < 0)
        step_size = jnp.where(start, 1.0, jnp.where(accept, jnp.where(good, 3.5, 1.0), 0.25) * c["step_size"])
        done = accept & _cauchy(c["y_eval"], c["y_eval"] - y, r_e, r_e - r)
        y, r, jac = (jnp.where(accept, new, old) for new, old in ((c["y_eval"], y), (r_e, r), (j_e, c["jac"])))
        done = done | (accept & (_distance(jac, r) < EDM_ROUND))
        steps = jnp.where(start, 1, c["steps"] + 1)
        over = done | (steps >= budget)
        return {"y": y, "r": r, "jac": jac, "s": s, "step_size": step_size, "steps": steps,
                "y_eval": jnp.where(over, y, y - _damped_step(jac, r, step_size)),
                "start": over, "round": c["round"] + over.astype(int), "total": c["total"] + jnp.where(final, 0, 1),
                "result": optx.RESULTS.where(over & ~final, optx.RESULTS.where(done, optx.RESULTS.successful,
                                                                       optx.RESULTS.nonlinear_max_steps_reached),
                                             c["result"]),
                # the loop ends after the measurement at the solution: the last one is the solution's
                "final": final, "at": (f, s_now, jf)}

    blank = jax.tree_util.tree_map(lambda a: jnp.zeros(a.shape, a.dtype), jax.eval_shape(measure, theta0))
    m = blank[0].shape[0] + n
    init = {"y": theta0, "r": jnp.zeros(m), "jac": jnp.zeros((m, p)), "s": blank[1], "step_size": jnp.asarray(1.0),
            "steps": jnp.asarray(0), "y_eval": theta0, "start": jnp.asarray(True), "round": jnp.asarray(0),
            "total": jnp.asarray(0), "result": optx.RESULTS.successful, "final": jnp.asarray(False), "at": blank}
    c = jax.lax.while_loop(lambda c: ~c["final"], body, init)
    edm, j, j_all, z = _edm(c["y"], c["at"], prob, n)
    return c["y"], c["result"], c["total"], edm, j, j_all, z


def _solve(theta0, prob, model, max_steps):
    """The solve of ``model`` (in its set, see :func:`compiled_together`), cut back to the model's own entries.

    Called with concrete values, the padding and the cutting are done in NumPy (each eager JAX operation is a
    dispatch, and a diagnosis solves a hundred times); under ``jit`` or ``vmap`` in JAX."""
    models, index = _members(model)
    pad = max(m.n for m in models) - model.n
    xp = jnp if isinstance(theta0, jax.core.Tracer) else np
    if pad:
        theta0 = xp.concatenate([xp.asarray(theta0), xp.zeros(pad)])
    theta, result, steps, edm, j, j_all, z = _solve_in(theta0, prob, models, jnp.asarray(index),
                                                         jnp.asarray(max_steps))
    if xp is np:
        theta, steps, edm, j, j_all, z = (np.asarray(a) for a in (theta, steps, edm, j, j_all, z))
    if pad:
        width, rows = theta.shape[-1] - pad, j.shape[-2] - pad
        theta, j, j_all = theta[..., :width], j[..., :rows, :width], j_all[..., :rows, :width]
    return theta, result, steps, edm, j, j_all, z


def solve(theta0, prob: Problem, model: Model = IDEAL, max_steps: int = FIRST_STEPS):
    """Levenberg-Marquardt from ``theta0``; returns ``(theta, result, num_steps, edm)`` (jit- and vmap-safe).

    ``REWEIGHTINGS`` rounds with the effective-variance weights held fixed, at most ``max_steps`` steps each
    (a traced number: every budget runs the same compiled solve); ``num_steps`` counts the steps of all
    rounds; ``result`` is the last round's (``successful`` when the Cauchy test or :data:`EDM_ROUND` stopped it,
    else ``nonlinear_max_steps_reached``, as optimistix names them); ``edm`` decides convergence (see ``EDM_MAX``).
    """
    return _solve(theta0, prob, model, max_steps)[:4]


def solve_and_measure(theta0, prob: Problem, model: Model = IDEAL, max_steps: int = FIRST_STEPS,
                      every_row: bool = False):
    """:func:`solve`, plus the Jacobian of :func:`residuals` and the standardized residuals of every row at the
    solution: ``(theta, result, num_steps, edm, jacobian, z)``, and with ``every_row`` the Jacobian with every
    row at weight 1 as a seventh entry (a single fit's outlier test and leverages need it).  One compiled
    function per model, or per set of models within :func:`compiled_together` (the diagnosis fits dozens of
    models, and compile time dominates there)."""
    theta, result, steps, edm, j, j_all, z = _solve(theta0, prob, model, max_steps)
    out = theta, result, steps, edm, j, z
    return out + (j_all,) if every_row else out


@eqx.filter_jit
def jacobian(theta, prob: Problem, model: Model = IDEAL):
    """Jacobian ``d r / d theta`` of :func:`residuals` [rows + effect priors, params] (scaled parameters)."""
    return _weighted(theta, _measured(theta, prob, model, theta.shape[0]), prob.mask, model.n)[1]


@eqx.filter_jit
def _unit_force(theta, prob: Problem, model: Model):
    """The model's force with k = 1 on every row."""
    p = unpack(theta, prob, model)
    return _force(BearingParams(p.params.g0, p.params.x0, jnp.ones(2)), p.effects, prob, model)


def seed_loads_and_k(theta, prob: Problem, model: Model = IDEAL):
    """``theta`` with k (from the known loads) and the nuisance loads set to their best values at its gap and origin."""
    a = np.asarray(prob.ax)
    unit = np.asarray(_unit_force(jnp.asarray(theta), prob, model))
    known, load, gidx = np.asarray(prob.known), np.asarray(prob.load), np.asarray(prob.gidx)
    mask = np.asarray(prob.mask) > 0
    theta = np.array(theta)
    for ax in range(2):
        sel = known & (a == ax) & mask
        if sel.any() and np.sum(unit[sel] ** 2) > 0:
            theta[4 + ax] = np.sum(load[sel] * unit[sel]) / np.sum(unit[sel] ** 2) / SCALE_HEAD[4]
    k_used = np.where(np.asarray(prob.k_free), theta[4:6] * SCALE_HEAD[4], K_REFERENCE)
    for j in range(prob.n_loads):
        sel = gidx == j
        theta[6 + j] = float(np.mean(k_used[a[sel]] * unit[sel])) / SCALE_LOAD
    return theta


def free_mask(prob: Problem, meta: Meta, model: Model = IDEAL) -> np.ndarray:
    """Which entries of theta are estimated: gap/origin of present axes, k where loads are known, loads, effects."""
    p = meta.axes_present
    return np.array([p[0], p[1], p[0], p[1], meta.k_free[0] and p[0], meta.k_free[1] and p[1]]
                    + [True] * (prob.n_loads + model.n))


def row_jacobian(theta, prob: Problem, meta: Meta, model: Model = IDEAL) -> np.ndarray:
    """Jacobian of every row's standardized residual at weight 1 (held-out rows too), free columns only: what
    leverages and the discrepancy's projection need (a fit measures it with its solve: ``FitResult.jacobian_rows``)."""
    ones = prob.with_mask(np.ones(len(prob.mask)))
    return np.asarray(jacobian(jnp.asarray(theta), ones, model))[: len(prob.mask)][:, free_mask(prob, meta, model)]


def free_names(meta: Meta, free: np.ndarray, model: Model = IDEAL) -> list[str]:
    """Names of the estimated entries of theta: head parameters, ``load[<group>]``, then ``effect.field[axis]``."""
    every = list(HEAD_NAMES) + [f"load[{g}]" for g in meta.load_groups] + model.names()
    return [n for n, f in zip(every, free) if f]


def si_scale(prob: Problem, model: Model = IDEAL) -> tuple[np.ndarray, np.ndarray]:
    """``(scale, offset)`` so that SI values are ``offset + scale * theta`` for every entry."""
    n_loads = prob.n_loads
    scale = np.concatenate([param_scale(n_loads), np.asarray(model.width)])
    offset = np.concatenate([np.zeros(6 + n_loads), np.asarray(model.centre)])
    return scale, offset
