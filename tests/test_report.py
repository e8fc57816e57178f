"""The HTML reports: each section is a function of a result, rendered by its template macro; every number in the
prose is the number in the result (or in the paper's tables) it came from, and nothing is left unexpanded."""

import dataclasses
import json
import re
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from typer.testing import CliRunner

from ambfit.data import read_csv
from ambfit.estimation.fit import fit
from ambfit.faces.cli import app
from ambfit.faces.report import dataset
from ambfit.faces.report import paper_sections as ps
from ambfit.faces.report.render import plain, section
from ambfit.physics.bearing import PAPER_BEARING
from ambfit.studies import paper as study
from ambfit.studies import paper_gap

ROOT = Path(__file__).resolve().parents[1]
TABLE2 = ROOT / "data" / "paper_table2.csv"
DATA, PAPER = "data_sections.html.j2", "paper_sections.html.j2"
MARKERS = ("{{", "}}", "{%", "%}", "{#", "#}")


def expanded(html: str) -> bool:
    """No template syntax left in the output."""
    return not any(m in html for m in MARKERS)


def _self_contained(html: str) -> bool:
    srcs = re.findall(r'(?:src|href)="([^"]+)"', html)
    return all(s.startswith("data:") for s in srcs) and "<img" in html


@pytest.fixture(scope="module")
def data():
    return read_csv(TABLE2)


@pytest.fixture(scope="module")
def ls(data):
    return fit(data)


# --- the data report's sections --------------------------------------------------------------------------

def test_identification_quotes_the_fit_and_the_closed_form(data, ls):
    from ambfit.estimation import closed_form
    from ambfit.estimation.units import pm

    closed = closed_form.identify(data)
    html = str(section(DATA, "identification", dataset.identification(ls, closed)))
    text = plain(html)
    assert expanded(html)
    assert f"reduced χ² {ls.reduced_chi2:.3f} on {ls.dof} dof" in text
    assert f"condition number of the scaled Jacobian {ls.condition:.3g}" in text
    for key, p in ls.contract_params().items():          # contract units are the display units
        assert f"<td>{pm(p['value'], p['std'])}</td>" in html, key
    c = closed.params()["g_v0_um"]
    assert f"<td>{pm(c['value'], c['std'])}</td>" in html
    assert "Closed form: mean ± standard error" in text


def test_identification_shows_k_with_its_unit_to_the_digits_its_error_justifies(data, ls):
    """Issue 24: k (~3e-6 N·m²/A²) read 0.0000 ± 0.0000 in the report: a fixed number of decimals per column."""
    import re

    from ambfit.estimation import closed_form

    html = str(section(DATA, "identification", dataset.identification(ls, closed_form.identify(data))))
    assert "0.0000" not in html
    for name in ("k_v", "k_w"):
        row = re.search(rf"<td>{name} \[N·m²/A²\]</td>\s*<td>([^<]+)</td>\s*<td>([^<]+)</td>", html)
        assert row, name
        shown = row.group(1)
        value, std = (float(t) for t in shown.split(" ± "))
        # the value to the std's second significant digit, the two on one power of ten
        assert abs(value - ls.value(name)) <= 0.5 * 10 ** (np.floor(np.log10(ls.error(name))) - 1) * (1 + 1e-9)
        assert std == pytest.approx(ls.error(name), rel=0.05)
        assert shown.split(" ± ")[0][-4:] == shown.split(" ± ")[1][-4:]          # same exponent, e.g. e-06
        assert len(shown.split(" ± ")[1].split("e")[0].lstrip("0.")) == 2          # two significant digits
        # one formatter: the report's text is the command line's table and print(result)
        assert shown in ls.display_row()[f"{name} [N·m²/A²]"] and shown in str(ls)
        assert row.group(2) != "0.0000 ± 0.0000"


def test_identification_says_why_the_closed_form_does_not_apply(ls):
    from ambfit.estimation.closed_form import ClosedFormError

    html = str(section(DATA, "identification", dataset.identification(ls, ClosedFormError("needs two biases"))))
    assert "Closed form not applicable: needs two biases" in plain(html)
    assert "closed form (Eq. 5-7)" not in html


