"""``ambfit identify`` and ``ambfit sample``: least squares, the paper's closed form, the posterior."""

from __future__ import annotations

import sys
from enum import Enum
from pathlib import Path
from typing import Annotated

import typer

from ambfit.faces.cli.app import (
    AcceptOption,
    BearingOption,
    app,
    bearing_of,
    check_output,
    console,
    enable_compilation_cache,
    fail,
    judge,
    note,
    read_data,
    show_table,
    warn,
    write_json,
)


class Method(str, Enum):
    least_squares = "least-squares"
    closed_form = "closed-form"


class Loss(str, Enum):
    auto = "auto"
    linear = "linear"
    huber = "huber"
    cauchy = "cauchy"


def drop_duplicates(ds, name: str, keep: bool):
    """Name exact duplicate readings; unless ``keep``, count each once.  Returns ``(dataset, dropped rows)``."""
    from ambfit.data import Dataset, duplicate_rows

    dupes = duplicate_rows(ds.frame)
    if not dupes:
        return ds, []
    listed = ", ".join(f"{r} repeats {f}" for r, f in dupes[:8]) + (" ..." if len(dupes) > 8 else "")
    if keep:
        warn(f"{name}: {len(dupes)} exact duplicate reading(s) kept (--keep-duplicates): rows {listed}; each "
             "counts twice and the error bars are too small (up to sqrt(2) when every row repeats)")
        return ds, []
    drop = [r - 1 for r, _ in dupes]
    frame = ds.frame.drop(index=ds.frame.index[drop])
    warn(f"{name}: {len(dupes)} exact duplicate reading(s) counted once (rows {listed}); a repeated reading is a "
         "copy, not a new measurement, and would shrink the error bars (--keep-duplicates counts them)")
    return Dataset(frame=frame, source=ds.source), drop


def _duplicate_effect(original, record: dict, bearing, loss: str) -> float | None:
    """How much smaller the gap's error bar would be with the duplicates counted (a fit of the full file)."""
    from ambfit.estimation import fit

    try:
        with_dupes = fit.fit(original, bearing=bearing, loss=loss, throw=False)
    except fit.FitError:
        return None
    std, dup = record["params"]["g_v0_um"]["std"], with_dupes.error("g_v0") * 1e6
    note(f"counted as often as they appear, the duplicates would shrink the error bars {std / dup:.2f} x "
         f"(g_v0 ± {dup:.3g} µm instead of ± {std:.3g} µm)")
    return std / dup


class By(str, Enum):
    none = "none"
    experiment = "experiment"


@app.command()
def check(
    data: Annotated[Path, typer.Argument(help="Perturbation data, contract CSV (see ambfit/docs/data-format.md).")],
    max_position_um: Annotated[float | None, typer.Option(help="Positions at least this large [µm] are flagged "
                                                          "(default: the bearing's nominal gap).")] = None,
    bearing: BearingOption = None,
):
    """List every problem of a data file at once (row, column, value, why), and exact duplicate readings.

    Exits 2 when the file has problems, 0 when it is ready for identify.
    """
    from ambfit.data import duplicate_rows, inspect, read_csv

    desc = bearing_of(bearing)
    limit = max_position_um or desc.nominal_gap * 1e6
    problems = inspect(data, max_position_um=limit)
    if problems:
        show_table([{"row": "" if e.row is None else str(e.row), "column": e.column or "",
                     "value": "" if e.value is None else repr(e.value), "problem": e.reason} for e in problems],
                   f"{data}: {len(problems)} problem(s)", left=("column", "value", "problem"))
        raise typer.Exit(2)
    ds = read_csv(data, max_position_um=limit)
    df = ds.frame
    dupes = duplicate_rows(df)
    for row, first in dupes:
        warn(f"{data}: row {row} repeats row {first} exactly; a repeated reading counts twice and makes the "
             "error bars too small (up to sqrt(2) when every row is repeated)")
    known = int(df["load_N"].notna().sum()) if "load_N" in df else 0
    noise = "std columns" if all(c in df and df[c].notna().all() for c in ("i_top_std_A", "i_bottom_std_A")) \
        else "no current std columns (noise will be estimated from the residuals)"
    note(f"{data}: ok, {len(df)} rows ({', '.join(f'{(df.axis == ax).sum()} {ax}' for ax in ('v', 'w'))}), "
         f"{known} rows with a known load, {noise}; {len(dupes)} duplicate reading(s)")


