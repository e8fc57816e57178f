"""The fitted model extended by unmodelled effects (the same classes the rig uses as truth).

An extension is a tuple of :mod:`ambfit.effects` objects whose ``RANGES`` fields
become free parameters next to gap, origin, k and the nuisance loads.  The force is
:func:`ambfit.model.evaluate` with those effects; the residuals are effective-variance
residuals as in :mod:`ambfit.likelihood`, with the derivatives of the force with
respect to the readings taken by automatic differentiation.  Each effect parameter
has a weak Gaussian prior (centre and width from its ``RANGES``; zero-centred for
signed ones) added as a residual, so an effect the data cannot see stays at its
prior instead of wandering.
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

from ambfit import data as data_mod
from ambfit.effects import Effect
from ambfit.likelihood import (
    EDM_MAX, K_REFERENCE, build_problem, free_mask, free_names, param_scale, seed_loads_and_k, to_theta,
)
from ambfit.model import ALPHA_DEFAULT, BearingParams, Readings, evaluate


class ExtProblem(eqx.Module):
    """A data set's arrays for the extended model (SI units)."""

    readings: Readings
    s_top: jnp.ndarray
    s_bottom: jnp.ndarray
    s_x: jnp.ndarray
    load: jnp.ndarray
    known: jnp.ndarray
    gidx: jnp.ndarray
    k_free: jnp.ndarray
    mask: jnp.ndarray      # 1 for rows the fit uses, 0 for held-out rows (same shapes for every fold)


def ext_problem(df: pd.DataFrame, mask=None, **noise) -> tuple[ExtProblem, object]:
    prob, meta = build_problem(df, **noise)
    r = data_mod.readings(df)
    m = jnp.ones(len(df)) if mask is None else jnp.asarray(mask, dtype=float)
    return ExtProblem(readings=r, s_top=prob.s_top, s_bottom=prob.s_bottom, s_x=prob.s_x, load=prob.load,
                      known=prob.known, gidx=prob.gidx, k_free=prob.k_free, mask=m), (prob, meta)


class EffectSpec(eqx.Module):
    """Which fields of which effects are free, with their prior centres and widths (SI units)."""

    effects: tuple
    fields: tuple = eqx.field(static=True)   # ((effect index, field name), ...), each a (2,) per-axis parameter
    centre: jnp.ndarray = None                # [n_fields * 2]
    width: jnp.ndarray = None

    @classmethod
    def of(cls, effects: Sequence[Effect]) -> EffectSpec:
        fields, centre, width = [], [], []
        for i, e in enumerate(effects):
            for name, (lo, hi) in type(e).RANGES.items():
                if lo == hi:
                    continue
                fields.append((i, name))
                signed = name in type(e).SIGNED
                c = 0.0 if signed else 0.5 * (lo + hi)
                wd = hi if signed else max(hi - lo, 1e-12)
                centre += [c, c]
                width += [wd, wd]
        return cls(tuple(effects), tuple(fields), jnp.asarray(centre, dtype=float).reshape(-1),
                   jnp.asarray(width, dtype=float).reshape(-1))

    @property
    def n(self) -> int:
        return int(self.centre.shape[0])

    def names(self) -> list[str]:
        return [f"{type(self.effects[i]).name}.{f}[{ax}]" for i, f in self.fields for ax in ("v", "w")]

    def build(self, q):
        """Effects with their free fields set from the scaled vector ``q`` (value = centre + width * q)."""
        vals = self.centre + self.width * q
        effects = list(self.effects)
        for j, (i, f) in enumerate(self.fields):
            effects[i] = eqx.tree_at(lambda e, f=f: getattr(e, f), effects[i], vals[2 * j:2 * j + 2])
        return tuple(effects)


def _ext_misfit(theta, q, prob: ExtProblem, spec: EffectSpec, alpha, turns):
    sc = param_scale(theta.shape[0] - 6)
    g0, x0 = theta[0:2] * sc[0], theta[2:4] * sc[2]
    k = jnp.where(prob.k_free, theta[4:6] * sc[4], K_REFERENCE)
    loads = theta[6:] * sc[6:] if theta.shape[0] > 6 else jnp.zeros(0)
    params = BearingParams(g0, x0, k)
    effects = spec.build(q)
    r = prob.readings

    def force(it, ib, x):
        rr = eqx.tree_at(lambda z: (z.i_top, z.i_bottom, z.x), r, (it, ib, x))
        return evaluate(params, rr, effects, alpha=alpha, turns=turns)[0]

    f = force(r.i_top, r.i_bottom, r.x)
    ones, zeros = jnp.ones_like(r.x), jnp.zeros_like(r.x)
    dt = jax.jvp(force, (r.i_top, r.i_bottom, r.x), (ones, zeros, zeros))[1]
    db = jax.jvp(force, (r.i_top, r.i_bottom, r.x), (zeros, ones, zeros))[1]
    dx = jax.jvp(force, (r.i_top, r.i_bottom, r.x), (zeros, zeros, ones))[1]
    s = jnp.sqrt((dt * prob.s_top) ** 2 + (db * prob.s_bottom) ** 2 + (dx * prob.s_x) ** 2)
    nuisance = loads[jnp.maximum(prob.gidx, 0)] if loads.shape[0] else jnp.zeros_like(f)
    target = jnp.where(prob.known, prob.load, nuisance)
    return f - target, s