def test_posterior_section_reports_the_run(data, ls):
    from ambfit.estimation import bayes

    post = bayes.sample(data, n_ensembles=2, n_steps=150, max_steps=150, seed=1, ls=ls)
    rec = post.to_json()
    html = str(section(DATA, "posterior", dataset.posterior(post, draw=False)))
    text = plain(html)
    assert expanded(html)
    assert f"2 independent emcee ensembles × 150 steps × {post.n_walkers} walkers" in text
    assert f"max autocorrelation time {np.max(post.tau):.0f} steps" in text
    assert f"{rec['hdi_prob'] * 100:g} % HDI" in html
    # mean ± sd to the precision the sd justifies, the same numbers as the contract record
    from ambfit.estimation.units import pm
    g = rec["params"]["g_v0_um"]
    assert f"<td>{pm(g['value'], g['std'])}</td>" in html
    assert f"<td>{g['ess_bulk']:.0f}</td>" in html


def test_solution_space_caption_follows_its_contour_levels(data, ls):
    from scipy.stats import chi2

    from ambfit.estimation import conditioning

    spaces = {"v": conditioning.solution_space(data, "v", weights_at=ls), "w": ValueError("no w map")}
    gap, origin, step = dataset.zoom_ranges(ls, "v")
    zooms = {"v": conditioning.solution_space(data, "v", gap=gap, origin=origin, step=step, weights_at=ls),
             "w": ValueError("no w map")}
    html = str(section(DATA, "solution_space", dataset.solution_space(spaces, ls, sigmas=(1, 2), zooms=zooms)))
    text = plain(html)
    assert expanded(html) and "<img" in html
    # 1 and 2 sigma in two dimensions: chi2(2).ppf(0.6827) = 2.30, ppf(0.9545) = 6.18, on the zoom; the wide
    # map's own levels above it
    assert f"Δχ² = {chi2.ppf(0.6827, 2):.1f}, {chi2.ppf(0.9545, 2):.1f} (68.3, 95.4 % in 2-D)" in text
    assert "11.8" not in text and "white contours at Δχ² = 50, 200, 1000" in text
    # without a zoom the caption names only what the wide map draws
    text = plain(str(section(DATA, "solution_space", dataset.solution_space(spaces, ls, sigmas=(1, 2)))))
    assert "2.3" not in text and "Δχ² = 50, 200, 1000" in text


def test_the_zoom_draws_the_contours_its_caption_names(data, ls):
    # each 1-3 sigma contour is a resolved closed curve on the zoom (the wide map's 1 µm cells draw them as a few
    # points or not at all), and the 1-sigma one is the least-squares 68 % ellipse: its half-height in gap is
    # sqrt(2.30) standard errors of g_v0
    from matplotlib.contour import ContourSet
    from matplotlib.figure import Figure

    from ambfit.estimation import conditioning
    from ambfit.faces import plots

    gap, origin, step = dataset.zoom_ranges(ls, "v")
    zoom = conditioning.solution_space(data, "v", gap=gap, origin=origin, step=step, weights_at=ls)
    wide = conditioning.solution_space(data, "v", weights_at=ls)
    levels = (2.30, 6.18, 11.8)
    drawn = {}
    for name, space in (("zoom", zoom), ("wide", wide)):
        ax = plots.plot_solution_space(space, result=ls, levels=levels, ax=Figure().subplots())
        cs = next(c for c in ax.collections if isinstance(c, ContourSet))
        drawn[name] = [len(p.vertices) for p in cs.get_paths()]
    assert len(drawn["zoom"]) == 3 and min(drawn["zoom"]) > 50, drawn
    assert min(drawn["wide"]) < 20, drawn
    ax = plots.plot_solution_space(zoom, result=ls, levels=levels[:1], ax=Figure().subplots())
    path = next(c for c in ax.collections if isinstance(c, ContourSet)).get_paths()[0].vertices
    half = (path[:, 1].max() - path[:, 1].min()) / 2
    assert half == pytest.approx(np.sqrt(2.30) * ls.error("g_v0") * 1e6, rel=0.05)


