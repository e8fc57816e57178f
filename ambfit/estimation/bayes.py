"""Posterior of the bearing parameters: emcee sampling, ArviZ diagnostics.

Likelihood: the effective-variance model of :mod:`ambfit.estimation.core` as a proper
density of the force misfits, ``(F - L) ~ N(0, s_eff(theta)^2)`` per reading.
Priors (:class:`Prior`) have physical support: gap > 0, ``|origin| < gap``,
``k > 0``, weakly informative by default and centred on a nominal rig when one is
given.  The log-density is jitted and vectorised over walkers (emcee's
``vectorize=True``).

Several *independent* ensembles are run (R-hat across the walkers of one ensemble
is not valid: they are coupled by the stretch move).  Each ensemble's burn-in and
thinning come from its integrated autocorrelation time ``tau``; a run shorter than
``min_tau_multiple * tau`` is flagged with the length it should have had.  ArviZ
sees one chain per ensemble (its thinned walkers pooled), so R-hat compares
independent ensembles.

Reference: Foreman-Mackey et al., PASP 125, 306 (2013) (emcee, autocorrelation
guidance in its documentation: run for at least 50 tau).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pandas as pd

from ambfit.data import Dataset
from ambfit.estimation.core import (
    IDEAL,
    K_REFERENCE,
    Model,
    Problem,
    build_problem,
    free_mask,
    free_names,
    misfit,
    param_scale,
    to_theta,
    unpack,
)
from ambfit.estimation.ensembles import (
    PHASE,
    BlockStretchMove,
    Tally,
    advance,
    block_chain,
    check_settings,
    run_until_settled,
)
from ambfit.estimation.ensembles import SettingError as SettingError  # (what sample raises on bad settings)
from ambfit.estimation.fit import FitResult, fit
from ambfit.estimation.units import CONTRACT_PARAMS, DISPLAY, display, like, pm, si_unit
from ambfit.physics.bearing import PAPER_BEARING, Bearing


@dataclasses.dataclass(frozen=True)
class Prior:
    """Weakly informative priors with physical support (SI units).

    Gap: log-normal around ``gap`` with log-sd ``gap_log_sd`` (default: the paper's
    762 µm nominal, a factor e^0.3 ≈ 1.35 either way at 1 sd); origin: normal
    ``N(0, origin_sd)`` truncated to ``|origin| < gap``; k: log-normal around ``k``
    with log-sd ``k_log_sd``; nuisance loads: ``N(0, load_sd)``.
    """

    gap: float = PAPER_BEARING.nominal_gap
    gap_log_sd: float = 0.3
    origin_sd: float = 200e-6
    k: float = K_REFERENCE
    k_log_sd: float = 1.0
    load_sd: float = 100.0

    @classmethod
    def from_bearing(cls, bearing: Bearing, **kw) -> Prior:
        """The default weak prior centred on a bearing description: its nominal gap and its nominal ``k``."""
        return cls(gap=bearing.nominal_gap, k=bearing.force_constant(), **kw)

    @classmethod
    def from_rig(cls, spec, gap_rel_sd: float = 0.05, origin_sd: float = 100e-6, k_rel_sd: float = 0.2) -> Prior:
        """A prior from a rig's nominal geometry: nominal gap and force constant with relative spreads."""
        return cls(gap=spec.nominal_gap, gap_log_sd=gap_rel_sd, origin_sd=origin_sd, k=spec.force_constant,
                   k_log_sd=k_rel_sd)

    def sample(self, rng: np.random.Generator, n: int = 1) -> dict:
        """Draws ``{g0: [n,2], x0: [n,2], k: [n,2]}`` (for simulation-based calibration)."""
        g = self.gap * np.exp(self.gap_log_sd * rng.standard_normal((n, 2)))
        x = self.origin_sd * rng.standard_normal((n, 2))
        k = self.k * np.exp(self.k_log_sd * rng.standard_normal((n, 2)))
        return {"g0": g, "x0": x, "k": k}


