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
from ambfit.estimation.bayes import MAX_STEPS, N_STEPS
from ambfit.faces.report.render import figure, footer, render, table
from ambfit.faces.warnings import fit_warnings, plausibility_warnings, posterior_warnings
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


def summary_box(result, *, bearing, budget=None, post=None, diagnosed=None, spaces=None, instead=None,
                error=None, post_record: dict | None = None) -> dict:
    """The report's first box: the answer (least squares ± the readings' noise, u_combined with the calibration,
    the posterior beside it), the fit's health, the verdict in one line with its grade, and every warning the
    command line would print for the same data (:mod:`ambfit.faces.warnings`, the diagnosis' blind spot, a
    solution-space map whose minimum is on its edge).

    ``result``: the least-squares :class:`~ambfit.estimation.results.FitResult` (None with ``error``, why the fit
    failed); ``budget``, ``post``, ``diagnosed``: its :class:`~ambfit.estimation.budget.Budget`, the
    :class:`~ambfit.estimation.bayes.Posterior` and the :class:`~ambfit.diagnosis.Diagnosis`, each None when that
    section did not run; ``spaces``: ``{axis: SolutionSpace or exception}``; ``instead``: the current zeros'
    fit when identify would report it (:func:`ambfit.estimation.budget.fit_instead`); ``post_record``: the
    posterior's ``to_json()`` when at hand.
    """
    from ambfit.diagnosis import text
    from ambfit.estimation.units import CONTRACT_PARAMS, DISPLAY, pm, with_unit

    if result is None:
        return {"error": str(error), "table": None, "health": None, "verdict": None, "warnings": []}
    named = None          # the verdict's model, when the diagnosis names one: its parameters beside the ideal law's
    if diagnosed is not None and diagnosed.verdict not in ("none", "undecided", "unexplained"):
        named = diagnosed.verdict_fit
    rows = []
    for name, _, _ in CONTRACT_PARAMS:
        if name not in result.names:
            continue
        value, unit = with_unit(name, result.value(name), result.error(name))
        row = {"parameter": f"{name} [{unit}]", "least squares ± noise": value}
        if budget is not None:
            row["u_combined"] = f"{budget.u_combined(name) * DISPLAY[name][1]:.3g}"
        if post is not None and name in post.names:
            f = DISPLAY[name][1]
            row["posterior mean ± sd"] = pm(post.value(name) * f, post.error(name) * f)
        if named is not None and name in named.names:
            row[f"with {named.model} (the verdict)"] = with_unit(name, named.value(name), named.error(name))[0]
        rows.append(row)
    warnings = fit_warnings(result) + plausibility_warnings(result, bearing)
    if budget is not None and budget.failed:
        warnings.append(budget.failed_text())
    if instead is not None:
        warnings.append(f"{instead.text}: ambfit identify reports that fit (--no-fit-current-zeros: this one)")
    if post is not None:
        warnings += posterior_warnings(post, post_record)
    warnings += [f"{sp.edge_text()}" for sp in (spaces or {}).values() if not isinstance(sp, Exception) and sp.on_edge]
    verdict = None
    if diagnosed is not None:
        verdict = {"text": text.headline(diagnosed), "kind": diagnosed.verdict if diagnosed.verdict in (
            "none", "undecided", "unexplained") else "named"}
        if blind := text.blind_spot(diagnosed):
            warnings.append(blind)
    health = {"converged": result.converged, "adequate": result.adequate, "reduced_chi2": result.reduced_chi2,
              "dof": result.dof, "p_value": result.p_value}
    return {"error": None, "table": table(pd.DataFrame(rows)), "health": health, "verdict": verdict,
            "warnings": warnings}


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
            "dof": result.dof, "p_value": result.p_value, "adequate": result.adequate,
            "condition": result.condition, "weak_direction": result.weak_direction,
            "noise_source": result.noise_source, "closed_form": closed is not None, "closed_error": closed_error,
            "budget": budget is not None, "warnings": fit_warnings(result)}


def posterior(result, *, draw: bool = True, record: dict | None = None) -> dict:
    """Posterior summary, sampler settings and diagnostics, and the pair plot (``draw``).

    ``result``: :class:`~ambfit.estimation.bayes.Posterior`; ``record``: its ``to_json()`` when at hand."""
    rec = record if record is not None else result.to_json()
    post = pd.DataFrame(result.display_rows(rec["hdi_prob"]))
    pair = None
    if draw:
        from ambfit.faces import plots

        pair = figure(plots.plot_pair(result, result=result.ls))
    agree = rec["least_squares_agreement"]
    return {"table": table(post, 4), "n_ensembles": int(result.draws.shape[0]), "n_steps": result.n_steps,
            "n_walkers": result.n_walkers, "tau_max": float(np.max(result.tau)), "message": result.message,
            "converged": rec["converged"], "figure": pair, "sampler": result.sampler,
            "agreement": {n: agree["z"][n] for n in agree["z"]}, "threshold": agree["threshold"],
            "disagreement": agree["text"], "hdi_prob": rec["hdi_prob"]}