def test_design_section_describes_the_grid_it_chose_from(data, ls):
    from ambfit.estimation import design

    grid = design.candidate_steps((0.0, 0.0), offsets_um=(-30, 0, 30), biases_A=(1.0, 1.5))
    rec = design.recommend(data, n_steps=2, candidates=grid, result=ls)
    html = str(section(DATA, "design", dataset.design(rec, candidates=grid)))
    text = plain(html)
    assert expanded(html)
    assert f"A-optimal choice for g_v0 (now ± {rec.std_now * 1e6:.3g} µm)" in text
    assert "set-points ±30 µm" in text and "biases 1-1.5 A" in text
    assert f"kept within {rec.radius_um:.3g} µm of it" in text
    after = rec.steps["predicted_std_after"].iloc[-1] * 1e6
    assert "g_v0 std after [µm]" in html and f"<td>{after:.2f}</td>" in html
    # without a grid: the one recommend() chose from, the bearing's default cut to its limits
    rec = design.recommend(data, n_steps=2, result=ls)
    text = plain(section(DATA, "design", dataset.design(rec, max_radius_um=45.0)))
    # Table 2's two biases: the grid is cut to the positions already run (the diagonal pairs, ±28 µm from the
    # centre), and the page says why
    assert "kept within 45 µm of it" in text and "positions already run" in text and "2 biases" in text
    assert "biases 0.8-1.8 A" in text
    text = plain(section(DATA, "design", dataset.design(rec)))
    assert f"kept within {rec.radius_um:.3g} µm of it" in text and 55 < rec.radius_um < 60


@pytest.fixture(scope="module")
def small_diagnosis(data):
    from ambfit import diagnosis as gap
    from ambfit.physics import effects

    return gap.diagnose(data, candidates=[effects.PositionGain(), effects.IronReluctance()], pairs=False)


def test_diagnosis_section_reads_the_typed_diagnosis(small_diagnosis):
    from ambfit import diagnosis as gap

    dg = small_diagnosis
    html = str(section(DATA, "diagnosis", dataset.diagnosis(dg, draw=False)))
    text = plain(html)
    assert expanded(html)
    from ambfit.diagnosis import text as words

    assert words.headline(dg) in text and words.headline(dg).startswith(f"verdict: {dg.verdict}")
    nf = dg.noise_floor
    assert f"mean z² {nf.mean_z2:.2f} (expected {nf.expected_mean_z2:.2f}" in text
    assert f"Held-out excess of the ideal model {dg.heldout_excess_before:.2f} noise units" in text
    assert f"folds: {dg.folds}" in text
    where = [html.index(f"<td>{c.effect}</td>") for c in dg.ranking]
    assert where == sorted(where)                       # best first, as ranked
    shrink = f"{dg.ranking[0].shrink:.3f}".replace("-0.000", "0.000")
    assert f"<td>{dg.ranking[0].after:.3f}</td>" in html and f"<td>{shrink}</td>" in html
    # the nominal gap is the bearing's: another bearing, another sentence
    other = dataclasses.replace(PAPER_BEARING, nominal_gap=750e-6)
    text = plain(section(DATA, "diagnosis", dataset.diagnosis(
        dataclasses.replace(dg, parameter_gap=gap.parameter_gap(dg.baseline, other)), draw=False)))
    assert f"identified {dg.baseline.value('g_v0') * 1e6:.4g} vs nominal 750 (" in text and "762" not in text


def test_diagnosis_section_is_structured_not_one_paragraph(small_diagnosis):
    """Issue 24: the Diagnosis was a run-on paragraph; now a verdict line, lists, and tables with their heads."""
    from ambfit.diagnosis.checks import ForceCheck, ModelForce
    from ambfit.diagnosis.residuals import Region, Where

    regions = [Region("b_top_T", "v", 0.8, 0.9, 42, 7.5, 1.2), Region("time_s", "w", 0.0, 60.0, 12, -4.1, -1.2)]
    fc = ForceCheck(ideal=ModelForce(rms_rel=0.0058, max_rel=0.03, noise_floor_rel=0.001))
    dg = dataclasses.replace(small_diagnosis, where=Where(small_diagnosis.where.tests, regions, 4.0), force_check=fc)
    html = str(section(DATA, "diagnosis", dataset.diagnosis(dg, draw=False)))
    assert expanded(html)
    verdict = re.search(r'<p class="verdict">(.*?)</p>', html, re.S)
    assert verdict and plain(verdict.group(1)).startswith(f"verdict: {dg.verdict}")
    assert "mean z²" not in verdict.group(1) and len(plain(verdict.group(1))) < 120     # one line, the verdict
    heads = re.findall(r"<h3>(.*?)</h3>", html)
    assert heads[:3] == ["Candidate effects, held out (best first)", "Where the ideal law fails", "Force measurement"]
    ranking = html[html.index(heads[0]):html.index(heads[1])]
    for col in ("effect", "held-out RMS z", "held-out excess [noise units]", "shrink", "ΔAIC", "fit"):
        assert f"<th>{col}</th>" in ranking, col
    assert ranking.count("<tr") == len(dg.ranking) + 1                              # head and one row each
    items = re.findall(r"<li>(.*?)</li>", html[html.index(heads[1]):html.index(heads[2])], re.S)
    assert items == [f"{r.describe()}: {r.rows} readings, z {r.z:+.1f}" for r in regions]
    force = html[html.index(heads[2]):]
    assert "<th>RMS per reading [%]</th>" in force and "<td>0.580</td>" in force
    # no paragraph carries the whole story (the blind-spot note is one sentence, the command line's own words)
    assert max(len(plain(p)) for p in re.findall(r"<p(?! class=\"note\")[^>]*>(.*?)</p>", html, re.S)) < 300