class LogDensity(eqx.Module):
    """Jitted log-density over the free entries of the scaled parameter vector."""

    prob: Problem
    theta_ref: jnp.ndarray
    free_idx: jnp.ndarray
    prior: Prior = eqx.field(static=True)
    model: Model = IDEAL

    def full(self, z):
        return self.theta_ref.at[self.free_idx].set(z)

    def pointwise(self, z):
        """Log-likelihood of each reading [n]."""
        f, s = misfit(self.full(z), self.prob, self.model)
        return -0.5 * (f / s) ** 2 - jnp.log(s) - 0.5 * jnp.log(2 * jnp.pi)

    def log_prior(self, z):
        u = unpack(self.full(z), self.prob, self.model)
        g0, x0, k, loads = u.params.g0, u.params.x0, u.params.k, u.loads
        p = self.prior
        ok = jnp.all(g0 > 0) & jnp.all(jnp.abs(x0) < g0) & jnp.all(k > 0)
        lp = -0.5 * jnp.sum((jnp.log(jnp.abs(g0) / p.gap) / p.gap_log_sd) ** 2) - jnp.sum(jnp.log(jnp.abs(g0)))
        lp += -0.5 * jnp.sum((x0 / p.origin_sd) ** 2)
        # k only where it is free (held entries are constant and cancel)
        kterm = -0.5 * (jnp.log(jnp.abs(k) / p.k) / p.k_log_sd) ** 2 - jnp.log(jnp.abs(k))
        lp += jnp.sum(jnp.where(self.prob.k_free, kterm, 0.0))
        lp += -0.5 * jnp.sum((loads / p.load_sd) ** 2)
        return jnp.where(ok, lp, -jnp.inf)

    def __call__(self, z):
        lp = self.log_prior(z)
        return jnp.where(jnp.isfinite(lp), lp + jnp.sum(self.pointwise(z)), -jnp.inf)


class CompiledLogDensity:
    """``post`` vectorised over walkers (``zs [n, p] -> [n]``, NumPy in and out), compiled once ahead of time for
    batches of ``batch`` walkers (a larger call goes in chunks, a smaller one padded) and called without the jit
    wrapper's per-call dispatch: the sampler calls it tens of thousands of times, where that dispatch costs more
    than the density, and one compiled shape serves the start and both halves of every step."""

    def __init__(self, post: LogDensity, batch: int):
        self.arrays, static = eqx.partition(post, eqx.is_array)
        self._jit = jax.jit(lambda arrays, zs: jax.vmap(eqx.combine(arrays, static))(zs))
        self.batch = int(batch)
        self._run = None

    def __call__(self, zs) -> np.ndarray:
        zs = np.ascontiguousarray(zs, dtype=np.float64)
        n, b = len(zs), self.batch
        padded = np.concatenate([zs, np.repeat(zs[-1:], -n % b, axis=0)]) if n % b else zs
        if self._run is None:
            self._run = self._jit.lower(self.arrays, padded[:b]).compile()
        out = [np.asarray(self._run(self.arrays, padded[i:i + b])) for i in range(0, len(padded), b)]
        return np.concatenate(out)[:n]


@eqx.filter_jit
def _pointwise_batch(post: LogDensity, zs):
    return jax.vmap(post.pointwise)(zs)


N_STEPS = 3000
"""Steps per ensemble a posterior starts with (:func:`sample`; extended until 50 autocorrelation times)."""
MAX_STEPS = 30_000
"""Cap on the steps per ensemble (:func:`sample`)."""

DISAGREEMENT_SD = 2.0
"""Posterior sd between the posterior mean and the least-squares estimate beyond which they are said to disagree
(:meth:`Posterior.agreement`)."""


