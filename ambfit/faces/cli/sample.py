"""``ambfit sample``: the posterior of gap, origin and k with emcee (or BlackJAX's NUTS), summarised with ArviZ."""

from __future__ import annotations

import enum
from pathlib import Path
from typing import Annotated

import typer

from ambfit._jaxcache import enable_compilation_cache
from ambfit._output import write_bytes
from ambfit.faces.cli.app import (
    AcceptOption,
    BearingOption,
    app,
    bearing_of,
    check_output,
    fail,
    note,
    read_data,
    warn,
    write_json,
)
from ambfit.faces.cli.fitting import CurrentNoiseOption, PositionNoiseOption, declared_noise
from ambfit.faces.cli.options import number

SAMPLER_OPTIONS = {"n_steps": "--mcmc-steps", "max_steps": "--max-mcmc-steps", "n_ensembles": "--ensembles",
                   "n_walkers": "--walkers"}
"""The command line's name of each setting :class:`ambfit.estimation.bayes.SettingError` names."""
MAX_ENSEMBLES = 64
MAX_WALKERS = 1_024
"""Walkers per ensemble: each costs one log-probability per step (and its chain's memory); a thousand is a
hundred times the parameters of the richest model, past any gain in sampling."""
MIN_STEPS = 100
"""Fewest steps to start with: the burn-in alone is two autocorrelation times."""
EMCEE_STEPS, NUTS_DRAWS, MAX_STEPS = 3000, 1000, 30_000
"""--mcmc-steps by sampler (emcee's first run per ensemble, NUTS' draws per chain) and emcee's cap
(--max-mcmc-steps): the library's defaults (``bayes.N_STEPS``, ``nuts.N_DRAWS``, ``bayes.MAX_STEPS``), written
here so that ``--help`` does not import them (a test holds them equal)."""


class Sampler(enum.StrEnum):
    emcee = "emcee"
    nuts = "nuts"


def _add_budget(record: dict, ds, res, noise: dict, seed: int) -> None:
    """The calibration's type-B terms (:mod:`ambfit.estimation.budget`, sensitivities of the least-squares fit
    the sampler started from) combined with each parameter's posterior sd: ``u_combined`` and ``budget``."""
    import arviz as az
    import numpy as np

    from ambfit.estimation.budget import budget
    from ambfit.estimation.units import CONTRACT_PARAMS, DISPLAY

    if not (res.ls.converged and res.ls.well_conditioned):
        return
    b = budget(ds, res.ls, **noise)
    draws = {name: np.asarray(res.datatree.posterior[name], float).ravel() / DISPLAY[name][1]
             for name, _, _ in CONTRACT_PARAMS if name in res.datatree.posterior}          # SI
    sd = {name: float(np.std(x, ddof=1)) for name, x in draws.items()}
    b.merge(record["params"], sd, "posterior sd (type A)")
    # the calibration marginalised: every posterior draw shifted by a calibration error drawn anew (GUM-S1)
    wide = b.propagate(draws, np.random.default_rng(seed))
    for name, key, factor in CONTRACT_PARAMS:
        if name in wide and key in record["params"]:
            lo, hi = (float(v) for v in az.hdi(wide[name] * factor, prob=record["hdi_prob"]))
            record["params"][key].update(hdi_low_combined=lo, hdi_high_combined=hi)
    record["uncertainty_budget"] = b.to_json("the posterior sd") | {
        "hdi_combined": "the posterior with the calibration marginalised: each draw shifted by a calibration "
                        "error drawn anew through the least-squares sensitivities (GUM Supplement 1)"}
    if b.failed:
        warn(b.failed_text())
    note("u_combined (posterior sd with the calibration tolerances): " + ", ".join(
        f"{name} {b.u_combined(name, sd[name]) * DISPLAY[name][1]:.3g} {DISPLAY[name][0]}" for name in sd))


