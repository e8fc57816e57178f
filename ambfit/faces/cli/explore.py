"""``ambfit solution-space``, ``design`` and ``diagnose``: the paper's Fig. 2, what to measure next, the sim-to-real gap."""

from __future__ import annotations

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
    fail,
    note,
    pair,
    read_data,
    show_table,
    warn,
    write_json,
)
from ambfit.faces.cli.fitting import CurrentNoiseOption, Occam, OccamOption, PositionNoiseOption, declared_noise
from ambfit.faces.cli.options import number, span

MAX_DESIGN_STEPS = 1_000
"""Most next steps design recommends (each is a search over the candidate set-points)."""


class Axis(str, Enum):
    v = "v"
    w = "w"


class Target(str, Enum):
    # ambfit.estimation.units.HEAD, spelt here: the command line imports no estimation module before a command
    # runs (test_cli_options holds the two equal)
    g_v0 = "g_v0"
    g_w0 = "g_w0"
    v0 = "v0"
    w0 = "w0"
    k_v = "k_v"
    k_w = "k_w"


class Criterion(str, Enum):
    A = "A"
    D = "D"


@app.command("solution-space")
def solution_space_cmd(
    data: Annotated[Path, typer.Argument(help="Perturbation data, contract CSV.")],
    png: Annotated[Path, typer.Option(help="Write the map here (PNG).")],
    axis: Annotated[Axis, typer.Option(help="Axis: v or w.")] = Axis.v,
    gap_um: Annotated[str | None, typer.Option(callback=span(0, low_open=True),
                                               help="Gap range 'low,high' [µm] (the paper's Fig. 2: 600,1000; "
                                               "default: centred on the fit, 10 standard errors or a quarter "
                                               "of the gap to each side, widened while the minimum is on the "
                                               "edge).")] = None,
    origin_um: Annotated[str | None, typer.Option(callback=span(),
                                                  help="Origin range 'low,high' [µm] (Fig. 2: -100,100; default: "
                                                  "centred on the fit, 10 standard errors or an eighth of the "
                                                  "gap to each side).")] = None,
    step_um: Annotated[float | None, typer.Option(callback=number(0, low_open=True),
                                                  help="Grid step [µm] (default: 1, coarser beyond 401 points "
                                                  "per axis); a grid too large to compute is refused with its "
                                                  "size.")] = None,
    current_noise_ma: CurrentNoiseOption = None,
    position_noise_um: PositionNoiseOption = None,
    accept_implausible: AcceptOption = False,
    bearing: BearingOption = None,
):
    """Map the misfit over a (gap, origin) grid (the paper's Fig. 2), with the least-squares ellipse
    and the weakest Fisher direction drawn on it.

    Exits 3 (after drawing the map) when the minimum lies on the grid's edge: the valley runs beyond the
    grid and the map does not show the best fit.
    """
    from ambfit.data import DataError
    from ambfit.estimation import conditioning, fit
    from ambfit.faces import plots
    from ambfit.faces.cli.progress import progress_bar

    check_output(png, inputs=(data, bearing))
    enable_compilation_cache()
    desc = bearing_of(bearing)
    noise = declared_noise(current_noise_ma, position_noise_um)
    ds = read_data(data, desc, accept_implausible)
    if None not in (gap_um, origin_um, step_um):      # (default ranges are known only after the fit)
        try:
            conditioning.grid_shape(pair(gap_um, 1e-6), pair(origin_um, 1e-6), step_um * 1e-6,
                                    int((ds.frame["axis"] == axis.value).sum()))
        except conditioning.GridSizeError as exc:
            fail(f"--step-um {step_um:g}: {exc}")
    with progress_bar(3) as bar:
        try:
            sub = ds.frame[ds.frame["axis"] == axis.value]
            bar.step("least squares")
            try:
                res = fit.fit(sub, bearing=desc, **noise)
            except fit.FitError as exc:
                warn(f"least squares not shown: {exc}")
                res = None
            bar.step("χ² map")
            space = conditioning.solution_space(ds, axis.value, gap=pair(gap_um, 1e-6),
                                                origin=pair(origin_um, 1e-6),
                                                step=None if step_um is None else step_um * 1e-6, weights_at=res,
                                                bearing=desc, **noise)
        except conditioning.GridSizeError as exc:
            fail(f"--step-um {step_um:g}: {exc}" if step_um is not None else str(exc))
        except (DataError, ValueError) as exc:
            fail(str(exc))
        bar.step("drawing")
        plots.save(plots.plot_solution_space(space, result=res), png)
    note(f"{space.summary()}; wrote {png}")
    if space.on_edge:
        fail(space.edge_text() + " (--gap-um, --origin-um)", 3)


