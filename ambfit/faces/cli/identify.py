"""``ambfit identify`` and ``ambfit sample``: least squares, the paper's closed form, the posterior."""

from __future__ import annotations

import dataclasses
import sys
from enum import Enum
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
    console,
    err,
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


def say(kind: str, text: str) -> None:
    """Show one message now: ``kind`` is "warn", "note", "error" or "implausible".  Work that runs on an engine's
    worker processes collects ``(kind, text)`` pairs instead (a list's ``append`` in its place) and the command
    shows them, in order, when the results come back."""
    if kind == "warn":
        warn(text)
    elif kind == "note":
        note(text)
    else:
        err.print(f"[bold red]{kind}:[/] {text}", highlight=False, soft_wrap=True)


def _collector(messages: list):
    """A ``say`` that keeps the messages in ``messages`` (an engine task returns them with its results)."""
    return lambda kind, text: messages.append((kind, text))


def drop_duplicates(ds, name: str, keep: bool, say=say):
    """Name exact duplicate readings; unless ``keep``, count each once.  Returns ``(dataset, dropped rows)``.

    Rows are named as in the file (counted from 1): a group cut out of a file keeps the file's row numbers.
    """
    from ambfit.data import Dataset, duplicate_rows, file_rows

    dupes = duplicate_rows(ds.frame)
    if not dupes:
        return ds, []
    rows = file_rows(ds.frame)

    def row(r):                       # duplicate_rows counts positions from 1; messages name the file's rows
        return int(rows[r - 1])

    listed = ", ".join(f"{row(r)} repeats {row(f)}" for r, f in dupes[:8]) + (" ..." if len(dupes) > 8 else "")
    if keep:
        say("warn", f"{name}: {len(dupes)} exact duplicate reading(s) kept (--keep-duplicates): rows {listed}; "
            "each counts twice and the error bars are too small (up to sqrt(2) when every row repeats)")
        return ds, []
    frame = ds.frame.drop(index=ds.frame.index[[r - 1 for r, _ in dupes]])
    say("warn", f"{name}: {len(dupes)} exact duplicate reading(s) counted once (rows {listed}); a repeated reading "
        "is a copy, not a new measurement, and would shrink the error bars (--keep-duplicates counts them)")
    return Dataset(frame=frame, source=ds.source), [row(r) for r, _ in dupes]