@dataclasses.dataclass(frozen=True)
class Posterior:
    """Draws and diagnostics of several independent chains: emcee ensembles (:func:`sample`) or NUTS chains
    (:func:`ambfit.estimation.nuts.sample_nuts`).

    Attributes
    ----------
    names : list[str]
        Parameter names, as :attr:`FitResult.names <ambfit.estimation.results.FitResult.names>`.
    draws : array[n_ensembles, n_draws, p]
        Thinned post-burn-in draws in SI units (:attr:`units`: m, N·m²/A², N), walkers pooled per ensemble;
        :meth:`value` and :meth:`error` are their mean and sd, comparable with ``FitResult.value``.
    tau : array[n_ensembles, p]
        Integrated autocorrelation time of each ensemble or chain [steps of emcee, draws of NUTS].
    burn, thin : int
    n_steps, n_walkers : int
    too_short : bool
        Whether any ensemble or chain ran for fewer than ``min_tau_multiple * tau`` steps (draws).
    message : str
        What the diagnostics say, and how long to run if too short.
    datatree :
        ArviZ DataTree (posterior, log_likelihood, sample_stats, observed_data) in the units people read and the
        contract JSON uses (:data:`ambfit.estimation.units.DISPLAY`): gaps and origins in µm, ``k`` in N·m²/A²,
        loads in N.  Every variable states its unit in its ``units`` attribute
        (``datatree.posterior["g_v0"].attrs["units"] == "µm"``), which the NetCDF file keeps.
    ls : FitResult
        The least-squares fit the ensembles started from.
    sampler : str
        ``"emcee"`` (ensembles of walkers, :func:`sample`) or ``"nuts"`` (BlackJAX's No-U-Turn sampler, one chain per
        "ensemble" and ``n_walkers`` 1, :func:`ambfit.estimation.nuts.sample_nuts`).
    divergent : int
        NUTS' divergent transitions after the warm-up (0 for emcee): where the sampler could not follow the
        posterior; a posterior with any is not converged.
    """

    names: list
    draws: np.ndarray
    tau: np.ndarray
    burn: int
    thin: int
    n_steps: int
    n_walkers: int
    too_short: bool
    message: str
    datatree: object
    ls: FitResult
    acceptance: np.ndarray
    sampler: str = "emcee"
    divergent: int = 0

    def to_dataframe(self, ci_prob: float = 0.94):
        """ArviZ summary (mean, sd, HDI, ESS, R-hat across ensembles) in the reported units, unrounded."""
        import arviz as az

        return az.summary(self.datatree, ci_prob=ci_prob, ci_kind="hdi", round_to="none")

    def value(self, name: str) -> float:
        """Posterior mean of ``name`` in SI units (:attr:`units`), as ``FitResult.value``."""
        return float(np.mean(self.draws[..., self.names.index(name)]))

    def error(self, name: str) -> float:
        """Posterior standard deviation of ``name`` in SI units (:attr:`units`), as ``FitResult.error``."""
        return float(np.std(self.draws[..., self.names.index(name)], ddof=1))

    @property
    def units(self) -> dict:
        """The unit of :attr:`draws`, :meth:`value` and :meth:`error` per parameter: ``{"g_v0": "m", ...}`` (the
        DataTree's are in each variable's ``units`` attribute)."""
        return {n: si_unit(n) for n in self.names}

    @property
    def converged(self) -> bool:
        """Long enough for its autocorrelation time and R-hat below 1.01 across the ensembles (see :meth:`to_json`)."""
        return bool(self.to_json()["converged"])

    def display_rows(self, ci_prob: float = 0.94) -> list[dict]:
        """One ``{column: text}`` row per head parameter: mean ± sd and the HDI to the precision the sd justifies,
        R-hat to 3 decimals, ESS as a whole number."""
        pct = f"{ci_prob * 100:g} % HDI"
        return [{"parameter": n, "mean ± sd": v, pct: h, "R-hat": r, "ESS bulk": e}
                for n, v, h, r, e in self._lines(ci_prob)]

    def _lines(self, ci_prob: float = 0.94) -> list[tuple[str, str, str, str, str]]:
        """``(name, mean ± sd, HDI, R-hat, ESS)`` texts per head parameter, to the precision the sd justifies."""
        rec = self.to_json(ci_prob)["params"]
        out = []
        for name, key, _ in CONTRACT_PARAMS:
            if key not in rec:
                continue
            p = rec[key]
            text = pm(p["value"], p["std"])
            hdi = like(p["value"], p["std"], p["hdi_low"]) + " … " + like(p["value"], p["std"], p["hdi_high"])
            out.append((f"{name} [{DISPLAY[name][0]}]", text, hdi, f"{p['r_hat']:.3f}", f"{p['ess_bulk']:.0f}"))
        return out

    def summary(self, ci_prob: float = 0.94) -> str:
        """A short text summary: posterior mean ± sd, HDI, R-hat and ESS per parameter, and the run's verdict."""
        head = (f"posterior ({self.draws.shape[0]} ensembles x {self.n_walkers} walkers x {self.n_steps} steps)"
                if self.sampler == "emcee" else
                f"posterior ({self.draws.shape[0]} {self.sampler} chains x {self.n_steps} draws after {self.burn} "
                "warm-up steps)")
        rows = [f"  {n:<22} {v:<22} {int(ci_prob * 100)} % HDI {h:<26} R-hat {r}, ESS {e}"
                for n, v, h, r, e in self._lines(ci_prob)]
        return "\n".join([head, *rows, self.message])

    __str__ = summary

    def __repr__(self) -> str:
        return f"Posterior(names={self.names}, n_steps={self.n_steps}, too_short={self.too_short})"

    def _repr_html_(self) -> str:
        import html

        rows = self.display_rows()
        head = "".join(f"<th>{html.escape(c)}</th>" for c in rows[0]) if rows else ""
        body = "".join("<tr>" + "".join(f"<td>{html.escape(v)}</td>" for v in r.values()) + "</tr>" for r in rows)
        return (f"<b>posterior</b><table><tr>{head}</tr>{body}</table><p>{html.escape(self.message)}</p>")

    def agreement(self, threshold: float = DISAGREEMENT_SD) -> dict:
        """How far the posterior mean of each head parameter sits from the least-squares estimate it started from,
        in posterior sd: ``{"z": {name: z}, "threshold", "disagrees": [names beyond it], "text"}`` (``text`` is
        empty when they agree).  On data the model fits, with a prior the data overwhelm, the two agree to a small
        fraction of an sd; beyond ``threshold`` one of them is not to be read as it stands."""
        z = {}
        for name, _, _ in CONTRACT_PARAMS:
            if name in self.names and name in self.ls.names:
                z[name] = (self.value(name) - self.ls.value(name)) / self.error(name)
        bad = [n for n, v in z.items() if abs(v) > threshold]
        text = ""
        if bad:
            why = (f"the model does not fit these data (χ²/dof {self.ls.reduced_chi2:.3g}), so neither the "
                   "least-squares errors nor the posterior can be taken as they stand"
                   if self.ls.adequate is False else
                   "the posterior is not the Gaussian the least-squares errors assume (a curved valley, a bound "
                   "of the prior, or a prior the data do not overwhelm): read the pair plot")
            text = (f"posterior and least squares disagree beyond {threshold:g} sd on "
                    + ", ".join(f"{n} ({z[n]:+.1f} sd)" for n in bad) + f": {why}")
        return {"z": z, "threshold": threshold, "disagrees": bad, "text": text}

    def to_json(self, ci_prob: float = 0.94, rhat_max: float = 1.01) -> dict:
        """Contract section 2 record with ``"method": "bayes"`` (µm, N m²/A²); converged when the run was long
        enough for its autocorrelation time and R-hat across the ensembles is below ``rhat_max`` everywhere."""
        import arviz as az

        post = self.datatree.posterior
        hdi = az.hdi(self.datatree, prob=ci_prob)
        ess = az.ess(self.datatree, method="bulk")
        rhat = az.rhat(self.datatree)
        params = {}
        for name, key, _ in CONTRACT_PARAMS:
            if name in post:
                v = np.asarray(post[name])
                lo, hi = (float(a) for a in np.asarray(hdi[name]).ravel()[:2])
                params[key] = {"value": float(v.mean()), "std": float(v.std(ddof=1)), "hdi_low": lo, "hdi_high": hi,
                               "r_hat": float(rhat[name]), "ess_bulk": float(ess[name])}
        return {"method": "bayes", "sampler": self.sampler, "params": params, "converged": not self.too_short
                and self.divergent == 0 and bool(all(p["r_hat"] < rhat_max for p in params.values())),
                "divergent_transitions": self.divergent, "n_rows": self.ls.n_rows,
            "n_ensembles": int(self.draws.shape[0]), "n_walkers": self.n_walkers, "n_steps": self.n_steps,
            "burn": self.burn, "thin": self.thin, "tau_max": float(np.max(self.tau)), "message": self.message,
            "hdi_prob": ci_prob, "rhat_max": rhat_max, "least_squares_agreement": self.agreement()}