def test_diagnosis_section_on_the_noise_floor_says_so_with_no_empty_where(small_diagnosis):
    from ambfit.diagnosis.residuals import Where
    from ambfit.diagnosis.verdict import Verdict

    dg = dataclasses.replace(small_diagnosis, decision=Verdict("none"), where=Where(small_diagnosis.where.tests, [], 4.0))
    text = plain(section(DATA, "diagnosis", dataset.diagnosis(dg, draw=False)))
    assert "verdict: none (the ideal law's held-out residuals sit on the noise floor)." in text
    assert "Nowhere: no region of the operating space has residuals beyond the noise" in text


def test_tables_write_a_rounded_tiny_negative_as_zero():
    from ambfit.faces.report.render import table

    html = str(table(pd.DataFrame({"shrink": [-1e-12, 0.5, -0.25]}), 3))
    assert "<td>0.000</td>" in html and "-0.000" not in html and "<td>-0.250</td>" in html


def test_data_report_without_a_fit_says_why(tmp_path, monkeypatch):
    import importlib

    fit_mod = importlib.import_module("ambfit.estimation.fit")   # the module (the package exports the function)

    def fail(*args, **kwargs):
        raise fit_mod.FitError("singular Jacobian at the start")

    monkeypatch.setattr(fit_mod, "fit", fail)
    path, rec = dataset.data_report(TABLE2, tmp_path / "r")
    page = path.read_text()
    assert rec["least_squares"] == {"error": "singular Jacobian at the start"}
    assert set(rec) == {"data", "n_rows", "least_squares", "warnings"} and rec["warnings"] == []
    assert "Least squares failed: singular Jacobian at the start" in plain(page)
    assert page.index("Summary") < page.index("Least squares failed")
    assert "2. Posterior" not in page and expanded(page)


def test_data_report_skips_sections_on_request(tmp_path):
    path, rec = dataset.data_report(TABLE2, tmp_path / "r", design_steps=2, do_posterior=False,
                                    do_diagnosis=False)
    page = path.read_text()
    assert expanded(page) and _self_contained(page)
    assert set(rec) == {"data", "n_rows", "least_squares", "closed_form", "solution_space", "design", "warnings"}
    assert {ax: m["on_edge"] for ax, m in rec["solution_space"].items()} == {"v": False, "w": False}
    assert json.loads((tmp_path / "r" / "report.json").read_text())["n_rows"] == rec["n_rows"] == 80
    assert "Skipped (--no-posterior)." in page and "Skipped (--no-diagnosis)." in page
    assert f"reduced χ² {rec['least_squares']['reduced_chi2']:.3f}" in page
    assert f"now ± {rec['design']['std_now'] * 1e6:.3g} µm" in page


def test_data_report_cli_writes_all_sections(tmp_path):
    out = tmp_path / "rep"
    r = CliRunner().invoke(app, ["report", str(TABLE2), "--out", str(out),
                                 "--steps", "400", "--max-steps", "400", "--ensembles", "2", "--design-steps", "3",
                                 "--occam", "none"])
    assert r.exit_code == 0, r.output
    page = (out / "index.html").read_text()
    assert _self_contained(page)
    for head in ("1. Identification", "2. Posterior", "3. Solution space", "4. What to measure next",
                 "5. Sim-to-real gap diagnosis"):
        assert head in page
    assert "failed" not in page
    assert page.count("<img") >= 3
    assert expanded(page)
    rec = json.loads((out / "report.json").read_text())
    assert set(rec) == {"data", "n_rows", "least_squares", "closed_form", "bayes", "solution_space", "design",
                        "diagnosis", "warnings"}
    assert f'<p class="verdict">verdict: {rec["diagnosis"]["verdict"]}' in page
    assert rec["diagnosis"]["rules"]["occam"] == "none"          # the naming preference reached the diagnosis
    assert f"{rec['bayes']['n_ensembles']} independent emcee ensembles" in page
    # the combined uncertainty (GUM) beside the noise-only error, the same number in the page and the JSON
    v0 = rec["least_squares"]["params"]["v0_um"]
    assert "u_combined (with calibration)" in page and f"{v0['u_combined']:.3g}" in page
    assert v0["u_combined"] > v0["std"]


