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

import functools
from collections.abc import Sequence
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ambfit._arrays import numpy_unless_traced
from ambfit._recent import Recent
from ambfit.estimation.problem import Meta, Problem, build_problem  # noqa: F401  (build_problem: the core's entry)
from ambfit.estimation.units import FORCE_CONSTANTS, GAPS, ORIGINS
from ambfit.physics.bearing import AXES, PAPER_BEARING, Bearing
from ambfit.physics.effects import Effect
from ambfit.physics.model import BearingParams, evaluate, ideal_force

K_REFERENCE = PAPER_BEARING.force_constant()
"""Force constant [N m^2/A^2] held on an axis without known loads (it cancels from gap and origin)."""

# theta = (g_v0, g_w0) / 1 cm, (v0, w0) / 0.1 mm, (k_v, k_w) / 1e-4, loads / 100 N.  The units are coarse
# on purpose: every column of the standardized Jacobian is then >= ~1e3, so Levenberg-Marquardt's
# initial damping (lambda = 1) is negligible and it takes Gauss-Newton steps from a good seed, while
# keeping its trust region for a poor one.  (With units near the parameters' size the weakest
# eigenvalue of J^T J was ~10, and lambda = 1 cost ~8 extra steps per solve.)
SCALE_HEAD = np.array([1e-2, 1e-2, 1e-4, 1e-4, 1e-4, 1e-4])
SCALE_LOAD = 100.0
HEAD_NAMES = GAPS + ORIGINS + FORCE_CONSTANTS
"""The head of theta: gaps, origins, force constants (each pair v, w; :data:`ambfit.estimation.units.HEAD`)."""

EDM_MAX = 1e-6
"""Convergence: the estimated distance to the minimum, ``EDM = r^T J (J^T J)^-1 J^T r`` (the χ² a
full Gauss-Newton step would still gain), must fall below this, i.e. every parameter is within
about 1e-3 standard errors of the optimum (iminuit's criterion).  The solver's own Cauchy test
(:mod:`ambfit.estimation.lm`) is reported too, but near the optimum its trust region rejects steps on round-off
and it can stop late or never while the solution is already exact."""