@app.command()
def design(
    data: Annotated[Path, typer.Argument(help="Perturbation data so far, contract CSV.")],
    steps: Annotated[int, typer.Option("--next-steps", "--steps", callback=number(1, MAX_DESIGN_STEPS),
                                       help="How many next perturbations (set-point and bias) to recommend.")] = 8,
    target: Annotated[Target, typer.Option(help="Parameter whose variance to minimise (A-optimal).")] = Target.g_v0,
    criterion: Annotated[Criterion, typer.Option(help="'A' (variance of the target) or 'D' (log det of gap and "
                                                 "origin covariance).")] = Criterion.A,
    json_out: Annotated[Path | None, typer.Option("--json", help="Write the recommendation as JSON.")] = None,
    max_radius_um: Annotated[float | None, typer.Option(callback=number(0, low_open=True),
                                                        help="Only set-points within this distance of the "
                                                        "estimated bearing centre [µm] (default: the bearing's "
                                                        "back-up clearance, less the origin's uncertainty).")] = None,
    current_noise_ma: CurrentNoiseOption = None,
    position_noise_um: PositionNoiseOption = None,
    accept_implausible: AcceptOption = False,
    bearing: BearingOption = None,
    discriminate: Annotated[bool, typer.Option(help="Instead: diagnose the data and, when several effect families "
                                               "explain them alike (verdict undecided), say which protocol within "
                                               "the bearing's limits would tell them apart (expected log Bayes "
                                               "factor of each protocol scored).")] = False,
    occam: OccamOption = Occam.all,
    plan_out: Annotated[Path | None, typer.Option("--plan-out", help="With --discriminate: write the recommended "
                                                  "protocol's steps here (CSV: order, loads, set-points [µm], "
                                                  "biases [A]).")] = None,
):
    """Recommend the next perturbations (set-points [µm], bias [A]) that most reduce the target's uncertainty; with
    --discriminate, the protocol that best tells the diagnosis' undecided candidates apart."""
    from ambfit.data import DataError
    from ambfit.estimation import design as design_mod
    from ambfit.estimation import fit
    from ambfit.faces.cli.progress import progress_bar

    if plan_out is not None and not discriminate:
        fail("--plan-out writes the protocol --discriminate recommends: give --discriminate too")
    check_output(json_out, plan_out, inputs=(data, bearing))
    enable_compilation_cache()
    desc = bearing_of(bearing)
    ds = read_data(data, desc, accept_implausible)
    if discriminate:
        _discriminate(ds, desc, json_out, declared_noise(current_noise_ma, position_noise_um), occam.value, plan_out)
        return
    try:
        with progress_bar(2) as bar:
            bar.step("least squares")
            noise = declared_noise(current_noise_ma, position_noise_um)
            res = fit.fit(ds, bearing=desc, **noise)
            bar.step("choosing steps")
            rec = design_mod.recommend(ds, n_steps=steps, target=target.value, criterion=criterion.value,
                                       max_radius_um=max_radius_um, bearing=desc, result=res, **noise)
    except DataError as exc:
        fail(str(exc))
    except (fit.FitError, ValueError) as exc:
        fail(str(exc), 3)
    show_table(rec.display_rows(), rec.title)
    note(rec.limits)
    if json_out is not None:
        write_json(rec.to_json(), json_out)


