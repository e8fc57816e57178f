"""``ambfit report`` and ``ambfit paper``: self-contained HTML pages."""

from __future__ import annotations

import sys
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
)
from ambfit.faces.cli.explore import MAX_DESIGN_STEPS
from ambfit.faces.cli.fitting import CurrentNoiseOption, Occam, OccamOption, PositionNoiseOption, declared_noise
from ambfit.faces.cli.options import number
from ambfit.faces.cli.sample import EMCEE_STEPS, MAX_ENSEMBLES, MAX_STEPS, MIN_STEPS

MAX_REPLICATES = 100_000
"""Most replicates of the paper's experiments (each simulates and fits every experiment of Tables 1-4)."""


@app.command()
def report(
    data: Annotated[Path, typer.Argument(help="Perturbation data, contract CSV.")],
    out: Annotated[Path, typer.Option("--out", "-o", help="Folder for index.html (self-contained, figures "
                                      "embedded) and report.json.")],
    steps: Annotated[int, typer.Option("--mcmc-steps", "--steps", callback=number(MIN_STEPS),
                                       help="emcee steps per ensemble to start the posterior with (extended "
                                       "until 50 autocorrelation times).")] = EMCEE_STEPS,
    max_steps: Annotated[int, typer.Option("--max-mcmc-steps", "--max-steps", callback=number(MIN_STEPS),
                                           help="Cap on the posterior's steps per ensemble.")] = MAX_STEPS,
    ensembles: Annotated[int, typer.Option(callback=number(2, MAX_ENSEMBLES),
                                           help="Independent emcee ensembles (R-hat across them).")] = 4,
    design_steps: Annotated[int, typer.Option("--next-steps", "--design-steps", callback=number(1, MAX_DESIGN_STEPS),
                                              help="How many next perturbations to recommend.")] = 8,
    max_radius_um: Annotated[float | None, typer.Option(callback=number(0, low_open=True),
                                                        help="Recommend only set-points within this distance "
                                                        "of the estimated bearing centre [µm] (default: the "
                                                        "bearing's back-up clearance less the origin's "
                                                        "uncertainty).")] = None,
    bearing: BearingOption = None,
    posterior: Annotated[bool, typer.Option(help="Sample the posterior (the slowest section).")] = True,
    diagnosis: Annotated[bool, typer.Option(help="Run the sim-to-real gap diagnosis.")] = True,
    seed: Annotated[int, typer.Option(callback=number(0), help="Sampler seed.")] = 0,
    current_noise_ma: CurrentNoiseOption = None,
    position_noise_um: PositionNoiseOption = None,
    accept_implausible: AcceptOption = False,
    occam: OccamOption = Occam.all,
):
    """One self-contained HTML page: identification table, posterior summary and pair plot, solution-space
    map, design recommendation and diagnosis."""
    from ambfit.data import DataError
    from ambfit.diagnosis import Rules
    from ambfit.faces import report as report_mod
    from ambfit.faces.cli.progress import progress_bar
    from ambfit.faces.report.dataset import FILES

    check_output(out, folder=True)
    check_output(*(out / name for name in FILES), parents=True, inputs=(data, bearing))
    if max_steps < steps:
        fail(f"--max-mcmc-steps {max_steps}: the cap is below --mcmc-steps {steps}")
    enable_compilation_cache()
    desc = bearing_of(bearing)
    read_data(data, desc, accept_implausible)      # input and plausibility problems end here, before any work
    try:
        with progress_bar() as bar:
            path, rec = report_mod.data_report(
                data, out, steps=steps, max_steps=max_steps, ensembles=ensembles, design_steps=design_steps,
                bearing=desc, max_radius_um=max_radius_um, do_posterior=posterior, do_diagnosis=diagnosis, seed=seed,
                command="ambfit report " + " ".join(sys.argv[2:]), progress=bar, rules=Rules(occam=occam.value),
                **declared_noise(current_noise_ma, position_noise_um))
    except (DataError, OSError) as exc:
        fail(str(exc))
    note(f"wrote {path}")
    if "error" in rec["least_squares"]:   # the page says why; the exit code says it to scripts
        raise typer.Exit(3)


@app.command()
def paper(
    out: Annotated[Path, typer.Option("--out", "-o", help="Folder for the reproduction report.")] = Path(
        "reports/paper"),
    replicates: Annotated[int, typer.Option(callback=number(1, MAX_REPLICATES),
                                            help="Repetitions of every experiment for the predicted spreads (the "
                                            "run's time grows with them).")] = 200,
    seed: Annotated[int, typer.Option(callback=number(0), help="Seed of the reproduction and the replicates.")] = 0,
    demonstration: Annotated[bool, typer.Option(help="Also simulate which effect explains the paper's gap "
                                                "excess and what separates the candidates (a diagnosis of each "
                                                "candidate).")] = True,
):
    """Rerun the seed paper's Tables 1-4 and Figs. 2, 3 and 5 on the virtual rig; write the side-by-side
    report (index.html, README.md, comparison.csv, spread.csv, reproduction.json, PNG figures)."""
    from ambfit.faces import report as report_mod
    from ambfit.faces.cli.progress import progress_bar
    from ambfit.faces.report.paper import FILES

    check_output(out, folder=True)
    check_output(*(out / name for name in FILES), parents=True)
    enable_compilation_cache()
    with progress_bar() as bar:
        path = report_mod.paper_report(out, replicates=replicates, seed=seed, demonstration=demonstration,
                                       command="ambfit paper " + " ".join(sys.argv[2:]), progress=bar)
    note(f"wrote {path}")
    # the summary and the spread table (paper vs prediction); every row of Tables 1-4 is in the report
    console.print((Path(out) / "README.md").read_text().split("## Table 1")[0], highlight=False)


