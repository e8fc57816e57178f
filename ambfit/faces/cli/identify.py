"""``ambfit check`` and ``ambfit identify``: a data file's problems; least squares or the paper's closed form.

One data set is identified here; several files or ``--by`` groups by
:mod:`~ambfit.faces.cli.groups`; what both do for every data set is :mod:`~ambfit.faces.cli.fitting`.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Annotated

import typer

from ambfit._jaxcache import enable_compilation_cache
from ambfit.faces.cli.app import (
    AcceptOption,
    BearingOption,
    app,
    bearing_of,
    check_output,
    fail,
    judge,
    note,
    read_data,
    show_table,
    warn,
    write_json,
)
from ambfit.faces.cli.fitting import (
    CurrentNoiseOption,
    Loss,
    Method,
    PositionNoiseOption,
    _closed_form_record,
    _duplicate_effect,
    _Options,
    _status,
    _table_row,
    _warn_health,
    _write_table,
    checked_closed_form,
    drop_duplicates,
)
from ambfit.faces.cli.groups import _expand, _identify_groups
from ambfit.faces.cli.options import debias_choice, number

MAX_DEBIAS = 100_000
"""Most synthetic data sets for --debias N (2000 are plenty; each is a fit)."""
MAX_WORKERS = 4 * (os.cpu_count() or 1)
"""Most local worker processes: beyond a few per core they only contend for it."""


@app.command()
def check(
    data: Annotated[Path, typer.Argument(help="Perturbation data, contract CSV (see ambfit/docs/data-format.md).")],
    max_position_um: Annotated[float | None, typer.Option(callback=number(0, low_open=True),
                                                          help="Positions at least this large [µm] are flagged "
                                                          "(default: the bearing's nominal gap).")] = None,
    bearing: BearingOption = None,
):
    """List every problem of a data file at once (row, column, value, why), and duplicate readings.

    Besides the contract's checks, every column is judged against the bearing description (--bearing): currents
    beyond the coil limit (mA for A?), loads beyond what the bearing can lift, positions too small to be µm
    (metres?) or spread beyond the back-up clearance, the same checks identify makes.  Exits 2 when the file has
    problems, 0 when it is ready for identify.
    """
    from ambfit.data import duplicate_rows, inspect, read_csv
    from ambfit.estimation import plausibility

    desc = bearing_of(bearing)
    limit = max_position_um or desc.nominal_gap * 1e6
    problems = inspect(data, max_position_um=limit)
    rows = [{"row": "" if e.row is None else str(e.row), "column": e.column or "",
             "value": "" if e.value is None else repr(e.value), "problem": e.reason} for e in problems]
    if not problems:
        ds = read_csv(data, max_position_um=limit)
        rows = [{"row": str(f.row), "column": f.column, "value": repr(f.value),
                 "problem": f"implausible for the bearing {desc.name!r} ({f.expected}): {f.cause}"}
                for f in plausibility.check_data(ds.frame, desc, str(data))]
    if rows:
        show_table(rows, f"{data}: {len(rows)} problem(s)", left=("column", "value", "problem"))
        raise typer.Exit(2)
    for line in ds.notes:
        note(line)
    df = ds.frame
    dupes = duplicate_rows(df)
    for row, first in dupes:
        warn(f"{data}: row {row} repeats row {first} (the same labels, every number within 10 µA and 1 nm); a "
             "repeated reading counts twice and makes the error bars too small (up to sqrt(2) when every row is "
             "repeated)")
    known = int(df["load_N"].notna().sum()) if "load_N" in df else 0
    noise = "std columns" if all(c in df and df[c].notna().all() for c in ("i_top_std_A", "i_bottom_std_A")) \
        else "no current std columns (noise will be estimated from the residuals)"
    note(f"{data}: ok, {len(df)} rows ({', '.join(f'{(df.axis == ax).sum()} {ax}' for ax in ('v', 'w'))}), "
         f"{known} rows with a known load, {noise}; {len(dupes)} duplicate reading(s)")


@app.command()
def identify(
    data: Annotated[list[Path], typer.Argument(help="Perturbation data, contract CSV: one or more files or quoted "
                                               "globs ('runs/*.csv'); with several, one estimate per file.")],
    method: Annotated[Method, typer.Option(help="Estimator: 'least-squares' (all readings, weighted by their "
                                           "propagated noise; k from known loads) or 'closed-form' (the "
                                           "paper's Eq. 5-7 per iteration, averaged).")] = Method.least_squares,
    json_out: Annotated[Path | None, typer.Option("--json", help="Write the contract JSON here (with several "
                                                  "files or --by: one entry per group under 'groups').")] = None,
    by: Annotated[str, typer.Option(metavar="COLUMN", help="Split each file by this column, one estimate per value: "
                                    "'experiment' (like the paper's tables) or any other column ('bearing', "
                                    "'date', ...); 'none': one estimate per file.")] = "none",
    table: Annotated[Path | None, typer.Option("--table", help="Write one row per group (file, or file and --by "
                                               "value) as CSV here: estimates and standard errors [µm, N·m²/A²], "
                                               "χ²/dof, health, outliers, plausibility, error.")] = None,
    pooled: Annotated[bool, typer.Option("--pooled", help="With several files or --by: also fit all rows together "
                                         "(the 'pooled' entry; a file's unknown loads stay its own). Off by "
                                         "default: a pooled fit of different bearings or runs is neither.")] = False,
    current_noise_ma: CurrentNoiseOption = None,
    position_noise_um: PositionNoiseOption = None,
    require_k: Annotated[bool, typer.Option(help="Fail unless k can be calibrated on every axis "
                                            "(needs known loads).")] = False,
    debias: Annotated[str, typer.Option(metavar="second-order|none|N", callback=debias_choice(MAX_DEBIAS),
                                        help="The estimator's bias of second order in the noise, subtracted from "
                                        "the estimate: 'second-order' by the delta method (costs less than the "
                                        "fit); N: from N synthetic data sets of the fitted ideal law (a "
                                        "parametric bootstrap; 2000 are plenty); 'none': the plain least-squares "
                                        "estimate.")] = "second-order",
    max_position_um: Annotated[float | None, typer.Option(callback=number(0, low_open=True),
                                                          help="Reject positions at least this large [µm] "
                                                          "(unit check; default: the bearing's nominal "
                                                          "gap).")] = None,
    loss: Annotated[Loss, typer.Option(help="'auto': least squares with an outlier test (readings beyond the "
                                       "Bonferroni bound, 1 % false alarms per file, are named and left out); "
                                       "'linear': plain least squares (outliers named, kept); 'huber', 'cauchy': "
                                       "robust losses.")] = Loss.auto,
    keep_duplicates: Annotated[bool, typer.Option(help="Count duplicate readings as often as they appear "
                                                  "(default: once, with a warning naming them).")] = False,
    force_check: Annotated[bool, typer.Option(help="With two or more distinct known loads: leave each out, fit the "
                                              "rest, and compare the force predicted for its readings with it "
                                              "(contract force_check).")] = True,
    effect: Annotated[list[str] | None, typer.Option("--effect", metavar="NAME", help="Fit this unmodelled effect "
                                                  "with the ideal law, its parameters estimated (repeatable; e.g. "
                                                  "magnetic_circuit with a bearing description that has a B-H curve, "
                                                  "saturation); the model JSON then carries it for ambfit force.")] = None,
    discrepancy: Annotated[bool, typer.Option("--discrepancy", help="Also fit the model-discrepancy term (a smooth "
                                              "correction orthogonal to every fitted parameter) and add it to the "
                                              "model JSON for ambfit force.")] = False,
    fit_current_zeros: Annotated[bool, typer.Option(help="When the current channels' zeros (the bearing's "
                                                    "current_offset_tolerance_mA) dominate an error bar and the "
                                                    "readings determine them (several biases), fit them "
                                                    "(current_offset) and report that fit, saying so; "
                                                    "--no-fit-current-zeros keeps the ideal law and only "
                                                    "advises.  One data set, least squares without --debias N "
                                                    "or --effect (several files and --by groups get no "
                                                    "budget).")] = True,
    accept_implausible: AcceptOption = False,
    bearing: BearingOption = None,
    workers: Annotated[int | None, typer.Option(callback=number(1, MAX_WORKERS), help="With several files or --by: fit the groups on this "
                                                "many local worker processes (needs ambfit[dask]); plain least "
                                                "squares runs as vmapped batches of groups. Default: this "
                                                "process.")] = None,
    scheduler: Annotated[str | None, typer.Option(metavar="ADDRESS", help="With several files or --by: fit the "
                                                  "groups on the Dask cluster whose scheduler is at this address "
                                                  "(e.g. tcp://10.0.0.5:8786, a dask-jobqueue cluster's "
                                                  "scheduler_address; its workers need ambfit).")] = None,
):
    """Identify effective gap, origin (and k when loads are known) for each axis.

    least-squares: value ± standard error from the fit's covariance; exits 3 with the
    reason when the fit does not converge or the design does not identify the
    parameters.  closed-form: mean over iterations ± standard error of that mean; exits 3
    when its iterations cannot be trusted.  Both exit 3 when the bearing description rules
    the result out (unless --accept-implausible).

    Several files (or --by COLUMN): one estimate per group, each judged on its own; a group
    that fails does not stop the others.  Exit 0 when every group is fine, 2 when a file
    cannot be read, else 3; the last line names the groups that are not fine.  --workers N
    or --scheduler ADDRESS spread the groups over processes or a Dask cluster (same results).
    """
    check_output(json_out, table, inputs=(*data, bearing))
    if workers is not None and scheduler is not None:
        fail("give --workers (local processes) or --scheduler (a running Dask cluster), not both")
    enable_compilation_cache()
    desc = bearing_of(bearing)
    paths, unmatched = _expand(data)
    column = None if by.strip().lower() in ("", "none") else by.strip()
    effects = _effects(effect or [], desc)
    opts = _Options(method=method, current_noise_ma=current_noise_ma, position_noise_um=position_noise_um,
                    require_k=require_k, debias=debias, loss=loss.value, keep_duplicates=keep_duplicates,
                    accept=accept_implausible, bearing=desc, force_check=force_check, effects=effects,
                    discrepancy=discrepancy, fit_current_zeros=fit_current_zeros)
    single = len(paths) == 1 and not unmatched and column is None and not pooled
    if (effects or discrepancy) and (not single or method == Method.closed_form):
        fail("--effect and --discrepancy extend the least-squares model of one data set (not the closed form, "
             "not several files or --by groups)")
    if single:
        if workers is not None or scheduler is not None:
            note("one data set: nothing to spread over workers, it is fitted in this process (--workers and "
                 "--scheduler take several files or --by COLUMN)")
        from ambfit.estimation.debias import by_solve

        with by_solve():    # a command fits a data set or two and ends: their biases cost no compilation
            _identify_file(paths[0], opts, max_position_um, json_out, table)
    else:
        _identify_groups(paths, unmatched, column, opts, max_position_um, pooled, json_out, table, workers,
                         scheduler)


def _identify_file(data: Path, opts: _Options, max_position_um, json_out, table):
    """One file, one estimate: the contract's section-2 JSON."""
    from ambfit.estimation import plausibility
    from ambfit.physics.effects import CurrentOffset

    ds = read_data(data, opts.bearing, opts.accept, max_position_um)
    original = ds
    ds, dropped = drop_duplicates(ds, data.name, opts.keep_duplicates)
    if opts.method is Method.closed_form:
        record = _identify_closed_form(ds, data.name, opts.bearing)
    else:
        record = _identify_ls(ds, data.name, opts)
        if dropped and "g_v0_um" in record["params"]:
            # (the model reported: the user's effects, and the current zeros when identify fitted them)
            effects = opts.effects + ((CurrentOffset(),) if "current_zeros_fitted" in record.get(
                "uncertainty_budget", {}) else ())
            record["duplicates_error_bar_factor"] = _duplicate_effect(original, record, opts.bearing, opts.loss,
                                                                      effects=effects)
    record["duplicates_dropped"] = dropped
    flags = [plausibility.Flag(**f) for f in record.get("implausible", [])]
    if json_out is not None:
        from ambfit.estimation.model_file import stamp

        write_json(stamp(record, "identify"), json_out)
    if table is not None:
        status = _status(record, flags, opts.accept)
        _write_table([_table_row({"group": data.name, "file": str(data), "status": status, **record})], None, table)
    if not record["converged"]:
        raise typer.Exit(3)
    judge(flags, opts.accept)
    if record.get("trusted") is False:
        raise typer.Exit(3)