def _residual_fn(z, args):
    prob, spec, alpha, turns, s, n_theta = args
    theta, q = z[:n_theta], z[n_theta:]
    f, _ = _ext_misfit(theta, q, prob, spec, alpha, turns)
    return jnp.concatenate([prob.mask * f / s, q])          # prior residuals: q ~ N(0, 1)


@eqx.filter_jit
def _solve(z0, prob, spec, alpha, turns, max_steps):
    n_theta = z0.shape[0] - spec.n

    def round_(_, carry):
        z, _ = carry
        s = _ext_misfit(z[:n_theta], z[n_theta:], prob, spec, alpha, turns)[1]
        sol = optx.least_squares(_residual_fn, optx.LevenbergMarquardt(1e-8, 1e-8), z,
                                 args=(prob, spec, alpha, turns, s, n_theta), max_steps=max_steps, throw=False)
        return sol.value, sol.result

    z, result = jax.lax.fori_loop(0, 2, round_, (z0, optx.RESULTS.successful))
    s = _ext_misfit(z[:n_theta], z[n_theta:], prob, spec, alpha, turns)[1]
    args = (prob, spec, alpha, turns, s, n_theta)
    j = jax.jacfwd(_residual_fn)(z, args)
    r = _residual_fn(z, args)
    g = j.T @ r
    h = j.T @ j
    h = h + jnp.diag(jnp.where(jnp.diag(h) == 0, 1.0, 0.0))
    return z, result, g @ jnp.linalg.solve(h, g), _ext_misfit(z[:n_theta], z[n_theta:], prob, spec, alpha, turns), j


@dataclasses.dataclass(frozen=True)
class ExtendedFit:
    """An extended fit: parameters (SI), the effects at their fitted values, standardized residuals."""

    names: list
    values: np.ndarray
    effects: tuple
    residuals: np.ndarray      # standardized residuals of every row (held-out rows included)
    std: np.ndarray            # standard errors of ``values`` (priors included), SI units
    converged: bool
    theta: np.ndarray
    spec: EffectSpec


def fit_extended(data: pd.DataFrame, effects: Sequence[Effect] = (), *, turns: float = 480.0,
                 alpha: float = ALPHA_DEFAULT, start=None, max_steps: int = 60, mask=None, **noise) -> ExtendedFit:
    """Least squares of gap, origin, k, loads and the free effect parameters (see the module docstring).

    ``start``: a baseline :class:`ambfit.fit.FitResult` to start from (default: fit the data).
    ``mask``: 1 for rows to fit, 0 for rows held out (kept in the arrays so every fold compiles once).
    Nuisance loads of groups with no fitted row keep their start value.
    """
    from ambfit.fit import fit as baseline

    df = data.reset_index(drop=True)
    prob, (lprob, meta) = ext_problem(df, mask=mask, **noise)
    spec = EffectSpec.of(effects)
    base = start if start is not None else baseline(df, **noise)
    vals = dict(zip(base.names, base.values))
    g = [vals.get("g_v0", 762e-6), vals.get("g_w0", 762e-6)]
    x = [vals.get("v0", 0.0), vals.get("w0", 0.0)]
    k = [vals.get("k_v", K_REFERENCE), vals.get("k_w", K_REFERENCE)]
    loads = [vals.get(f"load[{grp}]", 0.0) for grp in meta.load_groups]
    theta = to_theta(np.array(g), np.array(x), np.array(k), np.array(loads))
    if not loads:
        theta = seed_loads_and_k(theta, lprob, alpha)
    z0 = np.concatenate([theta, np.zeros(spec.n)])
    z, result, edm, (f, s), jac = _solve(jnp.asarray(z0), prob, spec, float(alpha), float(turns), max_steps)
    z = np.asarray(z)
    n_theta = len(theta)
    free = free_mask(lprob, meta)
    head_names = free_names(meta, free)
    sc = param_scale(lprob.n_loads)
    values = np.concatenate([z[:n_theta][free] * sc[free], np.asarray(spec.centre + spec.width * z[n_theta:])])
    keep = np.concatenate([free, np.ones(spec.n, bool)])
    jk = np.asarray(jac)[:, keep]
    scale = np.concatenate([sc[free], np.asarray(spec.width)])
    std = np.sqrt(np.abs(np.diag(np.linalg.pinv(jk.T @ jk)))) * scale
    return ExtendedFit(names=head_names + spec.names(), values=values, effects=spec.build(jnp.asarray(z[n_theta:])),
                       residuals=np.asarray(f) / np.asarray(s), std=std, converged=bool(float(edm) < EDM_MAX * 100),
                       theta=z, spec=spec)


def heldout_residuals(fitted: ExtendedFit, data: pd.DataFrame, test: np.ndarray) -> np.ndarray:
    """Standardized residuals of the ``test`` rows (bool mask) under a fit that held them out.

    A nuisance load that no training row constrained is refitted on the test rows alone
    (its weighted mean misfit is removed, one number per group): the held-out check is
    about the shape of the force law, not about an unknown load the training data never saw.
    """
    from ambfit.data import load_groups

    z = fitted.residuals.copy()
    groups = load_groups(data.reset_index(drop=True)).to_numpy()
    known = data["load_N"].notna().to_numpy() if "load_N" in data else np.zeros(len(data), bool)
    for g in np.unique(groups[test & ~known]):
        m = groups == g
        if not np.any(m & ~test):
            zz = z[m & test]
            z[m & test] = zz - zz.mean()
    return z[test]
