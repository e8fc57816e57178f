"""``ambfit identify`` on several files, or one file split by a column: one estimate per group, each judged on
its own, in this process or on :mod:`ambfit.engine`."""

from __future__ import annotations

import dataclasses
from pathlib import Path

from ambfit.faces.cli.app import fail, note, show_table, warn, write_json
from ambfit.faces.cli.fitting import (
    STATUS_TEXT,
    Method,
    _closed_form_record,
    _collector,
    _duplicate_effect,
    _Options,
    _status,
    _table_row,
    _warn_health,
    _write_table,
    checked_closed_form,
    drop_duplicates,
    say,
)

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


def _identify_groups(paths, unmatched, column, opts: _Options, max_position_um, pooled, json_out, table,
                     workers: int | None = None, scheduler: str | None = None):
    """One estimate per file (and per value of ``column``), each judged on its own; exit 2 if a file is unreadable,
    3 if a group is not fine, else 0.  With ``workers`` or ``scheduler`` the groups run on :mod:`ambfit.engine`
    (chunks of groups per task, least squares as one batch per chunk); the entries are the same."""
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
        from ambfit.estimation.model_file import stamp

        write_json(stamp(record, "identify"), json_out)
    if table is not None:
        _write_table([_table_row(e) for e in shown], column, table)
    bad = [e for e in shown if e["status"] != "ok"]
    misfit = [e for e in shown if _misfit(e)]
    if misfit:            # estimates stand (as identify's of one file do), but the law does not fit these groups
        warn(f"{len(misfit)} group(s) whose model does not fit its readings (their errors assume it does; run "
             "ambfit diagnose): " + "; ".join(f"{e['group']} (χ²/dof {e['goodness_of_fit']['reduced_chi2']:.3g})"
                                               for e in misfit[:10]) + (" ..." if len(misfit) > 10 else ""))
    if not bad:
        note(f"all {len(shown)} group(s) fitted" + (f", {len(misfit)} of them not fitting their readings (see above)"
                                                     if misfit else " and fitting their readings"))
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
        fail(str(exc), 2)                   # (fail prints it literally: "ambfit[dask]" is not markup)
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

    data_flags = plausibility.check_data(ds.frame, opts.bearing, None if ds.source == "<memory>" else ds.source)
    deduplicated, dropped = drop_duplicates(ds, name, opts.keep_duplicates, say)
    return _Prepared(data_flags=data_flags, original=ds, ds=deduplicated, dropped=dropped)


def _finish_group(prep: _Prepared, name: str, opts: _Options, say=say, res=None) -> dict:
    """The group's entry from its fit: ``res`` (a :class:`FitResult`, or the exception its fit raised) when the
    fit ran in a batch, else the fit runs here."""
    from ambfit.data import DataError
    from ambfit.estimation import fit, plausibility
    from ambfit.estimation.closed_form import ClosedFormError

    prefix = f"{name}: "
    ds = prep.ds
    try:
        if opts.method is Method.closed_form:
            record = _closed_form_record(checked_closed_form(ds, opts.bearing), opts.bearing, prefix, say)
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
    except (fit.FitError, ClosedFormError, DataError, ValueError) as exc:
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
    """Whether the groups' fits run as one batch (:func:`ambfit.estimation.fit.fit_many`): every least-squares fit."""
    return opts.method is Method.least_squares


def _groups_task(chunk: list, opts: _Options) -> list:
    """One engine task: the entries of a chunk of ``(group label, Dataset)`` and each group's messages
    (``[(kind, text)]``), as the in-process loop would show them.  Least squares runs as one batch of the chunk's
    groups (:func:`ambfit.estimation.fit.fit_many`)."""
    from ambfit.estimation.fit import fit_many

    out, preps = [], []
    for name, ds in chunk:
        messages = []
        preps.append(_prepare_group(ds, name, opts, _collector(messages)))
        out.append(messages)
    fits = [None] * len(chunk)
    if _batched(opts):
        fits = fit_many([p.ds for p in preps], **opts.fit_kw())
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
    from ambfit.estimation.units import CONTRACT_PARAMS, DISPLAY, pm

    params = entry.get("params", {})
    row = {"group": entry["group"], "rows": str(entry.get("n_rows", "–"))}
    for name, key, _ in CONTRACT_PARAMS:
        p = params.get(key)
        std = p.get("std") if p else None
        row[f"{name} [{DISPLAY[name][0]}]"] = "–" if p is None else pm(p["value"], float("nan") if std is None
                                                                          else std)
    chi2 = entry.get("reduced_chi2")
    row["χ²/dof"] = "–" if chi2 is None else f"{chi2:.2f}"
    row["status"] = "ok, misfit" if _misfit(entry) else STATUS_TEXT[entry["status"]]   # (the warning below says more)
    return row


def _misfit(entry: dict) -> bool:
    """Whether a group was fitted but its model does not fit its readings (its estimates stand, with a warning)."""
    return entry["status"] == "ok" and (entry.get("goodness_of_fit") or {}).get("adequate") is False