def _discriminate(ds, desc, json_out, noise: dict, occam: str, plan_out: Path | None = None) -> None:
    """``design --discriminate``: the diagnosis' candidates and the protocols that would separate them."""
    from ambfit.data import DataError
    from ambfit.diagnosis import Rules
    from ambfit.diagnosis import diagnose as run_diagnosis
    from ambfit.estimation.core import FitError
    from ambfit.faces.cli.progress import progress_bar

    try:
        with progress_bar() as bar:
            dg = run_diagnosis(ds, bearing=desc, rules=Rules(occam=occam), progress=bar, check_force=False,
                               **noise)
    except (DataError, ValueError, OSError) as exc:
        fail(str(exc))
    except FitError as exc:
        fail(str(exc), 3)
    sep = dg.separation
    if dg.verdict == "undecided" and sep is None:
        note(f"undecided between {', '.join(dg.decision.candidates)}; no protocol within the bearing's limits "
             "could be scored for them")
        record = {"verdict": dg.verdict, "candidates": list(dg.decision.candidates), "separate_by": None}
    elif dg.verdict != "undecided":
        named = dg.decision.kind == "named"
        note(f"verdict: {dg.verdict}: nothing to tell apart" + (" (the data single it out)" if named else ""))
        if named and dg.confounded_with and occam != "none":
            note(f"{', '.join(dg.confounded_with)} explain these data too but did not count as rivals (more "
                 "flexible, or naming more families); --occam none weighs every other family's model")
        record = {"verdict": dg.verdict, "candidates": [], "separate_by": None}
    else:
        note(f"undecided between {', '.join(dg.decision.candidates)}; these data: expected log Bayes factor "
             f"{sep.on_these_data:.1f} for the weakest pair")
        show_table([{"protocol": k, "expected log Bayes factor": f"{v:.1f}"}
                    for k, v in sorted(sep.protocols.items(), key=lambda kv: -kv[1])],
                   "protocols within the bearing's limits (best first)", left=("protocol",))
        note(f"run: {sep.protocol}" + ("" if sep.separates else " (even that would not separate them clearly)"))
        if (current := sep.current_note()) is not None:
            note(current)
        record = {"verdict": dg.verdict, "candidates": list(dg.decision.candidates), "separate_by": sep.to_json()}
    if plan_out is not None:
        plan = sep.design if record["separate_by"] is not None else None
        if plan is None:
            warn(f"no protocol to run: {plan_out} not written")
        else:
            from ambfit._output import formula_safe, write_text

            write_text(plan_out, formula_safe(plan.steps()).to_csv(index=False))
            note(f"its {len(plan)} steps: {plan_out}")
    if json_out is not None:
        write_json(record, json_out)


@app.command()
def diagnose(
    data: Annotated[Path, typer.Argument(help="Perturbation data, contract CSV.")],
    json_out: Annotated[Path | None, typer.Option("--json", help="Write the contract section 3 JSON here.")] = None,
    current_noise_ma: CurrentNoiseOption = None,
    position_noise_um: PositionNoiseOption = None,
    bearing: BearingOption = None,
    accept_implausible: AcceptOption = False,
    pair_verdict: Annotated[bool, typer.Option(help="Let a pair of effects be the verdict when no single one "
                                               "explains the data (--no-pair-verdict: the pair is only reported as "
                                               "best_pair).")] = True,
    report: Annotated[Path | None, typer.Option(help="Write figures here: ranking.png and residuals.png "
                                                "(residuals against the most structured variable, before and "
                                                "after adding the verdict effect).")] = None,
    occam: OccamOption = Occam.all,
):
    """Where the ideal force model and the data disagree, which unmodelled effect explains it on held-out
    data, how far the gap shrinks, and how the identified parameters differ from the bearing as drawn."""
    from ambfit.data import DataError
    from ambfit.diagnosis import Rules, text
    from ambfit.diagnosis import diagnose as run_diagnosis
    from ambfit.estimation.core import FitError
    from ambfit.faces.cli.progress import progress_bar

    check_output(json_out, inputs=(data, bearing))
    check_output(report, folder=True)
    if report is not None:
        check_output(report / "ranking.png", report / "residuals.png", json_out, parents=True, inputs=(data, bearing))
    enable_compilation_cache()
    desc = bearing_of(bearing)
    ds = read_data(data, desc, accept_implausible)
    try:
        with progress_bar() as bar:
            dg = run_diagnosis(ds, bearing=desc, rules=Rules(occam=occam.value), pair_verdict=pair_verdict,
                               progress=bar,
                               **declared_noise(current_noise_ma, position_noise_um))
    except (DataError, ValueError, OSError) as exc:
        fail(str(exc))
    except FitError as exc:
        fail(str(exc), 3)
    note(text.floor(dg))
    show_table(text.where_rows(dg), "where the model fails (largest first)", left=("region",))
    show_table(text.ranking_rows(dg), "candidate effects, held-out (best first)", left=("effect",))
    note(text.verdict(dg))
    for line in text.flagged_parameters(dg):
        note(line)
    if json_out is not None:
        write_json(dg.to_json(), json_out)
    if report is not None:
        from ambfit.faces import plots

        report.mkdir(parents=True, exist_ok=True)
        plots.save(plots.plot_ranking(dg), report / "ranking.png")
        plots.save(plots.plot_diagnosis_residuals(dg), report / "residuals.png")
        note(f"wrote {report / 'ranking.png'} and {report / 'residuals.png'}")