class FitError(RuntimeError):
    """The fit did not converge or the design does not identify the parameters; the message says why.

    ``result`` is the :class:`~ambfit.estimation.results.FitResult` the fit failed on, when it got that far (as
    emcee's ``AutocorrError`` carries ``tau``): its estimates, health and solver record are there to read, without
    fitting again with ``throw=False``.  None when the fit stopped before it had a result (no readings, too few
    readings for the parameters, a force law that is not finite at the estimate).
    """

    def __init__(self, message: str, result=None):
        super().__init__(message)
        self.result = result


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
    prior centre and width from the effect's ``RANGES`` (zero-centred for signed parameters).  ``n`` is the number
    of free effect parameters (entries of ``q``), counted once from ``fields``.
    """

    effects: tuple
    fields: tuple = eqx.field(static=True)
    centre: jnp.ndarray
    width: jnp.ndarray
    bearing: Bearing = eqx.field(static=True)
    n: int = eqx.field(static=True)

    @classmethod
    def of(cls, effects: Sequence[Effect] = (), bearing: Bearing = PAPER_BEARING, fields: tuple | None = None) -> Model:
        """The model of ``effects`` on ``bearing``, their ``ranges()`` fields free (shared by the two axes where the
        class sets ``SHARED``); or the free ``fields`` given as ``(effect index, field name, shared)``: a model
        file's estimates, which may include a field its class now holds."""
        effects = tuple(effects)
        key = (tuple(map(id, effects)), bearing, fields)
        hit = _MODELS.get(key)
        if hit is not None:
            return hit[1]
        model = cls._of(effects, bearing, fields)
        _MODELS.put(key, (effects, model))      # holding the effects: their identities stay theirs while keyed
        return model

    @classmethod
    def _of(cls, effects: tuple, bearing: Bearing, fields: tuple | None = None) -> Model:
        if fields is None:
            fields = tuple((i, name, getattr(type(e), "SHARED", False)) for i, e in enumerate(effects)
                           for name, (lo, hi) in e.ranges().items() if lo != hi)
        centre, width = [], []
        built = list(effects)
        for i, name, shared in fields:
            e = effects[i]
            lo, hi = (type(e).RANGES | e.ranges())[name]
            # a free field's value comes from q (build): one shape for every instance, so that a model of
            # fitted effects runs the compiled solve of the same model with default ones
            value = getattr(e, name)
            xp = numpy_unless_traced(value)
            built[i] = eqx.tree_at(lambda ef, f=name: getattr(ef, f), built[i],
                                   xp.array(xp.broadcast_to(xp.asarray(value, dtype=float), (2,))))
            signed = name in type(e).SIGNED
            c = 0.0 if signed else 0.5 * (lo + hi)
            wd = hi if signed else max(hi - lo, 1e-12)
            centre += [c] if shared else [c, c]
            width += [wd] if shared else [wd, wd]
        return cls(tuple(built), tuple(fields), np.asarray(centre, dtype=float).reshape(-1),
                   np.asarray(width, dtype=float).reshape(-1), bearing, len(centre))

    def __check_init__(self):
        if self.n != sum(1 if shared else 2 for _, _, shared in self.fields):
            raise ValueError(f"a model of fields {self.fields} has n={self.n}: n counts their free entries")

    @property
    def name(self) -> str:
        """``ideal`` or the effect names joined with ``+`` (contract section 3)."""
        return "+".join(type(e).name for e in self.effects) or "ideal"

    @property
    def flux_width(self) -> int:
        """The width per row of the solve an effect makes (the magnetic circuit's loop fluxes), whose solution
        warm-starts the next evaluation (:func:`measured_from`); 0 without one."""
        return max((type(e).FLUX_WIDTH for e in self.effects), default=0)

    def names(self) -> list[str]:
        """``effect.field[axis]`` per axis, or ``effect.field`` for a field both axes share (one stator)."""
        return list(_names(self.fields, tuple(type(e).name for e in self.effects)))

    def build(self, q) -> tuple:
        """Effects with their free fields set from the scaled vector ``q`` (value = centre + width * q); in NumPy
        when ``q`` is concrete (a fit's result: each eager JAX operation of a new shape compiles a program)."""
        xp = numpy_unless_traced(q, self.centre, self.width)
        vals = xp.asarray(self.centre) + xp.asarray(self.width) * xp.asarray(q)
        effects = list(self.effects)
        j = 0
        for i, f, shared in self.fields:
            v = xp.array(xp.broadcast_to(vals[j:j + 1], (2,))) if shared else vals[j:j + 2]
            effects[i] = eqx.tree_at(lambda e, f=f: getattr(e, f), effects[i], v)
            j += 1 if shared else 2
        return tuple(effects)


@functools.lru_cache(maxsize=256)
def _names(fields: tuple, effect_names: tuple) -> tuple:
    out = []
    for i, f, shared in fields:
        base = f"{effect_names[i]}.{f}"
        out += [base] if shared else [f"{base}[{ax}]" for ax in AXES]
    return tuple(out)


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
    return _misfit_and_flux(theta, prob, model)[0]


def _misfit_and_flux(theta, prob: Problem, model: Model, flux_start=None):
    """:func:`force_misfit` and the solution of the model's solve per row, started from ``flux_start``
    (:meth:`ambfit.physics.stages.Effect.force_and_flux`; None for a model without one)."""
    p = unpack(theta, prob, model)
    force, flux = _force(p.params, p.effects, prob, model, flux_start)
    return force - target(prob, p.loads), flux