def test_data_report_cli_rejects_bad_data(tmp_path):
    bad = tmp_path / "bad.csv"
    bad.write_text("axis,bias_A,i_top_A\nv,1.4,oops\n")
    r = CliRunner().invoke(app, ["report", str(bad), "--out", str(tmp_path / "r"), "--no-posterior"])
    assert r.exit_code == 2
    assert "bad.csv" in r.output


# --- the paper report's sections -------------------------------------------------------------------------

@pytest.fixture(scope="module")
def rep():
    return study.reproduce(replicates=3, seed=1)


@pytest.fixture
def bias_check():
    """A bias-pair check with known ranges: 0 µm without an effect, 1.25 µm with the offset."""
    pairs = ["1.4/1.5", "1.4/1.6", "1.5/1.6"]
    return pd.DataFrame({"effect": ["none"] * 3 + ["offset"] * 3, "bias_pair": pairs * 2,
                         "v0_um": [33.3, 33.3, 33.3, 33.0, 33.5, 34.25], "w0_um": -11.3,
                         "g_v0_um": 775.0, "g_w0_um": 763.0})


def test_intro_and_calibration_quote_the_reproduction(rep):
    text = plain(section(PAPER, "intro", ps.intro(rep)))
    assert f"({rep.noise.current * 1e3:.2f} mA per current reading" in text
    assert f"repeated {rep.replicates.shape[0]} times ({rep.failed} rejected)" in text
    assert f"overall means ({rep.spec.g0[0] * 1e6:.0f}/{rep.spec.g0[1] * 1e6:.0f} µm" in text
    shift = study.TABLE4_SHIFT
    assert f"Table 4, {(rep.spec.x0[0] + shift[0]) * 1e6:.1f}/{(rep.spec.x0[1] + shift[1]) * 1e6:.1f} µm" in text
    nc = rep.noise_calibration()
    text = plain(section(PAPER, "calibration", ps.calibration(rep)))
    assert f"current noise of {nc['calibrated_current_noise_mA']:.2f} mA" in text
    assert f"from its {nc['dof']} degrees of freedom" in text


def test_paper_numbers_follow_the_paper_tables(rep, bias_check, monkeypatch):
    # edit the transcribed tables: every sentence that quotes them must follow (none may be typed into the prose)
    original = study.load_table

    def edited(n, averages=False):
        t = original(n, averages)
        if n == 2 and not averages:
            t.loc[7, "g_w0_um"], t.loc[0, "w0_um"] = 900.0, -8.5
        if n == 1 and not averages:
            t["v0_um"] = [36.0, 32.0, 27.0]
        return t

    monkeypatch.setattr(study, "load_table", edited)
    text = plain(section(PAPER, "calibration", ps.calibration(rep)))
    assert "iteration 8's 900.0 µm on w" in text and "850.7" not in text
    assert "iteration 1 (-8.50 µm, before" in text and "-7.18" not in text
    text = plain(section(PAPER, "origin_spread", ps.origin_spread(rep, bias_check)))
    assert "36.00 → 32.00 → 27.00 µm" in text and "(-4.50 µm each)" in text and "(9.0 µm over Table 1)" in text
    assert "35.08" not in text and "6.3 µm" not in text
    assert "0.00 µm with none, 1.25 µm with offset" in text