def solution_space(spaces: dict, result, *, sigmas=(1, 2, 3), outer_levels=(50, 200, 1000), zooms=None) -> dict:
    """The Δχ² maps over (origin, gap), one column per axis: the wide map (the valley's extent, contours at
    ``outer_levels``) above a zoom on the least-squares point (contours at the Δχ² of ``sigmas`` in 2-D: 2.3, 6.2,
    11.8), each contour labelled with its Δχ².

    ``spaces``: ``{axis: SolutionSpace}`` (:func:`ambfit.estimation.conditioning.solution_space`), an
    exception in place of a map that could not be computed; ``zooms``: the same of the fine grids about the
    minimum (None: no zoom row); ``result``: the least-squares :class:`~ambfit.estimation.results.FitResult`
    drawn on top.
    """
    from matplotlib.figure import Figure
    from scipy.stats import chi2, norm

    from ambfit.faces import plots

    coverage = [1 - 2 * norm.sf(s) for s in sigmas]
    levels = [float(chi2.ppf(c, 2)) for c in coverage]
    rows = [(spaces, tuple(outer_levels), "wide")] + ([(zooms, tuple(levels), "zoom")] if zooms else [])
    fig = Figure(figsize=(12, 4.8 * len(rows)))
    grid = np.atleast_2d(fig.subplots(len(rows), len(spaces)))
    for r, (maps, lv, kind) in enumerate(rows):
        for ax, (axis, space) in zip(grid[r], maps.items()):
            if isinstance(space, Exception):
                ax.text(0.5, 0.5, f"axis {axis}: {space}", ha="center", wrap=True)
                continue
            plots.plot_solution_space(space, result=result, ax=ax, levels=lv, label_contours=True)
            ax.set_title(f"axis {axis}: " + ("the whole valley" if kind == "wide" else
                                             "zoom on the least-squares point"), fontsize=10)
    edges = [space.edge_text() for space in spaces.values() if not isinstance(space, Exception) and space.on_edge]
    return {"figure": figure(fig), "levels": levels, "outer_levels": list(outer_levels),
            "coverage_percent": [c * 100 for c in coverage], "edges": edges, "zoom": bool(zooms), "zoom_sds": ZOOM_SDS}


ZOOM_SDS = 5.0
"""Half-width of the solution-space zoom in standard errors of the least-squares gap and origin."""


def zoom_ranges(result, axis: str, sds: float = ZOOM_SDS):
    """Gap and origin ranges [m] of ``sds`` standard errors about the least-squares point of ``axis`` and a step
    of a 160th of the narrower span (fine enough to draw the 1-3 sigma contours), coarser where the wider span
    would pass 600 points."""
    g, x = result.value(f"g_{axis}0"), result.value(f"{axis}0")
    sg, sx = result.error(f"g_{axis}0"), result.error(f"{axis}0")
    step = max(2 * sds * min(sg, sx) / 160, 2 * sds * max(sg, sx) / 600)
    return (g - sds * sg, g + sds * sg), (x - sds * sx, x + sds * sx), step


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
            "bias_A": (float(grid["bias_A"].min()), float(grid["bias_A"].max())), "kept_among_run": rec.margin_reason,
            "remedy": rec.remedy, "limits": rec.limits}