def _identify_closed_form(ds, name, bearing, *, show: bool = True) -> dict:
    from ambfit.estimation.closed_form import ClosedFormError

    try:
        result = checked_closed_form(ds, bearing)
    except ClosedFormError as exc:
        fail(str(exc), 3)
    show_table(result.display_rows(), f"closed form (Eq. 5-7), {name}, {result.n_rows} rows",
               left=("experiment", "axis"))
    record = _closed_form_record(result, bearing, name="")
    if not result.trusted:
        warn("the closed-form result cannot be trusted (see above); ambfit identify exits 3")
    return record


def _effects(names: list[str], bearing) -> tuple:
    """The ``--effect`` names as effects to fit; the magnetic circuit needs the bearing's B-H curve."""
    from ambfit.physics.effects import effect_by_name

    out = []
    for text in names:
        try:
            e = effect_by_name(text.strip(), bearing=bearing)
        except ValueError as exc:
            fail(f"--effect: {exc}")
        if getattr(e, "needs_other_axis", False) and not bearing.b_curve:
            fail(f"--effect {text}: the magnetic circuit needs the lamination's B-H curve in the bearing description "
                 "(--bearing FILE with b_curve/h_curve)")
        out.append(e)
    return tuple(out)


def _show_budget(record: dict, b, bearing) -> None:
    """The GUM budget ``b`` (:mod:`ambfit.estimation.budget`) into the record's params (``u_combined``,
    ``budget``) and ``uncertainty_budget``, and shown: ``std`` stays the readings' noise alone."""
    from ambfit.estimation.budget import declared_text

    b.merge(record["params"])
    record["uncertainty_budget"] = b.to_json()
    show_table(b.summary_rows(), f"uncertainty: the readings' noise and the calibration tolerances "
               f"({declared_text(bearing, b.fitted_terms)})", left=("parameter", "largest calibration term"))
    for what in b.fitted_terms:
        note(f"{what}s: fitted by the model (their error is in std), not budgeted from the tolerance")
    if b.failed:
        warn(b.failed_text())