def _force(params: BearingParams, effects: tuple, prob: Problem, model: Model, flux_start=None):
    """Each row's force [N] (Eq. 4 for the ideal model, a small program to trace, else the effect pipeline) and its
    solve's solution (None without one)."""
    if not model.effects:
        a, r = prob.ax, prob.readings
        return ideal_force(params.g0[a], params.x0[a], params.k[a], r.i_top, r.i_bottom, r.x,
                           model.bearing.cos_alpha), None
    force, ctx = evaluate(params, prob.readings, effects, bearing=model.bearing, flux_start=flux_start)
    return force, ctx.flux


def measured(theta, prob: Problem, model: Model = IDEAL, width: int | None = None, wrt_theta: bool = True):
    """``F - L`` [N] of every row, its effective noise std ``s_eff`` [N] and, with ``wrt_theta``, ``d(F - L)/d theta``
    [rows, p]: the one place that differentiates the model (:func:`measured_from` without a warm start)."""
    return measured_from(theta, prob, model, width, wrt_theta)[:3]


def measured_from(theta, prob: Problem, model: Model = IDEAL, width: int | None = None, wrt_theta: bool = True,
                  flux_start=None):
    """:func:`measured`, its model's solve per row started from ``flux_start`` (a warm start, e.g. the previous
    point's; :attr:`Model.flux_width` wide), and that solve's solution as a fourth output (None for a model without
    one).  The force does not depend on the start.

    One batched forward pass (``jax.jvp`` under ``vmap``): a tangent per entry of theta (with ``wrt_theta``), then
    one per reading (top current, bottom current, position) for the effective variance.  Forward mode is exact, so
    the ideal law needs no hand-written copy of Eq. 4's derivatives.  ``width``: theta may be padded beyond the
    model's own entries (a set of models compiled together); the padding's columns are zero.
    """
    r = prob.readings
    width = theta.shape[0] if width is None else width

    def force(th, it, ib, x):
        return _misfit_and_flux(th[:width], prob.with_readings(it, ib, x), model, flux_start)

    n = r.x.shape[0]
    p = theta.shape[0] if wrt_theta else 0
    primals = (theta, r.i_top, r.i_bottom, r.x) if wrt_theta else (r.i_top, r.i_bottom, r.x)
    fn = force if wrt_theta else (lambda it, ib, x: force(theta, it, ib, x))
    # tangents: a unit vector per entry of theta (rows 0..p-1), then one per reading (rows p, p+1, p+2)
    readings = [jnp.zeros((p + 3, n)).at[p + k].set(1.0) for k in range(3)]
    tangents = ([jnp.concatenate([jnp.eye(p), jnp.zeros((3, p))])] if wrt_theta else []) + readings
    f, d, flux = jax.vmap(lambda *t: jax.jvp(fn, primals, t, has_aux=True), out_axes=(None, 1, None))(*tangents)
    dt, db, dx = d[:, p], d[:, p + 1], d[:, p + 2]
    return f, _effective_noise(prob, dt, db, dx), d[:, :p], flux


def misfit(theta, prob: Problem, model: Model = IDEAL):
    """Force misfit ``F - L`` [N] of every row and its effective noise std ``s_eff`` [N] (:func:`measured`)."""
    return measured(theta, prob, model, wrt_theta=False)[:2]


def _effective_noise(prob: Problem, dt, db, dx):
    """``s_eff`` from the force's derivatives with respect to the top and bottom currents and the position
    (effective variance), or the problem's held noise where it gives one (:meth:`Problem.with_noise`)."""
    s = jnp.sqrt((dt * prob.s_top) ** 2 + (db * prob.s_bottom) ** 2 + (dx * prob.s_x) ** 2)
    return jnp.where(prob.s_held > 0, prob.s_held, s)


def with_priors(theta, r, n: int):
    """The rows' residuals ``r``, then the priors' of the last ``n`` entries of theta (``q ~ N(0, 1)``)."""
    return jnp.concatenate([r, theta[theta.shape[0] - n:]]) if n else r