def diagnosis(result, *, draw: bool = True, max_regions: int = 8) -> dict:
    """Verdict, noise floor, ranking of the candidate effects, structured regions and flagged parameters.

    ``result``: :class:`~ambfit.diagnosis.Diagnosis`."""
    from ambfit.diagnosis import text
    from ambfit.faces.plots.diagnosis import VARIABLE_LABELS

    nf = result.noise_floor
    rows = []
    for c in result.ranking:
        rec = c.to_json(result.ideal)
        rows.append({"effect": c.effect, "held-out RMS z": rec["heldout_rms_after"],
                     "held-out excess [noise units]": c.after, "shrink": c.shrink, "ΔAIC": rec["delta_aic"],
                     "fit": "converged" if c.fit.converged else "not converged"})
    ranking = pd.DataFrame(rows)
    regions = [{"region": r.describe(), "rows": r.rows, "z": r.z} for r in result.where.regions[:max_regions]]
    bars = correction = resid = None
    if draw:
        from ambfit.faces import plots

        bars = figure(plots.plot_ranking(result))
        resid = figure(plots.plot_diagnosis_residuals(result))
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
            "discrepancy_figure": correction, "headline": text.headline(result), "blind_spot": text.blind_spot(result),
            "residuals_figure": resid, "residual_variable": VARIABLE_LABELS.get(result.most_structured_variable,
                                                                               result.most_structured_variable),
            "verdict_model": result.grade.model if result.grade is not None else None}


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
              do_diagnosis, seed, progress=None, noise=None, found: dict | None = None, rules=None) -> dict:
    """Sections 1-5 after a successful least-squares fit ``res``; fills ``record`` with each result's JSON and
    ``found`` with the results themselves (``budget``, ``post``, ``diagnosed``, ``spaces``: the summary box's).
    ``noise``: the declared ``sigma_i``/``sigma_x`` (:func:`data_report`)."""
    noise = noise or {}
    found = {} if found is None else found
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
        from ambfit.estimation.budget import budget, fit_instead

        b = budget(ds, res, **noise)
        b.merge(record["least_squares"]["params"])
        instead = fit_instead(ds, res, b, **noise)
        if instead is not None:
            record["least_squares"]["uncertainty_budget"] = {"fit_instead": instead.to_json()}
            found["instead"] = instead
    found["budget"] = b
    out = {"identification": identification(res, closed, b)}

    def sample():
        sr = bayes.sample(ds, n_ensembles=ensembles, n_steps=steps, max_steps=max_steps, seed=seed, ls=res,
                          bearing=bearing, progress=progress, **noise)
        record["bayes"] = sr.to_json()
        found["post"], found["post_record"] = sr, record["bayes"]
        return posterior(sr, record=record["bayes"])

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
    found["spaces"] = spaces
    zooms = {}
    for axis in ("v", "w"):
        try:
            gap, origin, step = zoom_ranges(res, axis)
            zooms[axis] = conditioning.solution_space(ds, axis, gap=gap, origin=origin, step=step, weights_at=res,
                                                      bearing=bearing, **noise)
        except Exception as exc:  # noqa: BLE001 - the panel says why, the other axis still stands
            zooms[axis] = exc
    out["solution_space"] = _attempt("Solution space", lambda: solution_space(spaces, res, zooms=zooms))

    def recommend():
        rec = design_mod.recommend(ds, n_steps=design_steps, target="g_v0", result=res, max_radius_um=max_radius_um,
                                   bearing=bearing, **noise)
        record["design"] = {k: v for k, v in rec.to_json().items() if k in ("std_now", "steps")}
        return design(rec, max_radius_um=max_radius_um)

    _step(progress, "design")
    out["design"] = _attempt("Design recommendation", recommend)

    def diagnose():
        from ambfit import diagnosis as gap

        dg = gap.diagnose(ds, bearing=bearing, baseline=res, progress=progress, rules=rules, **noise)
        record["diagnosis"] = dg.to_json()
        found["diagnosed"] = dg
        return diagnosis(dg)

    _step(progress, "diagnosis")
    out["diagnosis"] = _attempt("Diagnosis", diagnose) if do_diagnosis else skipped("--no-diagnosis")
    return out


FILES = ("index.html", "report.json")
"""The files :func:`data_report` writes into its folder (the command line checks them before the work)."""


def data_report(data_path, out, *, steps: int = N_STEPS, max_steps: int = MAX_STEPS, ensembles: int = 4, design_steps: int = 8,
                bearing=PAPER_BEARING, max_radius_um: float | None = None, do_posterior: bool = True,
                do_diagnosis: bool = True, seed: int = 0, command: str = "", progress=None, sigma_i: float | None = None,
                sigma_x: float | None = None, rules=None) -> tuple[Path, dict]:
    """Identify, sample, map, design and diagnose one contract CSV; write ``out/index.html`` (self-contained)
    and ``out/report.json``.  Returns the HTML path and the JSON record.  Sections that cannot run (e.g. the
    closed form on non-symmetric pairs) say why instead of stopping the report; when least squares fails,
    the page says why and the record's ``least_squares`` holds the ``error``.  ``progress``, if given, is
    called as ``progress("report: <section>", done, total)`` as each section starts (and by the diagnosis as
    ``progress("candidate effects", done, total)``, and by the sampler, :func:`ambfit.estimation.bayes.sample`).
    ``sigma_i`` [A] and ``sigma_x`` [m] declare the readings' noise for every fit of the report (as in
    :func:`ambfit.estimation.fit.fit`; default: the std columns, else estimated).  ``rules``: the diagnosis'
    thresholds (:class:`ambfit.diagnosis.Rules`; default: its defaults).

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
    found = {}
    try:
        res = fit(ds, bearing=bearing, sigma_i=sigma_i, sigma_x=sigma_x)
    except FitError as exc:
        record["least_squares"] = {"error": str(exc)}
        sections["identification"] = failed("Least squares", exc)
        sections["summary"] = summary_box(None, bearing=bearing, error=exc)
    else:
        record["least_squares"] = res.to_json()
        sections |= _sections(ds, res, record, steps=steps, max_steps=max_steps, ensembles=ensembles, design_steps=design_steps,
                              bearing=bearing, max_radius_um=max_radius_um, do_posterior=do_posterior,
                              do_diagnosis=do_diagnosis, seed=seed, progress=progress,
                              noise=dict(sigma_i=sigma_i, sigma_x=sigma_x), found=found, rules=rules)
        sections["summary"] = summary_box(res, bearing=bearing, **found)
    record["warnings"] = sections["summary"]["warnings"]
    _step(progress, "writing")
    write_json(out / "report.json", record, default=float)
    html_path = out / "index.html"
    command = command or f"ambfit report {data_path} --out {out}"
    write_text(html_path, render("data.html.j2", title=f"ambfit report: {Path(data_path).name}", sections=sections,
                                footer=footer(command, time.perf_counter() - t0)))
    return html_path, record