def test_gap_spread_and_eq7_bias_quote_the_reproduction(rep):
    s = ps.gap_spread(rep)
    text = plain(section(PAPER, "gap_spread", s))
    assert f"the paper's sd is {s['ratio'][0]:.2f}-{s['ratio'][1]:.2f} times the rig's median" in text
    assert f"sqrt(1 + 2 · 0.9 · ρ) = {np.sqrt(max(1 + 1.8 * s['rho'], 0.05)):.2f}" in text   # 10 iterations
    assert re.search(r"\b\d+(st|nd|rd|th) percentile", text) and not re.search(r"(?<!1)[123]th\b", text)
    comp = rep.comparison()
    e = ps.eq7_bias(rep)
    text = plain(section(PAPER, "eq7_bias", e))
    row = comp[(comp["table"] == 1) & (comp["row"] == 1) & (comp["quantity"] == "g_v0_um")].iloc[0]
    assert f"1.4/1.5 A: {row['rig_mean'] - rep.spec.g0[0] * 1e6:+.1f} ± " in text
    assert "Table 1's 0.1 A pairs" in text and f"row sd of about {e['row_sd']:.0f} µm" in text


def test_table_titles_and_figure_texts_come_from_the_protocol(rep):
    titles = [str(section(PAPER, "table_title", ps.side_by_side(rep, t))) for t in (1, 2, 3, 4)]
    assert titles == ["Table 1: 3 bias pairs, ±20 µm", "Table 2: 10 iterations of Table 1's experiment 2",
                      "Table 3: 4 initial rotor positions", "Table 4: after rotor reassembly"]
    text = plain(section(PAPER, "fig3", ps.fig3(rep)))
    # Table 4's widest pairs (±50 µm) about (47.4, -13.1) µm reach 97.4 µm; the paper's clearance is 60 µm
    assert "reach about 97 µm" in text and "beyond the 60 µm clearance" in text
    wide = dataclasses.replace(rep.spec, bearing=dataclasses.replace(rep.spec.bearing, backup_clearance=150e-6))
    text = plain(section(PAPER, "fig3", ps.fig3(dataclasses.replace(rep, spec=wide))))
    assert "within the 150 µm clearance" in text


def test_own_gap_uses_the_bearing_and_the_demonstration():
    bearing = dataclasses.replace(PAPER_BEARING, nominal_gap=770e-6, position_gain_tolerance=0.005)
    published = paper_gap.published_gap(nominal=bearing)
    gv = {e["parameter"]: e for e in published}["g_v0_um"]
    demo = {"nominal_gap_um": 770.0,
            "implied": {"iron_reluctance_mu_r": [3000.0, 9e4], "iron_path_mm": 80.0,
                        "position_gain_percent": [0.6, 0.1]},
            "scenarios": {
                "iron_reluctance": {"paper_protocol": {"g_v0_um": [778.6, 1.4], "verdict": "none"},
                                    "bias_sweep": {"n_rows": 90, "g_v0_um": [770.2, 0.5], "verdict": "iron_reluctance",
                                                   "heldout_excess": 1.57, "shrink": 1.0}},
                "position_gain": {"paper_protocol": {"g_v0_um": [777.9, 1.4], "verdict": "none"},
                                  "bias_sweep": {"n_rows": 90, "g_v0_um": [774.6, 0.5], "verdict": "none",
                                                 "heldout_excess": 0.4, "shrink": 0.0}}}}
    s = ps.own_gap(published, demo, biases=(1.4, 1.6), bearing=bearing)
    html = str(section(PAPER, "own_gap", s))
    text = plain(html)
    assert expanded(html)
    assert "nominal 770 µm" in text and "762" not in text
    assert f"by {gv['difference']:+.1f} µm ({gv['z']:.0f} se)" in text
    assert "micrometer calibration (0.50 %)" in text
    assert "iron reluctance (μr 3000 over 80 mm) gives an effective g_v0 of 778.6 ± 1.4 µm" in text
    assert "at 1.4-1.6 A the iron's extra gap is constant" in text
    assert "separates them: the diagnosis names 'iron_reluctance' for the iron (held-out excess 1.57" in text
    assert "true effect (nominal 770 µm)" in str(s["demo_table"])