@dataclasses.dataclass(frozen=True)
class Target:
    """What a sampler needs of one data set: the log-density ``post`` over the scaled free parameters ``z``
    (``theta = z * scale``), the least-squares fit ``ls`` with its optimum ``z_hat`` and the Cholesky factor
    ``chol`` of its covariance in ``z``, the parameter ``names`` and the readings ``df``."""

    post: LogDensity
    names: list
    scale: np.ndarray
    z_hat: np.ndarray
    chol: np.ndarray
    ls: FitResult
    df: pd.DataFrame

    @property
    def ndim(self) -> int:
        return len(self.names)

    @classmethod
    def of(cls, data, prior: Prior | None, bearing: Bearing, ls: FitResult | None, fit_kw: dict) -> Target:
        prior = prior if prior is not None else Prior.from_bearing(bearing)
        df = data.frame if isinstance(data, Dataset) else data
        ls = ls or fit(df, bearing=bearing, **({"debias": "none"} | fit_kw))
        prob, meta = build_problem(df, sigma_i=fit_kw.get("sigma_i"), sigma_x=fit_kw.get("sigma_x"))
        free = free_mask(prob, meta)
        scale = param_scale(prob.n_loads)
        theta_hat = np.zeros(len(free))
        theta_hat[free] = ls.values / scale[free]
        theta_hat[~free] = to_theta(bearing.nominal_gap, 0.0, K_REFERENCE, np.zeros(prob.n_loads))[~free]
        post = LogDensity(prob=prob, theta_ref=jnp.asarray(theta_hat), free_idx=jnp.asarray(np.nonzero(free)[0]),
                          prior=prior, model=Model.of((), bearing))
        cov_z = ls.cov / np.outer(scale[free], scale[free])
        chol = np.linalg.cholesky(cov_z + 1e-300 * np.eye(int(free.sum())))
        return cls(post, free_names(meta, free), scale[free], theta_hat[free], chol, ls, df)