@app.command()
def identify(
    data: Annotated[Path, typer.Argument(help="Perturbation data, contract CSV.")],
    method: Annotated[Method, typer.Option(help="Estimator: 'least-squares' (all readings, weighted by their "
                                           "propagated noise; k from known loads) or 'closed-form' (the "
                                           "paper's Eq. 5-7 per iteration, averaged).")] = Method.least_squares,
    json_out: Annotated[Path | None, typer.Option("--json", help="Write the contract JSON here.")] = None,
    by: Annotated[By, typer.Option(help="'experiment': one estimate per experiment (like the paper's "
                                   "tables); 'none': one estimate from all rows.")] = By.none,
    current_noise_ma: Annotated[float | None, typer.Option(
        "--current-noise-ma", help="Declared current noise std [mA] (default: the std columns, else "
                                   "estimated from the residuals).")] = None,
    position_noise_um: Annotated[float | None, typer.Option(
        help="Declared position noise std [µm] (default: the std columns, else 0).")] = None,
    require_k: Annotated[bool, typer.Option(help="Fail unless k can be calibrated on every axis "
                                            "(needs known loads).")] = False,
    debias: Annotated[int, typer.Option(help="Subtract the estimator's second-order bias, estimated from this "
                                        "many synthetic data sets of the fitted model (0: off; 2000 is "
                                        "plenty).")] = 0,
    max_position_um: Annotated[float | None, typer.Option(help="Reject positions at least this large [µm] "
                                                          "(unit check; default: the bearing's nominal "
                                                          "gap).")] = None,
    loss: Annotated[Loss, typer.Option(help="'auto': least squares with an outlier test (readings beyond the "
                                       "Bonferroni bound, 1 % false alarms per file, are named and left out); "
                                       "'linear': plain least squares (outliers named, kept); 'huber', 'cauchy': "
                                       "robust losses.")] = Loss.auto,
    keep_duplicates: Annotated[bool, typer.Option(help="Count exact duplicate readings as often as they appear "
                                                  "(default: once, with a warning naming them).")] = False,
    accept_implausible: AcceptOption = False,
    bearing: BearingOption = None,
):
    """Identify effective gap, origin (and k when loads are known) for each axis.

    least-squares: value ± standard error from the fit's covariance; exits 3 with the
    reason when the fit does not converge or the design does not identify the
    parameters.  closed-form: mean over iterations ± standard error of that mean; exits 3
    when its iterations cannot be trusted.  Both exit 3 when the bearing description rules
    the result out (unless --accept-implausible).
    """
    from ambfit.estimation import plausibility

    check_output(json_out)
    enable_compilation_cache()
    desc = bearing_of(bearing)
    ds = read_data(data, desc, accept_implausible, max_position_um)
    original = ds
    ds, dropped = drop_duplicates(ds, data.name, keep_duplicates)
    if method is Method.closed_form:
        record = _identify_closed_form(ds, data.name, by, desc)
    else:
        record = _identify_ls(ds, data.name, by, current_noise_ma, position_noise_um, require_k, debias, desc,
                              loss.value)
        if dropped and "g_v0_um" in record["params"]:
            record["duplicates_error_bar_factor"] = _duplicate_effect(original, record, desc, loss.value)
    record["duplicates_dropped"] = [r + 1 for r in dropped]
    flags = [plausibility.Flag(**f) for f in record.get("implausible", [])]
    if json_out is not None:
        write_json(record, json_out)
    if not record["converged"]:
        raise typer.Exit(3)
    judge(flags, accept_implausible)
    if record.get("trusted") is False:
        raise typer.Exit(3)


def _identify_closed_form(ds, name, by, bearing) -> dict:
    from ambfit.estimation import closed_form, plausibility

    try:
        result = closed_form.identify(ds, by_experiment=by is By.experiment, bearing=bearing)
    except closed_form.ClosedFormError as exc:
        fail(str(exc), 3)
    show_table(result.display_rows(), f"closed form (Eq. 5-7), {name}, {result.n_rows} rows",
               left=("experiment", "axis"))
    for line in result.rejections():
        warn(line)
    for line in result.health():
        warn(line)
    record = result.to_json()
    keys = {e for e, _ in result.estimates}
    record["implausible"] = [f.to_json() for key in sorted(keys) for f in plausibility.check_result(
        {name: est_value for name, est_value in _si_values(result.params(key)).items()}, bearing)]
    if not result.trusted:
        warn("the closed-form result cannot be trusted (see above); ambfit identify exits 3")
    return record


def _si_values(params: dict) -> dict:
    """Contract parameter block -> internal names in SI."""
    from ambfit.estimation.results import CONTRACT_PARAMS

    return {name: params[key]["value"] / f for name, key, f in CONTRACT_PARAMS if key in params}