def _duplicate_effect(original, record: dict, bearing, loss: str, prefix: str = "", say=say) -> float | None:
    """How much smaller the gap's error bar would be with the duplicates counted (a fit of the full file)."""
    from ambfit.estimation import fit

    try:
        with_dupes = fit.fit(original, bearing=bearing, loss=loss, throw=False)
    except fit.FitError:
        return None
    std, dup = record["params"]["g_v0_um"]["std"], with_dupes.error("g_v0") * 1e6
    say("note", f"{prefix}counted as often as they appear, the duplicates would shrink the error bars "
        f"{std / dup:.2f} x (g_v0 ± {dup:.3g} µm instead of ± {std:.3g} µm)")
    return std / dup


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
    accept_implausible: AcceptOption = False,
    bearing: BearingOption = None,
    workers: Annotated[int | None, typer.Option(min=1, help="With several files or --by: fit the groups on this "
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
    check_output(json_out, table)
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
                    discrepancy=discrepancy)
    single = len(paths) == 1 and not unmatched and column is None and not pooled
    if (effects or discrepancy) and (not single or method == Method.closed_form):
        fail("--effect and --discrepancy extend the least-squares model of one data set (not the closed form, "
             "not several files or --by groups)")
    if single:
        if workers is not None or scheduler is not None:
            note("one data set: nothing to spread over workers, it is fitted in this process (--workers and "
                 "--scheduler take several files or --by COLUMN)")
        _identify_file(paths[0], opts, max_position_um, json_out, table)
    else:
        _identify_groups(paths, unmatched, column, opts, max_position_um, pooled, json_out, table, workers,
                         scheduler)


@dataclasses.dataclass(frozen=True)
class _Options:
    """The fit settings of one ``identify`` run, the same for every group."""

    method: Method
    current_noise_ma: float | None
    position_noise_um: float | None
    require_k: bool
    debias: int
    loss: str
    keep_duplicates: bool
    accept: bool
    bearing: object
    force_check: bool = True
    effects: tuple = ()
    discrepancy: bool = False

    def fit_kw(self) -> dict:
        return dict(sigma_i=None if self.current_noise_ma is None else self.current_noise_ma * 1e-3,
                    sigma_x=None if self.position_noise_um is None else self.position_noise_um * 1e-6,
                    require_k=self.require_k, debias=self.debias, bearing=self.bearing, loss=self.loss)


def _identify_file(data: Path, opts: _Options, max_position_um, json_out, table):
    """One file, one estimate: the contract's section-2 JSON."""
    from ambfit.estimation import plausibility

    ds = read_data(data, opts.bearing, opts.accept, max_position_um)
    original = ds
    ds, dropped = drop_duplicates(ds, data.name, opts.keep_duplicates)
    if opts.method is Method.closed_form:
        record = _identify_closed_form(ds, data.name, opts.bearing)
    else:
        record = _identify_ls(ds, data.name, opts)
        if dropped and "g_v0_um" in record["params"]:
            record["duplicates_error_bar_factor"] = _duplicate_effect(original, record, opts.bearing, opts.loss)
    record["duplicates_dropped"] = dropped
    flags = [plausibility.Flag(**f) for f in record.get("implausible", [])]
    if json_out is not None:
        write_json(record, json_out)
    if table is not None:
        status = _status(record, flags, opts.accept)
        _write_table([_table_row({"group": data.name, "file": str(data), "status": status, **record})], None, table)
    if not record["converged"]:
        raise typer.Exit(3)
    judge(flags, opts.accept)
    if record.get("trusted") is False:
        raise typer.Exit(3)


def _identify_closed_form(ds, name, bearing, *, show: bool = True) -> dict:
    from ambfit.estimation import closed_form

    try:
        result = closed_form.identify(ds, bearing=bearing)
    except closed_form.ClosedFormError as exc:
        fail(str(exc), 3)
    show_table(result.display_rows(), f"closed form (Eq. 5-7), {name}, {result.n_rows} rows",
               left=("experiment", "axis"))
    record = _closed_form_record(result, bearing, name="")
    if not result.trusted:
        warn("the closed-form result cannot be trusted (see above); ambfit identify exits 3")
    return record


def _closed_form_record(result, bearing, name: str, say=say) -> dict:
    """The closed form's contract record with its plausibility flags; its rejections and health as warnings."""
    from ambfit.estimation import plausibility

    for line in result.rejections():
        say("warn", name + line)
    for line in result.health():
        say("warn", name + line)
    record = result.to_json()
    keys = {e for e, _ in result.estimates}
    record["implausible"] = [f.to_json() for key in sorted(keys) for f in plausibility.check_result(
        _si_values(result.params(key)), bearing)]
    return record


def _si_values(params: dict) -> dict:
    """Contract parameter block -> internal names in SI."""
    from ambfit.estimation.results import CONTRACT_PARAMS

    return {name: params[key]["value"] / f for name, key, f in CONTRACT_PARAMS if key in params}


def _effects(names: list[str], bearing) -> tuple:
    """The ``--effect`` names as effects to fit; the magnetic circuit needs the bearing's B-H curve."""
    from ambfit.physics.effects import effect_by_name

    out = []
    for text in names:
        try:
            e = effect_by_name(text.strip())
        except ValueError as exc:
            fail(f"--effect: {exc}")
        if getattr(e, "needs_other_axis", False) and not bearing.b_curve:
            fail(f"--effect {text}: the magnetic circuit needs the lamination's B-H curve in the bearing description "
                 "(--bearing FILE with b_curve/h_curve)")
        out.append(e)
    return tuple(out)


def _identify_ls(ds, name, opts: _Options) -> dict:
    from ambfit.estimation import fit

    try:
        res = fit.fit(ds, opts.effects, **opts.fit_kw())
    except fit.FitError as exc:
        fail(str(exc), 3)
    except ValueError as exc:                   # e.g. --debias with effects
        fail(str(exc))
    show_table([{"experiment": "all", **res.display_row()}], f"least squares, {name}, {len(ds)} rows",
               left=("experiment",))
    for line in res.notes():
        note(line)
    _warn_health(res)
    record = res.to_json()
    kw = opts.fit_kw()
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


def _warn_health(res, prefix: str = "", say=say):
    for check, ok, text in res.checks():
        if ok is False and check not in ("k_identified", "plausible"):   # plausibility: judge() says it
            say("warn", prefix + text)


# --- several files, or one file split by a column ---------------------------------------------------------------

GLOB_CHARACTERS = "*?["


def _expand(args: list[Path]) -> tuple[list[Path], list[str]]:
    """The files named, quoted globs expanded (sorted); a file named twice counted once.

    Returns ``(paths, patterns that matched no file)``.  A path that exists is taken as it is, even when its name
    contains glob characters.
    """
    import glob

    found, unmatched = [], []
    for arg in args:
        text = str(arg)
        if arg.exists() or not any(c in text for c in GLOB_CHARACTERS):
            found.append(arg)
            continue
        hits = sorted(h for h in glob.glob(text, recursive=True) if Path(h).is_file())
        if not hits:
            unmatched.append(text)
        found += [Path(h) for h in hits]
    paths, seen = [], set()
    for p in found:
        key = p.resolve()
        if key in seen:
            warn(f"{p}: named more than once; identified once")
            continue
        seen.add(key)
        paths.append(p)
    return paths, unmatched


def _split(frame, column: str | None):
    """``(value, rows)`` for each value of ``column`` in order of first appearance; ``(None, frame)`` without one.

    Values are compared as text (as :func:`ambfit.estimation.fit.fit_by` does); rows with an empty cell form the
    group ``"(empty)"``.  Each group keeps the file's row index, so messages name the file's rows.
    """
    if column is None:
        return [(None, frame)]
    keys = frame[column].astype("string").fillna("(empty)").astype(str)
    return [(str(value), frame[keys == value]) for value in dict.fromkeys(keys)]


STATUS_TEXT = {"ok": "ok", "failed": "fit failed", "implausible": "implausible", "untrusted": "not trusted",
               "unreadable": "unreadable"}


def _status(record: dict, flags, accept: bool) -> str:
    """ok, failed (no estimate or not converged), implausible (ruled out by the bearing), untrusted (closed form)."""
    if record.get("error") or not record.get("converged"):
        return "failed"
    if flags and not accept:
        return "implausible"
    if record.get("trusted") is False:
        return "untrusted"
    return "ok"


def _identify_groups(paths, unmatched, column, opts: _Options, max_position_um, pooled, json_out, table,
                     workers: int | None = None, scheduler: str | None = None):
    """One estimate per file (and per value of ``column``), each judged on its own; exit 2 if a file is unreadable,
    3 if a group is not fine, else 0.  With ``workers`` or ``scheduler`` the groups run on :mod:`ambfit.engine`
    (chunks of groups per task, plain least squares as one vmapped batch per chunk); the entries are the same."""
    from ambfit.data import DataError, Dataset, read_csv
    from ambfit.faces.cli.progress import progress_bar

    several = len(paths) + len(unmatched) > 1
    limit = max_position_um or opts.bearing.nominal_gap * 1e6
    jobs, readable = [], []       # jobs: (file, value, Dataset or the reason it cannot be read)
    for pattern in unmatched:
        jobs.append((pattern, None, f"{pattern}: no file matches this pattern"))
    for path in paths:
        try:
            ds = read_csv(path, max_position_um=limit)
        except (DataError, OSError) as exc:
            jobs.append((str(path), None, str(exc)))
            continue
        if column is not None and column not in ds.frame.columns:
            cols = ", ".join(map(str, ds.frame.columns))
            jobs.append((str(path), None, f"{path}: no column {column!r} to split by (--by); columns: {cols}"))
            continue
        readable.append((path, ds))
        jobs += [(str(path), value, Dataset(frame=rows, source=ds.source)) for value, rows in _split(ds.frame, column)]

    def label(file, value):
        name = file if several else Path(file).name
        return name if value is None else (f"{name}:{value}" if several else value)

    entries = []
    with progress_bar() as bar:
        heads = [{"group": label(file, value), "file": file, **({} if column is None else {"by": column,
                                                                                         "value": value})}
                 for file, value, _ in jobs]
        if workers is None and scheduler is None:
            for head, (_, _, ds) in zip(heads, bar.iterate(jobs, "groups")):
                if isinstance(ds, str):
                    say("error", ds)
                    entries.append({**head, "status": "unreadable", "error": ds})
                else:
                    entries.append({**head, **_identify_group(ds, head["group"], opts)})
        else:
            entries = _groups_on_engine(jobs, heads, opts, workers, scheduler, bar)
        pooled_entry = None
        if pooled and readable:
            bar("pooled fit", 0, 1)
            pooled_entry = {"group": "(pooled)", "file": "; ".join(str(p) for p, _ in readable),
                            **_identify_group(_pooled(readable), "pooled", opts)}
            bar("pooled fit", 1, 1)

    shown = entries + ([pooled_entry] if pooled_entry else [])
    what = "closed form (Eq. 5-7)" if opts.method is Method.closed_form else "least squares"
    files = len(paths) + len(unmatched)
    show_table([_display_row(e) for e in shown],
               f"{what}, {len(entries)} group(s) from {files} file(s)" + (f" by {column}" if column else ""),
               left=("group", "status"))
    if json_out is not None:
        record = {"method": "closed_form" if opts.method is Method.closed_form else "least_squares",
                  "by": column, "files": [str(p) for p in paths] + unmatched, "n_groups": len(entries),
                  "n_ok": sum(e["status"] == "ok" for e in entries), "groups": entries}
        if pooled_entry is not None:
            record["pooled"] = pooled_entry
        write_json(record, json_out)
    if table is not None:
        _write_table([_table_row(e) for e in shown], column, table)
    bad = [e for e in shown if e["status"] != "ok"]
    if not bad:
        note(f"all {len(shown)} group(s) fine")
        return
    listed = "; ".join(f"{e['group']} ({STATUS_TEXT[e['status']]})" for e in bad[:10]) + (" ..." if len(bad) > 10
                                                                                          else "")
    unreadable = any(e["status"] == "unreadable" for e in bad)
    written = " and ".join(str(p) for p in (json_out, table) if p is not None)
    rest = "" if len(bad) == len(shown) else "; the other groups' results stand" + (f" (in {written})" if written
                                                                                     else "")
    fail(f"{len(bad)} of {len(shown)} group(s) not fine: {listed}{rest}", 2 if unreadable else 3)


def _groups_on_engine(jobs, heads, opts: _Options, workers, scheduler, bar) -> list[dict]:
    """The groups' entries computed on the engine; their messages shown afterwards in the order of the groups."""
    import functools

    from ambfit import engine

    items = [(head["group"], ds) for head, (_, _, ds) in zip(heads, jobs) if not isinstance(ds, str)]
    try:
        with engine.using(workers, scheduler) as eng:
            done = eng.map_batches(functools.partial(_groups_task, opts=opts), items, progress=bar, what="groups")
    except engine.EngineError as exc:
        from rich.markup import escape

        fail(escape(str(exc)), 2)           # (escaped: "ambfit[dask]" is not markup)
    results = iter(done)
    entries = []
    for head, (_, _, ds) in zip(heads, jobs):
        if isinstance(ds, str):
            say("error", ds)
            entries.append({**head, "status": "unreadable", "error": ds})
            continue
        entry, messages = next(results)
        for kind, text in messages:
            say(kind, text)
        entries.append({**head, **entry})
    return entries


def _identify_group(ds, name: str, opts: _Options, say=say) -> dict:
    """Plausibility of the data, duplicates, the fit and the plausibility of its result for one group, as the
    single-file path does them, but reported instead of ending the run."""
    return _finish_group(_prepare_group(ds, name, opts, say), name, opts, say)


@dataclasses.dataclass(frozen=True)
class _Prepared:
    """A group before its fit: the data's plausibility flags, the table as read, and without duplicates."""

    data_flags: list
    original: object
    ds: object
    dropped: list


def _prepare_group(ds, name: str, opts: _Options, say=say) -> _Prepared:
    from ambfit.estimation import plausibility

    data_flags = plausibility.check_data(ds.frame, opts.bearing)
    deduplicated, dropped = drop_duplicates(ds, name, opts.keep_duplicates, say)
    return _Prepared(data_flags=data_flags, original=ds, ds=deduplicated, dropped=dropped)


def _finish_group(prep: _Prepared, name: str, opts: _Options, say=say, res=None) -> dict:
    """The group's entry from its fit: ``res`` (a :class:`FitResult`, or the exception its fit raised) when the
    fit ran in a batch, else the fit runs here."""
    from ambfit.data import DataError
    from ambfit.estimation import closed_form, fit, plausibility

    prefix = f"{name}: "
    ds = prep.ds
    try:
        if opts.method is Method.closed_form:
            record = _closed_form_record(closed_form.identify(ds, bearing=opts.bearing), opts.bearing, prefix, say)
        else:
            if res is None:
                res = fit.fit(ds, **opts.fit_kw())
            elif isinstance(res, Exception):
                raise res
            else:
                res.raise_for_health()          # what fit(throw=True) raises
            _warn_health(res, prefix, say)
            record = res.to_json()
            if prep.dropped and "g_v0_um" in record["params"]:
                record["duplicates_error_bar_factor"] = _duplicate_effect(prep.original, record, opts.bearing,
                                                                          opts.loss, prefix, say)
    except (fit.FitError, closed_form.ClosedFormError, DataError, ValueError) as exc:
        say("error", f"{prefix}{exc}")
        record = {"method": "closed_form" if opts.method is Method.closed_form else "least_squares", "params": {},
                  "converged": False, "n_rows": len(ds), "error": str(exc)}
    flags = [*prep.data_flags, *(plausibility.Flag(**f) for f in record.get("implausible", []))]
    record["implausible"] = [f.to_json() for f in flags]
    record["duplicates_dropped"] = prep.dropped
    for f in flags:
        say("warn" if opts.accept else "implausible", f"{prefix}{f}")
    return {"status": _status(record, flags, opts.accept), **record}


def _batched(opts: _Options) -> bool:
    """Whether the groups' fits can run as one vmapped batch (:func:`ambfit.estimation.batch.fit_many`): plain
    least squares of the ideal law (with its outlier test), no bias correction."""
    return opts.method is Method.least_squares and opts.loss in ("auto", "linear") and not opts.debias


def _groups_task(chunk: list, opts: _Options) -> list:
    """One engine task: the entries of a chunk of ``(group label, Dataset)`` and each group's messages
    (``[(kind, text)]``), as the in-process loop would show them.  Plain least squares runs as one vmapped batch
    of the chunk's groups; everything else (and every group whose outlier test finds a reading) is fitted by
    :func:`ambfit.estimation.fit.fit`, as in this process."""
    from ambfit.estimation import batch

    out, preps = [], []
    for name, ds in chunk:
        messages = []
        preps.append(_prepare_group(ds, name, opts, _collector(messages)))
        out.append(messages)
    fits = [None] * len(chunk)
    if _batched(opts):
        fits = batch.fit_many([p.ds for p in preps], **opts.fit_kw())
    return [(_finish_group(p, name, opts, _collector(messages), res), messages)
            for (name, _), p, res, messages in zip(chunk, preps, fits, out)]


def _pooled(readable):
    """All rows of all files as one data set; a file's loads stay its own (``load_id`` and ``experiment`` are
    prefixed with the file when there are several)."""
    import pandas as pd

    from ambfit.data import Dataset

    if len(readable) == 1:
        return readable[0][1]
    parts = []
    for path, ds in readable:
        f = ds.frame.copy()
        exp = f["experiment"].astype(str) if "experiment" in f else None
        base = (f["load_id"].astype(str) if "load_id" in f else
                ("experiment:" + exp) if exp is not None else pd.Series("all", index=f.index))
        f["load_id"] = f"{path}|" + base
        f["experiment"] = f"{path}|" + (exp if exp is not None else "all")
        parts.append(f)
    return Dataset(frame=pd.concat(parts, ignore_index=True), source="pooled")


def _display_row(entry: dict) -> dict:
    """One console-table row: the group, its rows, each parameter ± its error in display units, χ²/dof, status."""
    from ambfit.estimation.results import CONTRACT_PARAMS, DISPLAY, pm

    params = entry.get("params", {})
    row = {"group": entry["group"], "rows": str(entry.get("n_rows", "–"))}
    for name, key, _ in CONTRACT_PARAMS:
        p = params.get(key)
        std = p.get("std") if p else None
        row[f"{name} [{DISPLAY[name][0]}]"] = "–" if p is None else pm(p["value"], float("nan") if std is None
                                                                          else std)
    chi2 = entry.get("reduced_chi2")
    row["χ²/dof"] = "–" if chi2 is None else f"{chi2:.2f}"
    row["status"] = STATUS_TEXT[entry["status"]]
    return row


TABLE_PARAMS = (("g_v0", "um"), ("v0", "um"), ("g_w0", "um"), ("w0", "um"), ("k_v", "Nm2_per_A2"),
                ("k_w", "Nm2_per_A2"))


def _table_row(entry: dict) -> dict:
    """One ``--table`` row (file units in the column names, blank where a value does not apply)."""
    params = entry.get("params", {})
    row = {"group": entry["group"], "file": entry.get("file", ""), "_value": entry.get("value"),
           "n_rows": entry.get("n_rows")}
    for name, unit in TABLE_PARAMS:
        p = params.get(f"{name}_{unit}", {})
        row[f"{name}_{unit}"] = p.get("value")
        row[f"{name}_std_{unit}"] = p.get("std")
    gof = entry.get("goodness_of_fit", {})
    flags = entry.get("implausible", [])
    row |= {"reduced_chi2": entry.get("reduced_chi2"), "dof": entry.get("dof"), "p_value": gof.get("p_value"),
            "converged": entry.get("converged"), "well_conditioned": entry.get("well_conditioned"),
            "adequate": gof.get("adequate"), "trusted": entry.get("trusted"),
            "outliers": len(entry.get("outliers", [])), "duplicates_dropped": len(entry.get("duplicates_dropped", [])),
            "implausible": bool(flags), "implausible_why": "; ".join(f"{f['quantity']}: {f['cause']}" for f in flags),
            "status": entry["status"], "error": entry.get("error", "")}
    return row


def _write_table(rows: list[dict], column: str | None, path: Path):
    """Write the groups table as CSV (atomically: a temporary file in the same folder, then a rename)."""
    import os
    import tempfile

    import pandas as pd

    frame = pd.DataFrame(rows)
    value_name = column if column and column not in frame.columns else "by_value"
    if column is None:
        frame = frame.drop(columns="_value")
    else:
        frame = frame.rename(columns={"_value": value_name})
    for c in ("n_rows", "dof", "outliers", "duplicates_dropped"):
        frame[c] = frame[c].astype("Int64")
    path = Path(path)
    fd, tmp = tempfile.mkstemp(dir=path.parent if str(path.parent) else ".", prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "w", newline="") as f:
            frame.to_csv(f, index=False)
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)
    console.print(f"wrote {path} ({len(frame)} row(s))")


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

        plots.save(plots.plot_pair(res, result=res.ls), pair_png, close=True)
        console.print(f"wrote {pair_png}")
    if not record["converged"]:
        raise typer.Exit(3)