@app.command()
def sample(
    data: Annotated[Path, typer.Argument(help="Perturbation data, contract CSV.")],
    out: Annotated[Path | None, typer.Option(help="Write the ArviZ DataTree (posterior, log_likelihood, "
                                             "sample_stats, observed_data) as NetCDF here.")] = None,
    json_out: Annotated[Path | None, typer.Option("--json", help="Write the contract JSON (method 'bayes', "
                                                  "94 % HDI, R-hat, ESS) here.")] = None,
    pair_png: Annotated[Path | None, typer.Option(help="Write a pair plot of gap, origin and k here.")] = None,
    sampler: Annotated[Sampler, typer.Option(help="'emcee' (independent ensembles of walkers, the field's "
                                             "default) or 'nuts' (BlackJAX's No-U-Turn sampler, one chain per "
                                             "ensemble; needs ambfit[nuts]): the same posterior, a second "
                                             "opinion.")] = Sampler.emcee,
    steps: Annotated[int | None, typer.Option("--mcmc-steps", "--steps", callback=number(MIN_STEPS),
                                              help="emcee: steps per ensemble to start "
                                              f"with (default {EMCEE_STEPS}); each ensemble is extended until the "
                                              "run is 50 autocorrelation times long and tau has settled.  nuts: "
                                              f"draws per chain after as many warm-up steps (default "
                                              f"{NUTS_DRAWS}).")] = None,
    max_steps: Annotated[int | None, typer.Option("--max-mcmc-steps", "--max-steps", callback=number(MIN_STEPS),
                                                  help="emcee: cap on the steps per "
                                                  "ensemble (exit 3 with the length needed when it is reached; "
                                                  f"default {MAX_STEPS}).")] = None,
    ensembles: Annotated[int, typer.Option(callback=number(2, MAX_ENSEMBLES),
                                           help="Independent emcee ensembles or NUTS chains (R-hat compares "
                                           "them).")] = 4,
    walkers: Annotated[int | None, typer.Option(callback=number(2, MAX_WALKERS), help="Walkers per ensemble (default "
                                                "max(64, 4 x parameters); at least twice the parameters).")] = None,
    nominal_gap_um: Annotated[float | None, typer.Option(callback=number(0, low_open=True), help="Centre the gap prior on this nominal gap [µm] "
                                                          "(log-sd --gap-prior-log-sd).")] = None,
    gap_prior_log_sd: Annotated[float, typer.Option(callback=number(0, low_open=True),
                                                    help="Log-sd of the gap prior [-].")] = 0.3,
    seed: Annotated[int, typer.Option(callback=number(0), help="Seed.")] = 0,
    progress: Annotated[bool, typer.Option(help="Show a progress bar (on a terminal): steps of every ensemble, "
                                           "and the extension to 50 autocorrelation times.")] = True,
    current_noise_ma: CurrentNoiseOption = None,
    position_noise_um: PositionNoiseOption = None,
    accept_implausible: AcceptOption = False,
    bearing: BearingOption = None,
):
    """Sample the posterior of gap, origin (and k with known loads) with emcee or NUTS; summarise with ArviZ.

    emcee runs until the chains are 50 autocorrelation times long (up to --max-mcmc-steps); exits 3
    when the cap is reached (and says how long the run should be), when NUTS' chains are shorter
    than 50 autocorrelation times, or when R-hat across the ensembles or chains exceeds 1.01.
    """
    from ambfit.data import DataError
    from ambfit.estimation import bayes, fit
    from ambfit.faces.cli.progress import progress_bar

    check_output(out, json_out, pair_png, inputs=(data, bearing))
    if sampler is Sampler.nuts:
        for option, value in (("--walkers", walkers), ("--max-mcmc-steps", max_steps)):
            if value is not None:
                fail(f"{option} is emcee's; NUTS runs one chain per ensemble for exactly --mcmc-steps draws")
        from ambfit.estimation import nuts

        try:
            nuts._blackjax()
        except nuts.MissingSampler as exc:
            fail(str(exc))
    else:
        steps = steps or EMCEE_STEPS
        max_steps = max_steps or max(MAX_STEPS, steps)
        if max_steps < steps:
            fail(f"--max-mcmc-steps {max_steps}: the cap is below --mcmc-steps {steps}")
    enable_compilation_cache()
    desc = bearing_of(bearing)
    ds = read_data(data, desc, accept_implausible)
    try:
        prior = bayes.Prior.from_bearing(desc.with_(nominal_gap=nominal_gap_um * 1e-6) if nominal_gap_um else desc,
                                         gap_log_sd=gap_prior_log_sd)
        with progress_bar(enabled=None if progress else False) as bar:
            if sampler is Sampler.nuts:
                res = nuts.sample_nuts(ds, prior=prior, n_chains=ensembles, n_warmup=steps or NUTS_DRAWS,
                                       n_draws=steps or NUTS_DRAWS, seed=seed, progress=bar, bearing=desc,
                                       **declared_noise(current_noise_ma, position_noise_um))
            else:
                res = bayes.sample(ds, prior=prior, n_ensembles=ensembles, n_walkers=walkers, n_steps=steps,
                                   max_steps=max_steps, seed=seed, progress=bar, bearing=desc,
                                   **declared_noise(current_noise_ma, position_noise_um))
    except bayes.SettingError as exc:
        fail(f"{SAMPLER_OPTIONS.get(exc.setting, exc.setting)} {exc.value}: {exc.problem}")
    except DataError as exc:
        fail(str(exc))
    except fit.FitError as exc:
        fail(str(exc), 3)
    note(res.summary())
    record = res.to_json()
    from ambfit.faces.warnings import posterior_warnings

    for line in posterior_warnings(res, record):
        warn(line)
    _add_budget(record, ds, res, declared_noise(current_noise_ma, position_noise_um), seed)
    if out is not None:
        # serialised in memory first: HDF5 writing to a full disk fails uncleanly, Python's writes fail cleanly
        write_bytes(out, res.datatree.to_netcdf(engine="h5netcdf"))
        note(f"wrote {out}")
    if json_out is not None:
        from ambfit.estimation.model_file import stamp

        write_json(stamp(record, "sample"), json_out)
    if pair_png is not None:
        from ambfit.faces import plots

        plots.save(plots.plot_pair(res, result=res.ls), pair_png, close=True)
        note(f"wrote {pair_png}")
    if not record["converged"]:
        raise typer.Exit(3)