def sample(data: Dataset | pd.DataFrame, *, prior: Prior | None = None, n_ensembles: int = 4, n_walkers: int | None = None,
           n_steps: int = N_STEPS, max_steps: int = MAX_STEPS, min_tau_multiple: float = 50.0, seed: int = 0,
           progress: Callable[[str, int, int | None], None] | None = None, bearing: Bearing = PAPER_BEARING,
           ls: FitResult | None = None, **fit_kw) -> Posterior:
    """Sample the posterior with ``n_ensembles`` independent emcee ensembles, long enough for their autocorrelation.

    Each ensemble starts in a small Gaussian ball (0.1 sd of the least-squares
    covariance) around the least-squares optimum and runs ``n_steps`` steps; while the run is
    shorter than ``min_tau_multiple`` times the largest integrated autocorrelation time (or,
    once extended, tau still moves by more than ``ensembles.TAU_TOLERANCE``), every ensemble is extended
    to what the current tau asks for, up to ``max_steps``.  The draws are burned in by
    ``2 max(tau)`` and thinned by ``max(tau) / 2``.  ``prior`` defaults to
    :meth:`Prior.from_bearing` of ``bearing``.  A run that hits ``max_steps`` is marked
    ``too_short`` and its message says how long it should be.  Raises :class:`SettingError` for settings that
    cannot work (``max_steps < n_steps``, fewer walkers than twice the parameters, chains over the memory bound).

    ``progress``, if given, is called as ``progress(f"{PHASE}: <what runs>", done, total)`` with the steps done
    and planned over all ensembles (``total`` grows when the run is extended); nothing is drawn otherwise (the
    command line turns the calls into one labelled bar).
    """
    import emcee

    if progress is not None and not callable(progress):
        raise TypeError(f"progress must be a callback progress(what, done, total) or None, not {progress!r}")
    check_settings(n_ensembles=n_ensembles, n_steps=n_steps, max_steps=max_steps)

    target = Target.of(data, prior, bearing, ls, fit_kw)
    post, names, ndim, chol, ls, df = target.post, target.names, target.ndim, target.chol, target.ls, target.df
    n_walkers = n_walkers or max(64, 4 * ndim)
    check_settings(n_ensembles=n_ensembles, n_steps=n_steps, max_steps=max_steps, n_walkers=n_walkers, names=names)
    rng = np.random.default_rng(seed)

    tally = Tally(progress, n_ensembles * n_steps)
    # the ensembles run in lockstep as one emcee sampler whose stretch move keeps them apart (BlockStretchMove)
    p0 = target.z_hat + 0.1 * rng.standard_normal((n_ensembles * n_walkers, ndim)) @ chol.T
    # (a half-step moves half of each ensemble's walkers: at most ceil(n_walkers / 2) per ensemble)
    half = n_ensembles * -(-n_walkers // 2)
    sampler = emcee.EnsembleSampler(n_ensembles * n_walkers, ndim, CompiledLogDensity(post, half), vectorize=True,
                                    moves=BlockStretchMove(n_ensembles))
    sampler.random_state = np.random.RandomState(int(rng.integers(2**31))).get_state()  # reproducible
    advance(sampler, p0, n_steps, tally, f"{PHASE}: {n_ensembles} in lockstep", n_ensembles)
    steps, tau, settled = run_until_settled(sampler, n_ensembles, n_steps, max_steps, min_tau_multiple, tally)
    tmax = float(np.max(tau))
    burn = int(np.ceil(2 * tmax))
    thin = max(1, int(tmax / 2))
    too_short = not (steps >= min_tau_multiple * tmax and settled)
    message = (f"autocorrelation time up to {tmax:.1f} steps; {steps} steps per ensemble"
               + (f" ({steps - n_steps} added to reach {min_tau_multiple:g} tau)" if steps > n_steps else "")
               + (f" is too short and the cap of {max_steps} steps was reached: run at least "
                  f"{int(np.ceil(min_tau_multiple * tmax))} steps (--max-mcmc-steps) for a reliable tau and ESS"
                  if too_short else f" is {steps / tmax:.0f} tau (>= {min_tau_multiple:g})"))
    accs = sampler.acceptance_fraction.reshape(n_ensembles, n_walkers).mean(axis=1)
    draws_z = block_chain(sampler, n_ensembles)[:, burn::thin].reshape(n_ensembles, -1, ndim)  # [ens, draws, p]
    draws = draws_z * target.scale
    dt = datatree(names, draws, post, draws_z, df, tau, accs)
    return Posterior(names=names, draws=draws, tau=tau, burn=burn, thin=thin, n_steps=steps, n_walkers=n_walkers,
                     too_short=bool(too_short), message=message, datatree=dt, ls=ls, acceptance=accs)


OBSERVED_UNITS = {"i_top_A": "A", "i_bottom_A": "A", "v_um": "µm", "w_um": "µm"}
"""The observed_data group's variables (contract columns) and their units."""


def tree_name(name: str) -> str:
    """A parameter's variable name in the DataTree: ``load[rotor]`` becomes ``load_rotor``."""
    return name.replace("[", "_").replace("]", "").replace("|", "_")


def datatree(names, draws, post, draws_z, df, tau, acc, stats: dict | None = None):
    """The DataTree of draws ``[chains, draws, p]``; ``stats``: more ``sample_stats`` of that shape."""
    import arviz as az

    ens, nd, p = draws.shape
    posterior = {tree_name(n): draws[:, :, j] * display(n, 1.0)[0] for j, n in enumerate(names)}
    ll = np.asarray(_pointwise_batch(post, jnp.asarray(draws_z.reshape(-1, p)))).reshape(ens, nd, -1)
    lp = ll.sum(axis=-1)
    observed = {c: df[c].to_numpy(float) for c in OBSERVED_UNITS}
    dt = az.from_dict(
        {"posterior": posterior, "log_likelihood": {"reading": ll}, "sample_stats": {"lp": lp, **(stats or {})},
         "observed_data": observed},
        dims={"reading": ["row"], **{c: ["row"] for c in observed}},
        attrs={"posterior": {"units": "gaps and origins in µm, k in N m²/A², loads in N",
                             "tau_max": float(np.max(tau)), "acceptance": float(np.mean(acc))}},
    )
    for n in names:
        dt.posterior[tree_name(n)].attrs["units"] = display(n, 1.0)[1]
    for c, unit in OBSERVED_UNITS.items():
        dt.observed_data[c].attrs["units"] = unit
    return dt


def force_predictive(result: Posterior, axis: str, i_top, i_bottom, x, *, sigma_i: float = 0.0,
                     sigma_x: float = 0.0, seed: int = 0) -> dict:
    """Posterior predictive force [N] on ``axis`` for given currents [A] and position [m]: mean, sd and the 3 % and
    97 % quantiles (a 94 % equal-tailed interval).

    Parameter uncertainty comes from the draws; reading noise (``sigma_i``, ``sigma_x``) is added per draw.
    """
    from ambfit.physics.model import ideal_force

    need = (f"g_{axis}0", f"{axis}0", f"k_{axis}")
    if need[2] not in result.names:
        raise ValueError(f"the force on axis {axis} needs k_{axis}, which these data do not identify (no known load)")
    idx = [result.names.index(n) for n in need]
    d = result.draws.reshape(-1, result.draws.shape[-1])[:, idx]
    rng = np.random.default_rng(seed)
    it, ib, xx = (np.atleast_1d(np.asarray(v, dtype=float)) for v in (i_top, i_bottom, x))
    n = d.shape[0]
    it_s = it[None, :] + sigma_i * rng.standard_normal((n, it.size))
    ib_s = ib[None, :] + sigma_i * rng.standard_normal((n, ib.size))
    x_s = xx[None, :] + sigma_x * rng.standard_normal((n, xx.size))
    f = np.asarray(ideal_force(d[:, :1], d[:, 1:2], d[:, 2:3], it_s, ib_s, x_s, result.ls.bearing.cos_alpha))
    lo, hi = np.quantile(f, [0.03, 0.97], axis=0)
    return {"mean": f.mean(axis=0), "sd": f.std(axis=0, ddof=1), "q03": lo, "q97": hi}