def _identify_ls(ds, name, by, current_noise_ma, position_noise_um, require_k, debias, bearing, loss) -> dict:
    from ambfit.estimation import fit

    kw = dict(sigma_i=None if current_noise_ma is None else current_noise_ma * 1e-3,
              sigma_x=None if position_noise_um is None else position_noise_um * 1e-6, require_k=require_k,
              debias=debias, bearing=bearing, loss=loss)
    try:
        pooled = fit.fit(ds, **kw)
    except fit.FitError as exc:
        if by is By.none:
            fail(str(exc), 3)
        pooled = exc
    results = fit.fit_by(ds, "experiment", **kw) if by is By.experiment else {"all": pooled}
    show_table([{"experiment": key, **(r.display_row() if not isinstance(r, fit.FitError) else {"g_v0 [µm]": f"failed: {r}"})}
                for key, r in results.items()], f"least squares, {name}, {len(ds)} rows", left=("experiment",))
    if isinstance(pooled, fit.FitError):
        record = {"method": "least_squares", "params": {}, "converged": False, "n_rows": len(ds), "error": str(pooled)}
    else:
        for line in pooled.notes():
            note(line)
        for check, ok, text in pooled.checks():
            if ok is False and check not in ("k_identified", "plausible"):   # plausibility: judge() says it
                warn(text)
        record = pooled.to_json()
    if by is By.experiment:
        record["experiments"] = {k: (r.to_json() if not isinstance(r, fit.FitError) else
                                     {"converged": False, "error": str(r)}) for k, r in results.items()}
        record["converged"] = record["converged"] and all(not isinstance(r, fit.FitError) for r in results.values())
    return record


@app.command()
def sample(
    data: Annotated[Path, typer.Argument(help="Perturbation data, contract CSV.")],
    out: Annotated[Path | None, typer.Option(help="Write the ArviZ DataTree (posterior, log_likelihood, "
                                             "sample_stats, observed_data) as NetCDF here.")] = None,
    json_out: Annotated[Path | None, typer.Option("--json", help="Write the contract JSON (method 'bayes', "
                                                  "94 % HDI, R-hat, ESS) here.")] = None,
    pair_png: Annotated[Path | None, typer.Option(help="Write a pair plot of gap, origin and k here.")] = None,
    steps: Annotated[int, typer.Option(help="Steps per ensemble to start with; each ensemble is extended until "
                                       "the run is 50 autocorrelation times long and tau has settled.")] = 3000,
    max_steps: Annotated[int, typer.Option(help="Cap on the steps per ensemble (exit 3 with the length "
                                           "needed when it is reached).")] = 30000,
    ensembles: Annotated[int, typer.Option(help="Independent emcee ensembles (R-hat compares them).")] = 4,
    walkers: Annotated[int | None, typer.Option(help="Walkers per ensemble (default max(32, 4 x parameters)).")] = None,
    nominal_gap_um: Annotated[float | None, typer.Option(help="Centre the gap prior on this nominal gap [µm] "
                                                          "(log-sd --gap-prior-log-sd).")] = None,
    gap_prior_log_sd: Annotated[float, typer.Option(help="Log-sd of the gap prior [-].")] = 0.3,
    seed: Annotated[int, typer.Option(help="Seed.")] = 0,
    progress: Annotated[bool, typer.Option(help="Show a progress bar.")] = True,
    accept_implausible: AcceptOption = False,
    bearing: BearingOption = None,
):
    """Sample the posterior of gap, origin (and k with known loads) with emcee; summarise with ArviZ.

    Runs until the chains are 50 autocorrelation times long (up to --max-steps); exits 3 when
    the cap is reached (and says how long the run should be) or R-hat across the ensembles
    exceeds 1.01.
    """
    from ambfit.data import DataError
    from ambfit.estimation import bayes, fit

    check_output(out, json_out, pair_png)
    enable_compilation_cache()
    desc = bearing_of(bearing)
    ds = read_data(data, desc, accept_implausible)
    try:
        prior = bayes.Prior.from_bearing(desc.with_(nominal_gap=nominal_gap_um * 1e-6) if nominal_gap_um else desc,
                                         gap_log_sd=gap_prior_log_sd)
        res = bayes.sample(ds, prior=prior, n_ensembles=ensembles, n_walkers=walkers, n_steps=steps,
                           max_steps=max_steps, seed=seed, progress=progress and sys.stderr.isatty(), bearing=desc)
    except DataError as exc:
        fail(str(exc))
    except fit.FitError as exc:
        fail(str(exc), 3)
    note(res.summary())
    record = res.to_json()
    if out is not None:
        res.datatree.to_netcdf(out, engine="h5netcdf")
        console.print(f"wrote {out}")
    if json_out is not None:
        write_json(record, json_out)
    if pair_png is not None:
        from ambfit.faces import plots

        plots.save(plots.plot_pair(res), pair_png)
        console.print(f"wrote {pair_png}")
    if not record["converged"]:
        raise typer.Exit(3)