def test_paper_report_is_one_self_contained_page(tmp_path, rep):
    from ambfit.faces import report

    path = report.paper_report(tmp_path / "paper", replicates=3, seed=1, demonstration=False, reproduction=rep)
    paper_html = path.read_text()
    assert _self_contained(paper_html)
    for head in ("Table 1", "Table 2", "Table 3", "Table 4", "Fig. 2", "Fig. 3", "Fig. 5", "sim-to-real gap"):
        assert head in paper_html
    assert paper_html.count("<img") >= 6
    comp = pd.read_csv(tmp_path / "paper" / "comparison.csv")
    assert len(comp) == 108
    for f in ("fig2_solution_space.png", "fig5_iterations.png", "fig3_position_pairs.png", "README.md",
              "spread.csv", "reproduction.json"):
        assert (tmp_path / "paper" / f).stat().st_size > 500
    assert expanded(paper_html)
    readme = (tmp_path / "paper" / "README.md").read_text()
    assert expanded(readme) and not re.search(r"<[a-z/][^>]*>", readme) and "&#" not in readme
    assert "## Table 4: paper vs ambfit" in readme
    rec = json.loads((tmp_path / "paper" / "reproduction.json").read_text())
    assert set(rec) == {"replicates", "failed", "seed", "noise", "seconds_reproduction", "comparison", "spread",
                        "autocorrelation", "between_experiment_sd", "noise_calibration", "table2_trend", "fig2",
                        "published_gap", "gap_demonstration", "bias_pair_check"}
    assert f"repeated {rec['replicates']} times" in paper_html


def test_the_summary_box_says_every_warning_the_command_line_prints(tmp_path):
    # a saturating rig swept over four biases: the ideal law does not fit; identify warns, and the report's
    # summary box (top of the page) carries the same sentences and says the fit does NOT fit its data
    from ambfit import rig
    from ambfit.physics.effects import Saturation
    from ambfit.rig import protocol as P

    spec = rig.PAPER_RIG
    frame = rig.simulate(spec, P.rich(center=spec.centre), [Saturation(b_sat=1.0)], seed=2).data
    csv = tmp_path / "sat.csv"
    frame.to_csv(csv, index=False)
    r = CliRunner().invoke(app, ["identify", str(csv), "--no-force-check"])
    said = [line.removeprefix("warning: ") for line in r.output.splitlines() if line.startswith("warning: ")]
    assert said, r.output
    res = fit(frame)
    box = dataset.summary_box(res, bearing=PAPER_BEARING)
    text = plain(section(DATA, "summary", box))
    assert all(w in text for w in said), (said, text)
    assert "does NOT fit its data" in text and f"χ²/dof {res.reduced_chi2:.3g}" in text


def test_the_summary_box_flags_a_posterior_away_from_least_squares(data, ls):
    from ambfit.estimation import bayes

    post = bayes.sample(data, n_ensembles=2, n_steps=300, max_steps=300, seed=1, ls=ls)
    box = dataset.summary_box(ls, bearing=PAPER_BEARING, post=post)
    assert not any("disagree" in w for w in box["warnings"])
    before = post.agreement()["z"]["v0"]          # (the corrected least-squares estimate sits a fraction of an sd off)
    draws = post.draws.copy()
    draws[..., post.names.index("v0")] += 3 * post.error("v0")
    box = dataset.summary_box(ls, bearing=PAPER_BEARING, post=dataclasses.replace(post, draws=draws))
    text = plain(section(DATA, "summary", box))
    assert f"posterior and least squares disagree beyond 2 sd on v0 ({before + 3:+.1f} sd)" in text


def test_the_summary_box_gives_the_verdicts_parameters_beside_the_ideal_laws():
    # a named verdict: its model's gap and origin (what the bearing is once the effect is modelled) beside the
    # ideal law's, and the verdict in one line with its grade
    import types

    from ambfit import rig
    from ambfit.diagnosis.verdict import Grade
    from ambfit.estimation.units import with_unit
    from ambfit.physics.effects import Saturation
    from ambfit.rig import protocol as P

    spec = rig.PAPER_RIG
    frame = rig.simulate(spec, P.rich(center=spec.centre), [Saturation(b_sat=1.0)], seed=2).data
    ideal, sat = fit(frame), fit(frame, [Saturation()])
    grade = Grade("saturation", ("saturation",), "law", 0.99, 0.3, 1.05, 1.0, True, True)
    dg = types.SimpleNamespace(verdict="saturation", verdict_fit=sat, grade=grade)
    text = plain(section(DATA, "summary", dataset.summary_box(ideal, bearing=PAPER_BEARING, diagnosed=dg)))
    for name in ("g_v0", "v0"):
        assert with_unit(name, sat.value(name), sat.error(name))[0] in text
        assert with_unit(name, ideal.value(name), ideal.error(name))[0] in text
    assert "with saturation (the verdict)" in text
    assert "verdict: saturation (the library's law saturation: removes 0.990 of the held-out excess, at the noise " \
           "floor)" in text
