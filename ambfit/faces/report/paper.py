"""The seed paper's report (``ambfit paper --out reports/paper``).

:func:`paper_report` reruns the paper's Tables 1-4 and Figs. 2, 3 and 5 on the virtual
rig (:func:`ambfit.studies.paper.reproduce`) and sets them beside the paper: a
self-contained ``index.html`` (``templates/paper.html.j2``), a Markdown summary
(``templates/paper_readme.md.j2``), the comparison as CSV and JSON, and the figures as
PNG.  The sections' contexts come from :mod:`ambfit.faces.report.paper_sections`.
"""

from __future__ import annotations

import time
from pathlib import Path

from ambfit._output import write_bytes, write_json, write_text
from ambfit.faces.report import paper_sections as sec
from ambfit.faces.report.render import footer, img, markdown, plain, png_bytes, render, section
from ambfit.studies import paper as study
from ambfit.studies import paper_gap

FIGURES = ("fig2_solution_space.png", "fig2_map.png", "fig3_position_pairs.png", "fig3_position_pairs_table4.png",
           "fig5_iterations.png", "spread.png")
FILES = ("index.html", "README.md", "comparison.csv", "spread.csv", "origins_over_time.csv", "reproduction.json",
         *FIGURES)
"""The files :func:`paper_report` writes into its folder (the command line checks them before the work)."""

PROSE = ("intro", "calibration", "gap_spread", "origin_spread", "eq7_bias")
"""The paragraphs of the paper report that the Markdown summary repeats, in order."""


def _fig2_least_squares(result):
    """Fig. 2's least-squares point for the record: (g_v0, its se, v0, its se [µm], correlation), or why not."""
    if isinstance(result, Exception):
        return str(result)
    names = result.names
    return (result.value("g_v0") * 1e6, result.error("g_v0") * 1e6, result.value("v0") * 1e6,
            result.error("v0") * 1e6, float(result.corr[names.index("g_v0"), names.index("v0")]))


def _figures(out: Path, rep, space, fig2_fit, spread) -> dict:
    """Draw the report's figures once: each is written as PNG and kept as the page's embedded copy."""
    from ambfit.faces import plots

    clearance = rep.spec.bearing.backup_clearance
    drawings = {
        "fig2_solution_space.png": lambda: plots.plot_fig2_surface(space),
        "fig2_map.png": lambda: plots.plot_solution_space(
            space, result=None if isinstance(fig2_fit, Exception) else fig2_fit),
        "fig3_position_pairs.png": lambda: plots.plot_fig3_positions(rep.searches[rep.table2_index],
                                                                     backup_clearance=clearance),
        "fig3_position_pairs_table4.png": lambda: plots.plot_fig3_positions(
            rep.searches[sec.widest_shifted_row(rep)], backup_clearance=clearance),
        "fig5_iterations.png": lambda: plots.plot_fig5_iterations(rep),
        "spread.png": lambda: plots.plot_spread(spread),
    }
    figs = {}
    for name in FIGURES:                 # (the names the command line checks before the work)
        data = png_bytes(drawings[name]())
        write_bytes(out / name, data)
        figs[name.removesuffix(".png")] = img(data)
    return figs


def _record(rep, *, seed, space, fig2_fit, bias_check, published, demo) -> dict:
    """``reproduction.json``: every number of the report, by table."""
    return {"replicates": int(rep.replicates.shape[0]), "failed": rep.failed, "seed": seed,
            "noise": {"current_mA": rep.noise.current * 1e3, "position_um": rep.noise.position * 1e6},
            "seconds_reproduction": rep.seconds, "comparison": rep.comparison().to_dict(orient="records"),
            "spread": rep.spread().to_dict(orient="records"),
            "autocorrelation": rep.autocorrelation().to_dict(orient="records"),
            "between_experiment_sd": rep.between_experiment_sd().to_dict(orient="records"),
            "noise_calibration": rep.noise_calibration(), "table2_trend": rep.trend().to_dict(orient="records"),
            "fig2": {"grid": list(space.chi2.shape), "minimum_um": [m * 1e6 for m in space.minimum],
                     "least_squares": _fig2_least_squares(fig2_fit)},
            "published_gap": published, "gap_demonstration": demo,
            "bias_pair_check": bias_check.to_dict(orient="records")}


