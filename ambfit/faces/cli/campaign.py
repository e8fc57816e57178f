"""``ambfit campaign``: identification in windows of time, the drift of gap and origin, change points."""

from __future__ import annotations

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
    fail,
    note,
    read_data,
    show_table,
    warn,
    write_json,
)
from ambfit.faces.cli.options import number


@app.command()
def campaign(
    data: Annotated[Path | None, typer.Argument(help="Campaign data, contract CSV with time_s: seconds on one "
                                                "clock over the whole campaign (not restarting per "
                                                "experiment).")] = None,
    window: Annotated[float | None, typer.Option("--window", metavar="SECONDS", help="Rolling windows of this "
                                                 "width [s] of time_s; each window is identified on its "
                                                 "own.")] = None,
    step: Annotated[float | None, typer.Option("--step", metavar="SECONDS", help="Start a window every this many "
                                               "seconds (default: the width; overlapping windows are shown, but "
                                               "the tests use the ones that share no reading).")] = None,
    by: Annotated[str | None, typer.Option("--by", metavar="COLUMN", help="One window per value of this column: "
                                           "'experiment' (the default without --window).")] = None,
    alpha: Annotated[float, typer.Option(help="False-alarm probability of the change-point test per parameter "
                                         "(Bonferroni bound over the boundaries tested).")] = 0.01,
    json_out: Annotated[Path | None, typer.Option("--json", help="Write windows, drifts and change points as JSON "
                                                  "here.")] = None,
    table: Annotated[Path | None, typer.Option("--table", help="Write one row per window as CSV here: span and "
                                               "centre [s], rows, experiments, estimates and standard errors "
                                               "[µm, N·m²/A²], χ²/dof, why a window is not identified.")] = None,
    example: Annotated[Path | None, typer.Option("--example", help="Instead of DATA: simulate a campaign on the "
                                                 "virtual rig (12 experiments 2 h apart, steady drift of gap and "
                                                 "origin, a re-levitation jump of the origin at E7), write it to "
                                                 "this CSV (truth next to it as .truth.json) and analyse "
                                                 "it.")] = None,
    seed: Annotated[int, typer.Option(callback=number(0), help="Seed of --example's noise.")] = 0,
    current_noise_ma: Annotated[float, typer.Option("--current-noise-ma", callback=number(0),
                                                    help="--example: std of each recorded current [mA].")] = 0.6,
    position_noise_um: Annotated[float, typer.Option(callback=number(0),
                                                     help="--example: std of each recorded position [µm].")] = 0.1,
    accept_implausible: AcceptOption = False,
    bearing: BearingOption = None,
):
    """Identify gap, origin (and k) window by window over a campaign; their drift per hour with its error, and
    the experiments at which the origin or gap jumps beyond drift and noise.

    Drift: weighted least-squares line over the windows' centre times (error scaled by sqrt(χ²/dof) when the
    windows scatter more than their error bars, and said so).  Change points: the jump at each boundary between
    experiments (or windows) fitted with the drift, the largest tested against a Bonferroni bound (α per
    parameter).  Exit 2 on bad input (file, row, column), 3 when fewer than 3 windows can be identified (no
    drift); windows that cannot be identified are listed with the reason.
    """
    from ambfit._output import write_json as write_json_file
    from ambfit.data import DataError, write_csv
    from ambfit.faces.cli.progress import progress_bar
    from ambfit.studies import campaign as study

    truth_path = None if example is None else example.with_suffix(".truth.json")
    check_output(json_out, table, example, truth_path, inputs=(data, bearing))
    if (data is None) == (example is None):
        fail("give a campaign data file, or --example FILE to simulate one (not both)")
    if window is not None and by is not None:
        fail("give either --window SECONDS (rolling windows) or --by COLUMN (one window per value), not both")
    if window is not None and not window > 0:
        fail(f"--window must be a positive number of seconds, got {window:g}")
    if step is not None and (window is None or not step > 0):
        fail("--step needs --window and a positive number of seconds")
    if not 0 < alpha < 1:
        fail(f"--alpha must lie between 0 and 1, got {alpha:g}")
    desc = bearing_of(bearing)
    enable_compilation_cache()
    if example is not None:
        from ambfit import rig
        from ambfit.rig.campaign import simulate_campaign

        # the campaign on the bearing given (the paper's by default): its biases and pairs scaled from the paper's
        # 1.4/1.6 A of 3 A and ±20 µm of a 60 µm clearance to this bearing's current limit and clearance
        base = rig.PAPER_RIG.bearing
        current, room = desc.max_current / base.max_current, desc.backup_clearance / base.backup_clearance
        sim = simulate_campaign(rig.RigSpec.for_bearing(desc), biases=(1.4 * current, 1.6 * current),
                                offset=20e-6 * room, noise=rig.Noise(current_noise_ma * 1e-3, position_noise_um * 1e-6),
                                seed=seed)
        write_csv(sim.data, example)
        write_json_file(truth_path, sim.truth)
        console.print(f"wrote {example} and {truth_path}: {len(sim.data)} readings, jump at "
                      f"{sim.truth['jump']['experiment']}")
        data = example
    ds = read_data(data, desc, accept_implausible)
    with progress_bar() as bar:
        try:
            res = study.analyse(ds, width_s=window, step_s=step, by=by, alpha=alpha, bearing=desc, progress=bar)
        except DataError as exc:
            fail(str(exc))
    _show(res, data.name)
    if json_out is not None:
        write_json(res.to_json(), json_out)
    if table is not None:
        from ambfit._output import formula_safe

        write_csv(formula_safe(res.table()), table)       # a label is never run by a spreadsheet
        note(f"wrote {table}")
    if len(res.used) < 3:
        fail(f"{data.name}: only {len(res.used)} window(s) identified: no drift can be estimated; use wider "
             "windows or --by experiment", 3)