def _fit_ls(ds, effects, opts: _Options):
    from ambfit.estimation import fit

    try:
        return fit.fit(ds, effects, **opts.fit_kw())
    except fit.FitError as exc:
        fail(str(exc), 3)
    except ValueError as exc:                   # e.g. --debias with effects
        fail(str(exc))


def _show_fit(res, name: str, n: int, what: str = "least squares") -> None:
    show_table([{"experiment": "all", **res.display_row()}], f"{what}, {name}, {n} rows", left=("experiment",))
    for line in res.notes():
        note(line)
    _warn_health(res)


def _identify_ls(ds, name, opts: _Options) -> dict:
    from ambfit.estimation import fit
    from ambfit.estimation.budget import budget, fit_instead

    res = _fit_ls(ds, opts.effects, opts)
    _show_fit(res, name, len(ds))
    kw = opts.fit_kw()
    noise = {k: kw[k] for k in ("sigma_i", "sigma_x", "require_k", "loss")}
    bootstrap = not isinstance(opts.debias, str)
    b = budget(ds, res, **noise) if res.converged and res.well_conditioned else None
    # (the fit with the current zeros is made as this one was, but never with a bootstrap)
    instead = fit_instead(ds, res, b, **noise, debias=opts.debias) if b is not None and not bootstrap else None
    if instead is not None and opts.fit_current_zeros:
        note(f"{instead.text}; the fit below does (--no-fit-current-zeros keeps the ideal law and its budget)")
        res, b = instead.fit, instead.budget
        _show_fit(res, name, len(ds), "least squares with the current zeros fitted")
    record = res.to_json()
    if b is not None:
        _show_budget(record, b, res.bearing)
    if instead is not None:
        key = "current_zeros_fitted" if opts.fit_current_zeros else "fit_instead"
        record["uncertainty_budget"][key] = instead.to_json()
        if not opts.fit_current_zeros:
            note(f"{instead.text} (--fit-current-zeros or --effect {instead.effect})")
    if opts.discrepancy and res.converged:
        import numpy as np

        from ambfit.estimation.discrepancy import fit_discrepancy

        d = fit_discrepancy(res, ds, sigma_i=kw["sigma_i"], sigma_x=kw["sigma_x"])
        record["model_state"]["discrepancy"] = d.to_json()
        kept = res.fitted_rows
        before, after = np.mean(res.residuals[kept] ** 2), np.mean((res.residuals + d.row_correction)[kept] ** 2)
        record["discrepancy"] = {"mean_z2_before": float(before), "mean_z2_after": float(after), **d.summary(3)}
        note(f"discrepancy (orthogonal to every fitted parameter): mean z² {before:.2f} -> {after:.2f} with "
             f"{d.effective_parameters:.0f} effective terms; log Bayes factor "
             + ", ".join(f"{k} {v:.1f}" for k, v in d.log_bayes.items()) + " (above 10: the data want it)")
    if opts.force_check and res.converged:
        from ambfit.estimation.measure import force_check

        try:
            fc = force_check(ds, res.effects, bearing=opts.bearing, base=res, sigma_i=kw["sigma_i"],
                             sigma_x=kw["sigma_x"], loss=opts.loss, discrepancy=opts.discrepancy)
        except fit.FitError as exc:            # the check is extra: its failure must not cost the result
            fc = {"method": "leave-one-load-out", "error": str(exc)}
            warn(f"force check not possible: {exc}")
        if fc is not None and "error" not in fc:
            record["force_check"] = fc
            unconverged = (f"; {fc['n_not_converged']} of the refits did not converge (counted as they stand)"
                           if fc["n_not_converged"] else "")
            with_d = (f"; with the discrepancy {100 * fc['discrepancy']['rms_rel']:.2f} % RMS"
                      if "discrepancy" in fc else "")
            note(f"force check (each of {fc['n_loads']} known loads left out and predicted): "
                 f"{100 * fc['rms_rel']:.2f} % RMS, {100 * fc['max_rel']:.2f} % worst{unconverged}{with_d}; the "
                 f"readings' noise alone gives {100 * fc['noise_floor_rel']:.2f} %, so the model's own error is "
                 f"{100 * fc['model_error_rel']:.2f} %")
        elif fc is not None:
            record["force_check"] = fc
    return record
