"""The posterior by BlackJAX's No-U-Turn sampler: a second sampler beside emcee (:func:`ambfit.estimation.bayes.sample`),
for checking one against the other and for posteriors whose gradient is cheap.

NUTS runs in whitened coordinates ``u`` (``z = z_hat + L u`` with ``L L^T`` the least-squares covariance), where the
posterior is close to a unit normal: Stan's window adaptation regularises the mass matrix towards the identity,
which in the fit's own scales (variances near 1e-10) would swamp it.  Each chain starts from its own unit-normal
draw of ``u``, tunes its step size and dense mass matrix by the window adaptation, then draws.  The chains are
independent, so R-hat across them is valid, as across emcee's ensembles.  Needs the optional extra
``ambfit[nuts]`` (BlackJAX); nothing imports this module unless NUTS is asked for.

Reference: Hoffman & Gelman, JMLR 15, 1593 (2014); Cabezas et al., "BlackJAX" (2024).
"""

from __future__ import annotations

from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ambfit.estimation.bayes import Posterior, Prior, Target, datatree
from ambfit.estimation.ensembles import SettingError, integrated_time
from ambfit.physics.bearing import PAPER_BEARING, Bearing

EXTRA = "pip install 'ambfit[nuts]'"
"""How to get BlackJAX."""


class MissingSampler(ImportError):
    """NUTS was asked for without BlackJAX installed."""


def _blackjax():
    try:
        import blackjax
    except ImportError as exc:
        raise MissingSampler(f"the NUTS sampler needs BlackJAX, which is not installed ({EXTRA})") from exc
    return blackjax


class Whitened(eqx.Module):
    """The log-density of ``u`` with ``z = z_hat + chol @ u`` (a constant Jacobian)."""

    post: eqx.Module
    z_hat: jnp.ndarray
    chol: jnp.ndarray

    def z(self, u):
        return self.z_hat + self.chol @ u

    def __call__(self, u):
        return self.post(self.z(u))


@eqx.filter_jit
def _chain(logdensity: Whitened, key, u0, n_warmup: int, n_draws: int, target_accept: float):
    """One chain: window adaptation from ``u0``, then ``n_draws`` NUTS transitions; the draws in ``z``."""
    blackjax = _blackjax()
    warmup = blackjax.window_adaptation(blackjax.nuts, logdensity, is_mass_matrix_diagonal=False,
                                        target_acceptance_rate=target_accept)
    k_warm, k_draw = jax.random.split(key)
    (state, params), _ = warmup.run(k_warm, u0, num_steps=n_warmup)
    step = blackjax.nuts(logdensity, **params).step

    def one(state, k):
        state, info = step(k, state)
        return state, (logdensity.z(state.position), info.acceptance_rate, info.is_divergent,
                       info.num_integration_steps)

    _, out = jax.lax.scan(one, state, jax.random.split(k_draw, n_draws))
    return out, params["step_size"]


N_DRAWS = 1000
"""Draws per chain, and warm-up steps before them, of :func:`sample_nuts` by default."""


def sample_nuts(data, *, prior: Prior | None = None, n_chains: int = 4, n_warmup: int = N_DRAWS, n_draws: int = N_DRAWS,
                target_accept: float = 0.8, min_tau_multiple: float = 50.0, seed: int = 0,
                progress: Callable[[str, int, int | None], None] | None = None, bearing: Bearing = PAPER_BEARING,
                ls=None, **fit_kw) -> Posterior:
    """The posterior of :func:`ambfit.estimation.bayes.sample` (same likelihood, prior and result) drawn by
    ``n_chains`` independent NUTS chains of ``n_draws`` draws after ``n_warmup`` adaptation steps.

    ``too_short`` when a chain is shorter than ``min_tau_multiple`` integrated autocorrelation times (as emcee's
    rule); divergent transitions after the warm-up are counted in the message and in the DataTree's
    ``sample_stats.diverging``.  ``progress(what, done, total)`` is called after each chain (chains done of
    ``n_chains``).  Raises :class:`MissingSampler` without BlackJAX and
    :class:`~ambfit.estimation.ensembles.SettingError` for settings below one.
    """
    _blackjax()
    for name, value in (("n_chains", n_chains), ("n_warmup", n_warmup), ("n_draws", n_draws)):
        if value < 1:
            raise SettingError(name, value, "must be at least 1")
    target = Target.of(data, prior, bearing, ls, fit_kw)
    post, ndim = target.post, target.ndim
    logdensity = Whitened(post, jnp.asarray(target.z_hat), jnp.asarray(target.chol))
    rng = np.random.default_rng(seed)
    what = f"posterior draws, NUTS: {n_chains} chains of {n_warmup} warm-up steps and {n_draws} draws"
    if progress is not None:
        progress(what, 0, n_chains)
    chains, accept, diverging, leapfrogs, step_sizes = [], [], [], [], []
    for c in range(n_chains):
        u0 = np.zeros(ndim)
        for _ in range(100):          # a start one posterior sd out, inside the prior's support
            trial = rng.standard_normal(ndim)
            if np.isfinite(float(logdensity(jnp.asarray(trial)))):
                u0 = trial
                break
        key = jax.random.PRNGKey(int(rng.integers(2**31)))
        (z, acc, div, n_leap), step = _chain(logdensity, key, jnp.asarray(u0), n_warmup, n_draws, target_accept)
        chains.append(np.asarray(z))
        accept.append(np.asarray(acc))
        diverging.append(np.asarray(div))
        leapfrogs.append(np.asarray(n_leap))
        step_sizes.append(float(step))
        if progress is not None:
            progress(what, c + 1, n_chains)
    draws_z = np.stack(chains)                                               # [chains, draws, p]
    tau = np.array([integrated_time(z[:, None, :]) for z in draws_z])
    tmax = float(np.max(tau))
    too_short = n_draws < min_tau_multiple * tmax
    n_div = int(np.sum(diverging))
    message = (f"NUTS: autocorrelation time up to {tmax:.2f} draws; {n_draws} draws per chain "
               + (f"is too short: run at least {int(np.ceil(min_tau_multiple * tmax))} draws" if too_short else
                  f"is {n_draws / tmax:.0f} tau (>= {min_tau_multiple:g})")
               + f"; step size {min(step_sizes):.3g}-{max(step_sizes):.3g}, {np.mean(leapfrogs):.1f} leapfrog steps "
               f"per draw; {n_div} divergent transition(s)"
               + (" (the sampler could not follow the posterior there: compare with emcee)" if n_div else ""))
    acceptance = np.array([a.mean() for a in accept])
    dt = datatree(target.names, draws_z * target.scale, post, draws_z, target.df, tau, acceptance,
                   {"diverging": np.stack(diverging), "acceptance_rate": np.stack(accept),
                    "n_steps": np.stack(leapfrogs)})
    return Posterior(names=target.names, draws=draws_z * target.scale, tau=tau, burn=n_warmup, thin=1,
                     n_steps=n_draws, n_walkers=1, too_short=bool(too_short), message=message, datatree=dt,
                     ls=target.ls, acceptance=acceptance, sampler="nuts", divergent=n_div)