def _pm(v, s, digits=2):
    from ambfit.estimation.units import pm

    return pm(float(v), float(s), digits)


def _show(res, name: str):
    import math

    from ambfit.estimation.units import GEOMETRY

    rows = []
    for j, w in enumerate(res.windows):
        row = {"window": w.label, "t (h)": f"{w.centre_s / 3600:.2f}", "rows": str(w.n_rows),
               "experiment": w.group}
        for p in GEOMETRY:
            v, s = w.estimate(p)
            row[f"{p} [µm]"] = _pm(v * 1e6, s * 1e6) if math.isfinite(v) else "–"
        row["χ²/dof"] = f"{w.fit.reduced_chi2:.2f}" if w.fit is not None else "–"
        row["status"] = "used" if j in res.used else ("identified" if w.identified else "NOT IDENTIFIED")
        rows.append(row)
    show_table(rows, f"campaign {name} ({res.mode}): {len(res.windows)} windows", left=("window", "experiment"))
    drift_rows = []
    for p, d in res.drifts.items():
        if isinstance(d, str):
            drift_rows.append({"parameter": p, "note": d})
            continue
        ph = d.per_hour()
        drift_rows.append({"parameter": p, "drift [µm/h]": _pm(ph[0] * 1e6, ph[1] * 1e6),
                           "[µm/s]": f"{d.slope * 1e6:+.3g}", "z": f"{d.z:+.1f}",
                           "χ²/dof": f"{d.reduced_chi2:.2f}" if math.isfinite(d.reduced_chi2) else "–",
                           "note": d.note()})
    show_table(drift_rows, "drift (weighted least-squares line over the windows' centre times)",
               left=("parameter", "note"))
    cp_rows = []
    for p, cp in res.changes.items():
        if isinstance(cp, str):
            continue
        final = {s.index: s for s in cp.flagged}
        for s in cp.tests:
            s = final.get(s.index, s)
            cp_rows.append({"parameter": p, "at": s.at, "jump [µm]": _pm(s.size * 1e6, s.std * 1e6),
                            "z": f"{s.z:+.1f}", "p (Bonferroni)": f"{s.p_bound:.2g}", "candidates": str(s.m),
                            "flagged": "YES" if s.flagged else "no"})
    if cp_rows:
        show_table(cp_rows, f"change points: the largest jump of each stage, drift removed (α = {res.alpha:g})",
                   left=("parameter", "at"))
    jumps = res.jumps
    if jumps:
        note("change point(s): " + "; ".join(f"{', '.join(n)} jump(s) at {where}" for where, n in jumps.items()))
    else:
        note(f"no change point: no jump beyond drift and noise at α = {res.alpha:g}")
    for w in res.failed:
        warn(f"{name}: window {w.label} ({w.n_rows} rows, {w.start_s:g}-{w.end_s:g} s) not identified: {w.problem}")
    for n in res.notes:
        note(n)
