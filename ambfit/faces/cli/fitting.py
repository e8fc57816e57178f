"""What ``ambfit identify`` does for every data set, one file or many groups: the run's options, messages,
duplicate readings, and the contract record with its status and ``--table`` row."""

from __future__ import annotations

import dataclasses
from enum import Enum
from pathlib import Path
from typing import Annotated

import typer

from ambfit.faces.cli.app import err, escape, note, warn
from ambfit.faces.cli.options import number

CurrentNoiseOption = Annotated[float | None, typer.Option(
    "--current-noise-ma", callback=number(0), help="Declared current noise std [mA], over the std columns "
                                                   "(default: the std columns, else estimated: by a fit from its "
                                                   "residuals, by diagnose from each reading against its "
                                                   "neighbours).")]
PositionNoiseOption = Annotated[float | None, typer.Option(
    "--position-noise-um", callback=number(0), help="Declared position noise std [µm] (default: the std "
                                                    "columns, else 0).")]
"""The readings' noise as every command that fits data takes it (identify, diagnose, sample, solution-space,
design, report); :func:`declared_noise` turns them into the library's ``sigma_i``/``sigma_x``."""


def declared_noise(current_noise_ma: float | None, position_noise_um: float | None) -> dict:
    """``--current-noise-ma`` and ``--position-noise-um`` as the library's ``sigma_i`` [A] and ``sigma_x`` [m]
    (None: not declared)."""
    return dict(sigma_i=None if current_noise_ma is None else current_noise_ma * 1e-3,
                sigma_x=None if position_noise_um is None else position_noise_um * 1e-6)


class Occam(str, Enum):
    # ambfit.diagnosis.verdict.OCCAM, spelt here as Target is (test_cli_options holds the two equal)
    all = "all"
    siblings = "siblings"
    none = "none"


OccamOption = Annotated[Occam, typer.Option(
    help="Which more flexible models (pairs, laws widened by their family's signature) must predict the held-out "
         "readings better than a library law that explains them before they count as its rivals: all of them; "
         "siblings (only widened laws of the law's own signature: another family's physics that predicts as well "
         "leaves the verdict undecided); none (a family is named only when its best model beats every other "
         "family's clearly). Stricter names fewer wrong families on laws unlike the library's, and fewer right "
         "ones on the library's own.")]
"""``--occam``: :attr:`ambfit.diagnosis.Rules.occam` for the commands that diagnose (diagnose, design
--discriminate, report)."""


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
        err.print(f"[bold red]{kind}:[/] {escape(text)}", highlight=False, soft_wrap=True)


def _collector(messages: list):
    """A ``say`` that keeps the messages in ``messages`` (an engine task returns them with its results)."""
    return lambda kind, text: messages.append((kind, text))


def drop_duplicates(ds, name: str, keep: bool, say=say):
    """Name duplicate readings (:func:`ambfit.data.duplicate_rows`: the same labels, numbers within 10 µA and 1 nm); unless ``keep``, count each once.  Returns ``(dataset, dropped rows)``.

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
        say("warn", f"{name}: {len(dupes)} duplicate reading(s) kept (--keep-duplicates): rows {listed}; "
            "each counts twice and the error bars are too small (up to sqrt(2) when every row repeats)")
        return ds, []
    frame = ds.frame.drop(index=ds.frame.index[[r - 1 for r, _ in dupes]])
    say("warn", f"{name}: {len(dupes)} duplicate reading(s) counted once (rows {listed}; the same labels, every number "
        "within 10 µA and 1 nm); a repeated reading "
        "is a copy, not a new measurement, and would shrink the error bars (--keep-duplicates counts them)")
    return Dataset(frame=frame, source=ds.source), [row(r) for r, _ in dupes]


def _duplicate_effect(original, record: dict, bearing, loss: str, prefix: str = "", say=say,
                      effects: tuple = ()) -> float | None:
    """How much smaller the gap's error bar would be with the duplicates counted (a fit of the full file with the
    record's model, ``effects``)."""
    from ambfit.estimation import fit

    try:
        with_dupes = fit.fit(original, effects, bearing=bearing, loss=loss, throw=False)
    except fit.FitError:
        return None
    std, dup = record["params"]["g_v0_um"]["std"], with_dupes.error("g_v0") * 1e6
    say("note", f"{prefix}counted as often as they appear, the duplicates would shrink the error bars "
        f"{std / dup:.2f} x (g_v0 ± {dup:.3g} µm instead of ± {std:.3g} µm)")
    return std / dup


@dataclasses.dataclass(frozen=True)
class _Options:
    """The fit settings of one ``identify`` run, the same for every group."""

    method: Method
    current_noise_ma: float | None
    position_noise_um: float | None
    require_k: bool
    debias: int | str
    loss: str
    keep_duplicates: bool
    accept: bool
    bearing: object
    force_check: bool = True
    effects: tuple = ()
    discrepancy: bool = False
    fit_current_zeros: bool = True

    def fit_kw(self) -> dict:
        return dict(**declared_noise(self.current_noise_ma, self.position_noise_um), require_k=self.require_k,
                    debias=self.debias, bearing=self.bearing, loss=self.loss)


def checked_closed_form(ds, bearing):
    """The closed form of ``ds`` (Eq. 5-7) compared with least squares on the same readings: ``identify`` exits
    3 when they disagree beyond their errors (the ``agrees_with_least_squares`` check)."""
    from ambfit.estimation.checked import closed_form

    return closed_form(ds, bearing=bearing)


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
    from ambfit.estimation.units import CONTRACT_PARAMS

    return {name: params[key]["value"] / f for name, key, f in CONTRACT_PARAMS if key in params}


def _warn_health(res, prefix: str = "", say=say):
    from ambfit.faces.warnings import fit_warnings

    for text in fit_warnings(res):          # plausibility: judge() says it
        say("warn", prefix + text)


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


def _table_row(entry: dict) -> dict:
    """One ``--table`` row (file units in the column names, blank where a value does not apply)."""
    from ambfit.estimation.units import CONTRACT_PARAMS

    params = entry.get("params", {})
    row = {"group": entry["group"], "file": entry.get("file", ""), "_value": entry.get("value"),
           "n_rows": entry.get("n_rows")}
    for name, key, _ in CONTRACT_PARAMS:            # key: the name and its file unit, g_v0_um
        p = params.get(key, {})
        row[key] = p.get("value")
        row[f"{name}_std{key[len(name):]}"] = p.get("std")
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
    """Write the groups table as CSV (:mod:`ambfit._output`: atomically, through links, into devices)."""
    import pandas as pd

    from ambfit._output import formula_safe, write_text

    frame = pd.DataFrame(rows)
    value_name = column if column and column not in frame.columns else "by_value"
    if column is None:
        frame = frame.drop(columns="_value")
    else:
        frame = frame.rename(columns={"_value": value_name})
    for c in ("n_rows", "dof", "outliers", "duplicates_dropped"):
        frame[c] = frame[c].astype("Int64")
    write_text(path, formula_safe(frame).to_csv(index=False))   # a label is never run by a spreadsheet
    note(f"wrote {path} ({len(frame)} row(s))")