def weighted(theta, at, mask, n: int):
    """Residuals ``mask (F - L) / s`` then the effect priors' (the last ``n`` entries of theta), and their Jacobian
    with the noise ``s`` held, from ``at = (F - L, s, d(F - L)/d theta)`` (:func:`measured`)."""
    f, s, jac = at
    return (with_priors(theta, mask * f / s, n),
            jnp.concatenate([mask[:, None] * jac / s[:, None], jnp.eye(theta.shape[0])[theta.shape[0] - n:]]))


def residuals(theta, prob: Problem, model: Model = IDEAL):
    """Standardized residuals of every row (held-out rows masked to 0), then the effect priors' residuals."""
    f, s = misfit(theta, prob, model)
    return with_priors(theta, prob.mask * f / jax.lax.stop_gradient(s), model.n)


@eqx.filter_jit
def noise_std(theta, prob: Problem, model: Model = IDEAL):
    """Each row's effective force noise std ``s_eff`` [N] (:func:`misfit`, compiled once per model)."""
    return misfit(theta, prob, model)[1]


@eqx.filter_jit
def standardized(theta, prob: Problem, model: Model = IDEAL):
    """``(F - L) / s_eff`` of every row, held-out rows included (dimensionless)."""
    f, s = misfit(theta, prob, model)
    return f / s


@eqx.filter_jit
def jacobian(theta, prob: Problem, model: Model = IDEAL):
    """Jacobian ``d r / d theta`` of :func:`residuals` [rows + effect priors, params] (scaled parameters)."""
    return weighted(theta, measured(theta, prob, model), prob.mask, model.n)[1]


def free_mask(prob: Problem, meta: Meta, model: Model = IDEAL) -> np.ndarray:
    """Which entries of theta are estimated: gap/origin of present axes, k where loads are known, loads, effects."""
    p = meta.axes_present
    return np.array([p[0], p[1], p[0], p[1], meta.k_free[0] and p[0], meta.k_free[1] and p[1]]
                    + [True] * (len(meta.load_groups) + model.n))


def _measure_rows(theta, prob: Problem, model: Model):
    """``F - L``, ``s_eff`` and the weight-1 Jacobian of the standardized residual of every row (every column)."""
    f, s, jac = measured(theta, prob, model)
    return f, s, weighted(theta, (f, s, jac), jnp.ones_like(f), model.n)[1][: f.shape[0]]


_rows_measured = eqx.filter_jit(_measure_rows)

measured_sets = eqx.filter_jit(eqx.filter_vmap(_measure_rows, in_axes=(0, 0, None)))
""":func:`rows_measured` of a batch of problems (leading axis of theta and of the problems' leaves; every column of
theta): ``F - L``, ``s_eff`` and the weight-1 Jacobian of every row, with no cut to the free columns."""


def rows_measured(theta, prob: Problem, meta: Meta, model: Model = IDEAL) -> tuple[np.ndarray, ...]:
    """``F - L`` [N], ``s_eff`` [N] and the Jacobian of the standardized residual at weight 1 (free columns) of every
    row, held-out rows too: one compiled program per model and shape (a fit measures all three with its solve:
    ``FitResult.residuals``, ``row_noise``, ``jacobian_rows``)."""
    f, s, jac = (np.asarray(a) for a in _rows_measured(jnp.asarray(theta), prob, model))
    return f, s, jac[:, free_mask(prob, meta, model)]


def row_jacobian(theta, prob: Problem, meta: Meta, model: Model = IDEAL) -> np.ndarray:
    """Jacobian of every row's standardized residual at weight 1 (held-out rows too), free columns only: what
    leverages and the discrepancy's projection need (a fit measures it with its solve: ``FitResult.jacobian_rows``)."""
    return rows_measured(theta, prob, meta, model)[2]


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
