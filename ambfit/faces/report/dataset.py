"""The report of one data set (``ambfit report DATA.csv --out DIR``).

:func:`data_report` identifies the data (least squares and the paper's closed form),
samples the posterior, maps the solution space, recommends the next perturbations and
diagnoses the sim-to-real gap.  Each section is one function of its result
(:func:`identification` of a :class:`~ambfit.estimation.results.FitResult`,
:func:`posterior` of a :class:`~ambfit.estimation.bayes.Posterior`, ...) returning the
context of its macro in ``templates/data_sections.html.j2``; the prose is in the template,
every number in it comes from the result.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import pandas as pd

from ambfit._output import write_json, write_text
from ambfit.faces.report.render import figure, footer, render, table
from ambfit.physics.bearing import PAPER_BEARING


def failed(what: str, exc: BaseException | str) -> dict:
    """The context of a section that could not run: what failed and why."""
    return {"failed": what, "message": str(exc)}


def skipped(reason: str) -> dict:
    """The context of a section left out on request."""
    return {"reason": reason}


def overview(path, data) -> dict:
    """The data set at a glance: file, readings, experiments, load groups (``data``: a :class:`ambfit.data.Dataset`)."""
    df = data.frame
    return {"path": str(path), "n_rows": len(df),
            "n_experiments": int(df["experiment"].nunique()) if "experiment" in df else 1,
            "n_load_groups": int(df["load_id"].nunique()) if "load_id" in df else 1}


def identification(result, closed=None, budget=None) -> dict:
    """Least-squares estimates beside the closed form's.

    ``result``: :class:`~ambfit.estimation.results.FitResult`; ``closed``: a
    :class:`~ambfit.estimation.closed_form.ClosedFormResult`, the
    :class:`~ambfit.estimation.closed_form.ClosedFormError` that says why it does not apply, or None;
    ``budget``: its :class:`~ambfit.estimation.budget.Budget` (the combined uncertainty and its largest term).
    """
    from ambfit.estimation.budget import NOISE_TERM
    from ambfit.estimation.units import CONTRACT_PARAMS, DISPLAY, pm, with_unit

    closed_error = str(closed) if isinstance(closed, Exception) else None
    cf = closed.params() if closed is not None and closed_error is None else None
    rows = []
    for name, key, _ in CONTRACT_PARAMS:
        if name not in result.names:
            continue
        text, unit = with_unit(name, result.value(name), result.error(name))
        row = {"parameter": f"{name} [{unit}]", "least squares": text}
        if budget is not None:
            top = next((b for b in budget.shares(name) if b[0] != NOISE_TERM), None)
            row["u_combined (with calibration)"] = f"{budget.u_combined(name) * DISPLAY[name][1]:.3g}"
            row["largest calibration term"] = "–" if top is None else f"{top[0]} ({100 * top[2]:.0f} %)"
        if cf is not None:       # the closed form's block is in the contract's units, which are the display units
            c = cf.get(key)
            row["closed form (Eq. 5-7)"] = "–" if c is None else pm(c["value"], np.nan if c["std"] is None else c["std"])
        rows.append(row)
    ident = pd.DataFrame(rows)
    return {"table": table(ident), "converged": result.converged, "reduced_chi2": result.reduced_chi2,
            "dof": result.dof, "condition": result.condition, "weak_direction": result.weak_direction,
            "noise_source": result.noise_source, "closed_form": closed is not None, "closed_error": closed_error,
            "budget": budget is not None}


def posterior(result, *, draw: bool = True) -> dict:
    """Posterior summary, sampler settings and diagnostics, and the pair plot (``draw``).

    ``result``: :class:`~ambfit.estimation.bayes.Posterior`."""
    rec = result.to_json()
    post = pd.DataFrame(result.display_rows(rec["hdi_prob"]))
    pair = None
    if draw:
        from ambfit.faces import plots

        pair = figure(plots.plot_pair(result, result=result.ls))
    return {"table": table(post, 4), "n_ensembles": int(result.draws.shape[0]), "n_steps": result.n_steps,
            "n_walkers": result.n_walkers, "tau_max": float(np.max(result.tau)), "message": result.message,
            "converged": rec["converged"], "figure": pair}


def solution_space(spaces: dict, result, *, sigmas=(1, 2, 3), outer_levels=(50, 200, 1000)) -> dict:
    """The Δχ² maps over (origin, gap), one panel per axis, with contours at ``sigmas`` (2-D coverage).

    ``spaces``: ``{axis: SolutionSpace}`` (:func:`ambfit.estimation.conditioning.solution_space`), an
    exception in place of a map that could not be computed; ``result``: the least-squares
    :class:`~ambfit.estimation.results.FitResult` drawn on top.
    """
    from matplotlib.figure import Figure
    from scipy.stats import chi2, norm

    from ambfit.faces import plots

    coverage = [1 - 2 * norm.sf(s) for s in sigmas]
    levels = [float(chi2.ppf(c, 2)) for c in coverage]
    fig = Figure(figsize=(12, 4.8))
    for ax, (axis, space) in zip(np.atleast_1d(fig.subplots(1, len(spaces))), spaces.items()):
        if isinstance(space, Exception):
            ax.text(0.5, 0.5, f"axis {axis}: {space}", ha="center", wrap=True)
        else:
            plots.plot_solution_space(space, result=result, ax=ax, levels=(*levels, *outer_levels))
    edges = [space.edge_text() for space in spaces.values() if not isinstance(space, Exception) and space.on_edge]
    return {"figure": figure(fig), "levels": levels, "coverage_percent": [c * 100 for c in coverage], "edges": edges}


def design(recommendation, *, max_radius_um: float | None = None, candidates: pd.DataFrame | None = None) -> dict:
    """The recommended next steps with the target's predicted standard error after each.

    ``recommendation``: :class:`~ambfit.estimation.design.Recommendation`; ``candidates``: the grid it chose
    from (default: the recommendation's own, :func:`ambfit.estimation.design.candidate_steps` of the bearing
    centred on the estimated bearing centre and cut to the bearing's limits).  ``max_radius_um``: the
    distance from the estimated bearing centre the set-points were kept within [µm] (default: the
    recommendation's, the back-up clearance less the origin's uncertainty).
    """
    from ambfit.estimation import design as design_mod
    from ambfit.estimation.units import display

    rec = recommendation
    factor, unit = display(rec.target, 1.0)
    steps = rec.steps.copy()
    steps.insert(0, "step", np.arange(1, len(steps) + 1))
    if "predicted_std_after" in steps:
        steps[f"{rec.target} std after [{unit}]"] = steps.pop("predicted_std_after") * factor
    grid = candidates if candidates is not None else rec.candidates
    grid = design_mod.candidate_steps() if grid is None else grid
    radius = max_radius_um if max_radius_um is not None else rec.radius_um
    return {"table": table(steps, 2), "target": rec.target, "criterion": rec.criterion, "std_now": rec.std_now * factor,
            "unit": unit, "offset_um": float(np.ptp(grid["v_set_um"]) / 2), "max_radius_um": radius,
            "bias_A": (float(grid["bias_A"].min()), float(grid["bias_A"].max()))}


def diagnosis(result, *, draw: bool = True, max_regions: int = 8) -> dict:
    """Verdict, noise floor, ranking of the candidate effects, structured regions and flagged parameters.

    ``result``: :class:`~ambfit.diagnosis.Diagnosis`."""
    from ambfit.diagnosis import text

    nf = result.noise_floor
    rows = []
    for c in result.ranking:
        rec = c.to_json(result.ideal)
        rows.append({"effect": c.effect, "held-out RMS z": rec["heldout_rms_after"],
                     "held-out excess [noise units]": c.after, "shrink": c.shrink, "ΔAIC": rec["delta_aic"],
                     "fit": "converged" if c.fit.converged else "not converged"})
    ranking = pd.DataFrame(rows)
    regions = [{"region": r.describe(), "rows": r.rows, "z": r.z} for r in result.where.regions[:max_regions]]
    bars = correction = None
    if draw:
        from ambfit.faces import plots

        bars = figure(plots.plot_ranking(result))
        if result.ceiling is not None:
            correction = figure(plots.plot_discrepancy(result))
    rms_before = float(np.sqrt(result.ideal.score))
    return {"verdict": result.verdict, "confounded_with": list(result.confounded_with), "shrink": result.shrink,
            "noise_source": nf.source, "mean_z2": nf.mean_z2, "expected_mean_z2": nf.expected_mean_z2,
            "heldout_excess_before": result.heldout_excess_before, "heldout_rms_before": rms_before,
            "on_floor": not result.heldout_excess_before > 0, "folds": result.folds,
            "ranking": table(ranking, 3) if rows else None, "figure": bars, "where": regions,
            "n_regions": len(result.where.regions), "flagged": text.flagged_parameters(result),
            "force_check": _force_table(result.force_check), "notes": text.findings(result),
            "discrepancy_figure": correction}


def _force_table(fc):
    """Leave-one-load-out force measurement of each model (a :class:`~ambfit.diagnosis.checks.ForceCheck`) as a
    table (percent of the known load)."""
    if fc is None or fc.error is not None:
        return None
    rows = []
    for _, e in fc.models():
        rows.append({"model": e.model or "ideal", "RMS per reading [%]": 100 * e.rms_rel,
                     "worst reading [%]": 100 * e.max_rel,
                     "RMS of each load's mean [%]": 100 * e.rms_rel_mean if e.rms_rel_mean is not None else np.nan,
                     "beyond the readings' noise [%]": 100 * e.model_error_rel if e.model_error_rel is not None
                     else np.nan})
    if fc.ideal.noise_floor_rel is not None:
        rows.append({"model": "the readings' noise alone", "RMS per reading [%]": 100 * fc.ideal.noise_floor_rel,
                     "worst reading [%]": np.nan, "RMS of each load's mean [%]": np.nan,
                     "beyond the readings' noise [%]": np.nan})
    return table(pd.DataFrame(rows), 3)


def _attempt(what: str, compute) -> dict:
    """``compute()``, or the failed section's context: one failed section must not lose the rest of the report."""
    try:
        return compute()
    except Exception as exc:  # noqa: BLE001 - reported on the page, the rest still stands
        return failed(what, exc)


SECTIONS = ("least squares", "closed form", "posterior", "solution space", "design", "diagnosis", "writing")
"""The report's steps in order, as its ``progress`` callback names them."""


def _step(progress, name: str) -> None:
    if progress is not None:
        progress(f"report: {name}", SECTIONS.index(name), len(SECTIONS))


def _sections(ds, res, record: dict, *, steps, max_steps, ensembles, design_steps, bearing, max_radius_um, do_posterior,
              do_diagnosis, seed, progress=None, noise=None) -> dict:
    """Sections 1-5 after a successful least-squares fit ``res``; fills ``record`` with each result's JSON.
    ``noise``: the declared ``sigma_i``/``sigma_x`` (:func:`data_report`)."""
    noise = noise or {}
    from ambfit.estimation import bayes, closed_form, conditioning
    from ambfit.estimation import design as design_mod

    _step(progress, "closed form")
    try:
        closed = closed_form.identify(ds, bearing=bearing, reference=res)
        record["closed_form"] = closed.to_json()
    except closed_form.ClosedFormError as exc:
        closed = exc
    b = None
    if res.converged and res.well_conditioned:
        from ambfit.estimation.budget import budget

        b = budget(ds, res, **noise)
        b.merge(record["least_squares"]["params"])
    out = {"identification": identification(res, closed, b)}

    def sample():
        sr = bayes.sample(ds, n_ensembles=ensembles, n_steps=steps, max_steps=max_steps, seed=seed, ls=res,
                          bearing=bearing, progress=progress, **noise)
        record["bayes"] = sr.to_json()
        return posterior(sr)

    _step(progress, "posterior")
    out["posterior"] = _attempt("Posterior sampling", sample) if do_posterior else skipped("--no-posterior")
    _step(progress, "solution space")
    spaces = {}
    for axis in ("v", "w"):
        try:
            spaces[axis] = conditioning.solution_space(ds, axis, weights_at=res, bearing=bearing, **noise)
        except Exception as exc:  # noqa: BLE001 - the panel says why, the other axis still stands
            spaces[axis] = exc
    record["solution_space"] = {
        axis: {"gap_um": [sp.gap[0] * 1e6, sp.gap[-1] * 1e6], "origin_um": [sp.origin[0] * 1e6, sp.origin[-1] * 1e6],
               "minimum_um": [m * 1e6 for m in sp.minimum], "on_edge": sp.on_edge}
        for axis, sp in spaces.items() if not isinstance(sp, Exception)}
    out["solution_space"] = _attempt("Solution space", lambda: solution_space(spaces, res))

    def recommend():
        rec = design_mod.recommend(ds, n_steps=design_steps, target="g_v0", result=res, max_radius_um=max_radius_um,
                                   bearing=bearing, **noise)
        record["design"] = {k: v for k, v in rec.to_json().items() if k in ("std_now", "steps")}
        return design(rec, max_radius_um=max_radius_um)

    _step(progress, "design")
    out["design"] = _attempt("Design recommendation", recommend)

    def diagnose():
        from ambfit import diagnosis as gap

        dg = gap.diagnose(ds, bearing=bearing, baseline=res, progress=progress, **noise)
        record["diagnosis"] = dg.to_json()
        return diagnosis(dg)

    _step(progress, "diagnosis")
    out["diagnosis"] = _attempt("Diagnosis", diagnose) if do_diagnosis else skipped("--no-diagnosis")
    return out


FILES = ("index.html", "report.json")
"""The files :func:`data_report` writes into its folder (the command line checks them before the work)."""


def data_report(data_path, out, *, steps: int = 3000, max_steps: int = 30000, ensembles: int = 4, design_steps: int = 8,
                bearing=PAPER_BEARING, max_radius_um: float | None = None, do_posterior: bool = True,
                do_diagnosis: bool = True, seed: int = 0, command: str = "", progress=None, sigma_i: float | None = None,
                sigma_x: float | None = None) -> tuple[Path, dict]:
    """Identify, sample, map, design and diagnose one contract CSV; write ``out/index.html`` (self-contained)
    and ``out/report.json``.  Returns the HTML path and the JSON record.  Sections that cannot run (e.g. the
    closed form on non-symmetric pairs) say why instead of stopping the report; when least squares fails,
    the page says why and the record's ``least_squares`` holds the ``error``.  ``progress``, if given, is
    called as ``progress("report: <section>", done, total)`` as each section starts (and by the diagnosis as
    ``progress("candidate effects", done, total)``, and by the sampler, :func:`ambfit.estimation.bayes.sample`).
    ``sigma_i`` [A] and ``sigma_x`` [m] declare the readings' noise for every fit of the report (as in
    :func:`ambfit.estimation.fit.fit`; default: the std columns, else estimated).

    Raises :class:`ambfit.data.DataError` when the file does not meet the data contract.
    """
    from ambfit.data import read_csv
    from ambfit.estimation.fit import FitError, fit

    t0 = time.perf_counter()
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    ds = read_csv(data_path)
    record = {"data": str(data_path), "n_rows": len(ds.frame)}
    sections = {"overview": overview(data_path, ds)}
    _step(progress, "least squares")
    try:
        res = fit(ds, bearing=bearing, sigma_i=sigma_i, sigma_x=sigma_x)
    except FitError as exc:
        record["least_squares"] = {"error": str(exc)}
        sections["identification"] = failed("Least squares", exc)
    else:
        record["least_squares"] = res.to_json()
        sections |= _sections(ds, res, record, steps=steps, max_steps=max_steps, ensembles=ensembles, design_steps=design_steps,
                              bearing=bearing, max_radius_um=max_radius_um, do_posterior=do_posterior,
                              do_diagnosis=do_diagnosis, seed=seed, progress=progress,
                              noise=dict(sigma_i=sigma_i, sigma_x=sigma_x))
    _step(progress, "writing")
    write_json(out / "report.json", record, default=float)
    html_path = out / "index.html"
    command = command or f"ambfit report {data_path} --out {out}"
    write_text(html_path, render("data.html.j2", title=f"ambfit report: {Path(data_path).name}", sections=sections,
                                footer=footer(command, time.perf_counter() - t0)))
    return html_path, record