def sections(rep, *, fig2_data, space, fig2_fit, bias_check, published, demo) -> dict:
    """Every section's context (the page and the Markdown summary render the same ones)."""
    return {"intro": sec.intro(rep), "spread": sec.spread(rep), "calibration": sec.calibration(rep),
            "gap_spread": sec.gap_spread(rep), "origin_spread": sec.origin_spread(rep, bias_check),
            "origins_over_time": sec.origins_over_time(),
            "eq7_bias": sec.eq7_bias(rep), "supplements": sec.supplements(rep, bias_check),
            "tables": [sec.side_by_side(rep, t) for t in (1, 2, 3, 4)],
            "fig2": sec.fig2(space, fig2_fit, fig2_data), "fig3": sec.fig3(rep),
            "own_gap": sec.own_gap(published, demo, biases=rep.rows[rep.table2_index].biases,
                                   bearing=rep.spec.bearing)}


def readme(s: dict, *, replicates: int, seconds: float) -> str:
    """The Markdown summary: the prose of the page as plain text and the tables as Markdown."""
    text = {name: plain(section("paper_sections.html.j2", name, s[name])) for name in (*PROSE, "own_gap")}
    tables = [{"number": t["number"], "markdown": markdown(t["frame"])} for t in s["tables"]]
    o = s["origins_over_time"]
    origins = {"text": plain(section("paper_sections.html.j2", "origins_over_time", o)),
               "drift": markdown(o["drift_frame"]), "table": markdown(o["shown"])}
    return render("paper_readme.md.j2", command_replicates=replicates, intro=s["intro"], seconds=seconds,
                  text=text, prose=PROSE, spread=markdown(s["spread"]["frame"]), tables=tables, origins=origins)


def paper_report(out="reports/paper", *, replicates: int = 200, seed: int = 0, demonstration: bool = True,
                 command: str = "", progress=None, reproduction=None) -> Path:
    """Reproduce the seed paper on the rig and write ``out/``: ``index.html`` (self-contained),
    ``README.md``, ``comparison.csv`` (every row of Tables 1-4), ``spread.csv``, ``origins_over_time.csv``
    (Table 1's moves between experiments against noise and against Table 2's drift), ``reproduction.json`` and
    the figures as PNG.  Returns the HTML path.  ``progress``, if given, is called as ``progress(phase, done,
    total)`` (:func:`ambfit.studies.paper.reproduce`'s phases, then ``"paper: <step>"``).  ``reproduction``: a
    :func:`~ambfit.studies.paper.reproduce` result of these ``replicates`` and ``seed`` already at hand (it is the
    slow part)."""
    from ambfit.estimation import conditioning
    from ambfit.estimation.fit import FitError, fit

    t0 = time.perf_counter()
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    rep = reproduction if reproduction is not None else study.reproduce(replicates=replicates, seed=seed,
                                                                        progress=progress)
    spread = rep.spread()
    write_text(out / "comparison.csv", rep.comparison().to_csv(index=False))
    write_text(out / "spread.csv", spread.to_csv(index=False))
    steps = ("Fig. 2", "figures", "gap demonstration", "writing")

    def step(name):
        if progress is not None:
            progress(f"paper: {name}", steps.index(name), len(steps))

    step("Fig. 2")
    f2 = study.fig2_data()
    space = conditioning.solution_space(f2, "v", **conditioning.PAPER_FIG2)
    try:
        fig2_fit = fit(f2)
    except FitError as exc:
        fig2_fit = exc
    step("figures")
    figs = _figures(out, rep, space, fig2_fit, spread)
    bias_check = paper_gap.bias_pair_check()
    published = paper_gap.published_gap()
    step("gap demonstration")
    demo = paper_gap.gap_demonstration(seed=seed) if demonstration else None
    step("writing")
    record = _record(rep, seed=seed, space=space, fig2_fit=fig2_fit, bias_check=bias_check, published=published,
                     demo=demo)
    write_json(out / "reproduction.json", record, default=float)
    s = sections(rep, fig2_data=f2, space=space, fig2_fit=fig2_fit, bias_check=bias_check, published=published,
                 demo=demo)
    write_text(out / "origins_over_time.csv", s["origins_over_time"]["frame"].to_csv(index=False))
    write_text(out / "README.md", readme(s, replicates=replicates, seconds=time.perf_counter() - t0))
    html_path = out / "index.html"
    write_text(html_path, render(
        "paper.html.j2", title="ambfit: the seed paper's Tables 1-4 and Figs. 2, 3, 5 on the virtual rig", s=s,
        figs=figs, footer=footer(command or f"ambfit paper --out {out}", time.perf_counter() - t0)))
    return html_path
