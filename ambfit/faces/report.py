"""Self-contained HTML reports: one page, figures embedded as PNG, tables as HTML.

:func:`data_report` (``ambfit report DATA.csv --out DIR``) identifies one data set
(least squares and the paper's closed form), samples its posterior, maps its
solution space, recommends the next perturbations and diagnoses the sim-to-real gap.
:func:`paper_report` (``ambfit paper --out reports/paper``) reruns the seed paper's
Tables 1-4 and Figs. 2, 3 and 5 on the virtual rig and sets them beside the paper.
"""

from __future__ import annotations

import base64
import html
import io
import json
import time
from pathlib import Path

import numpy as np
import pandas as pd

from ambfit.physics.bearing import PAPER_BEARING

CSS = """
body{font-family:system-ui,-apple-system,'Segoe UI',sans-serif;max-width:1150px;margin:2em auto;padding:0 1em;
color:#222;line-height:1.45}
h1{font-size:1.6em;border-bottom:2px solid #345;padding-bottom:.2em}h2{font-size:1.25em;margin-top:1.8em;color:#234}
h3{font-size:1.05em}
table{border-collapse:collapse;margin:.6em 0 1em;font-size:.82em}
th,td{border:1px solid #ccc;padding:3px 7px;text-align:right}th{background:#eef2f6}
td:first-child,th:first-child{text-align:left}tr:nth-child(even) td{background:#fafbfc}
img{max-width:100%;border:1px solid #ddd;margin:.4em 0}
.note{background:#f6f8fa;border-left:4px solid #89a;padding:.5em .9em;margin:.8em 0}
.bad{color:#a00;font-weight:600}.good{color:#070;font-weight:600}
code{background:#f2f2f2;padding:0 3px}footer{margin-top:3em;font-size:.8em;color:#666}
"""


def png_bytes(obj, dpi: int = 110) -> bytes:
    """A matplotlib Figure/Axes or ArviZ plot collection rendered to PNG (by :func:`ambfit.plots.save`); closes it."""
    import matplotlib.pyplot as plt

    from ambfit.faces.plots import figure_of, save

    buf = io.BytesIO()
    save(obj, buf, dpi=dpi)
    plt.close(figure_of(obj))
    return buf.getvalue()


def img(data: bytes) -> str:
    """PNG bytes as an embedded ``<img>`` (base64)."""
    return f'<img alt="figure" src="data:image/png;base64,{base64.b64encode(data).decode()}">'


def png(obj, dpi: int = 110) -> str:
    """A figure as an embedded ``<img>``; closes it."""
    return img(png_bytes(obj, dpi))


def table(df: pd.DataFrame, digits: int = 2) -> str:
    """A DataFrame as an HTML table (floats to ``digits`` decimals, NaN as blank)."""
    def fmt(v):
        if isinstance(v, (float, np.floating)):
            if not np.isfinite(v):
                return ""
            return f"{v:.{digits}f}" if 1e-3 <= abs(v) < 1e5 or v == 0 else f"{v:.4g}"
        return str(v)
    return df.to_html(index=False, border=0, formatters={c: fmt for c in df.columns}, escape=True, na_rep="")


def page(title: str, body: list[str], footer: str = "") -> str:
    return (f"<!DOCTYPE html><html lang='en'><head><meta charset='utf-8'><title>{html.escape(title)}</title>"
            f"<style>{CSS}</style></head><body><h1>{html.escape(title)}</h1>{''.join(body)}"
            f"<footer>{footer}</footer></body></html>")


def _p(text: str, cls: str = "") -> str:
    return f"<p class='{cls}'>{text}</p>" if cls else f"<p>{text}</p>"


def _markdown(df: pd.DataFrame, digits: int = 2) -> str:
    def cell(v):
        if isinstance(v, (float, np.floating)):
            return "" if not np.isfinite(v) else f"{v:.{digits}f}"
        return str(v)
    lines = ["| " + " | ".join(map(str, df.columns)) + " |", "|" + "---|" * len(df.columns)]
    lines += ["| " + " | ".join(cell(v) for v in row) + " |" for row in df.itertuples(index=False)]
    return "\n".join(lines)


def _num(entry, key) -> float:
    v = entry.get(key) if isinstance(entry, dict) else None
    return float(v) if v is not None else np.nan


def _footer(command: str, seconds: float) -> str:
    from ambfit import __version__

    return (f"ambfit {__version__} · <code>{html.escape(command)}</code> · {seconds:.0f} s · "
            f"{time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}")


# --- one data set --------------------------------------------------------------------------------------

def data_report(data_path, out, *, steps: int = 3000, ensembles: int = 4, design_steps: int = 8,
                bearing=PAPER_BEARING, max_radius_um: float | None = 50.0, do_posterior: bool = True,
                do_diagnosis: bool = True, seed: int = 0,
                command: str = "") -> tuple[Path, dict]:
    """Identify, sample, map, design and diagnose one contract CSV; write ``out/index.html`` and
    ``out/report.json``.  Returns the HTML path and the JSON record.  Sections that cannot run (e.g. the closed form on
    non-symmetric pairs) say why instead of stopping the report."""
    from ambfit.estimation import closed_form, conditioning, design
    from ambfit.faces import plots
    from ambfit.data import read_csv
    from ambfit.estimation.fit import FitError, fit

    t0 = time.perf_counter()
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    ds = read_csv(data_path)
    df = ds.frame
    record = {"data": str(data_path), "n_rows": len(df)}
    body = [_p(f"Data: <code>{html.escape(str(data_path))}</code>, {len(df)} readings, "
               f"{df['experiment'].nunique() if 'experiment' in df else 1} experiment(s), "
               f"{df['load_id'].nunique() if 'load_id' in df else 1} load group(s).")]

    # 1. identification
    body.append("<h2>1. Identification</h2>")
    try:
        res = fit(ds, bearing=bearing)
    except FitError as exc:
        body.append(_p(f"Least squares failed: {html.escape(str(exc))}", "bad"))
        record["least_squares"] = {"error": str(exc)}
        (out / "report.json").write_text(json.dumps(record, indent=2, default=float))
        html_path = out / "index.html"
        html_path.write_text(page("ambfit report", body, _footer(command, time.perf_counter() - t0)))
        return html_path, record
    rec = res.to_json()
    record["least_squares"] = rec
    rows = []
    for key, p in rec["params"].items():
        rows.append({"parameter": key, "value": p["value"], "std": p["std"]})
    ident = pd.DataFrame(rows)
    try:
        cf = closed_form.identify(ds).to_json()
        record["closed_form"] = cf
        cfp = cf.get("params", {})
        ident["closed form (Eq. 5-7)"] = [_num(cfp.get(k), "value") for k in ident["parameter"]]
        ident["closed form std"] = [_num(cfp.get(k), "std") for k in ident["parameter"]]
        cf_note = "Closed form: mean ± standard error over iterations (the paper's tables)."
    except closed_form.ClosedFormError as exc:
        cf_note = f"Closed form not applicable: {html.escape(str(exc))}"
    body.append(table(ident, 4))
    status = "good" if rec["converged"] else "bad"
    body.append(_p(f"Least squares (Levenberg-Marquardt, effective-variance weights): "
                   f"<span class='{status}'>{'converged' if rec['converged'] else 'NOT converged'}</span>; "
                   f"reduced χ² {rec['reduced_chi2']:.3f} on {rec['dof']} dof; condition number of the scaled "
                   f"Jacobian {rec['condition']:.3g}; weakest direction: {html.escape(str(rec['weak_direction']))}; "
                   f"noise from {html.escape(str(rec['noise_source']))}. {cf_note}"))

    # 2. posterior
    body.append("<h2>2. Posterior</h2>")
    if do_posterior:
        from ambfit.estimation import bayes

        try:
            sr = bayes.sample(ds, n_ensembles=ensembles, n_steps=steps, seed=seed, ls=res)
            js = sr.to_json()
            record["bayes"] = js
            post = pd.DataFrame([{"parameter": k, "mean": p["value"], "sd": p["std"], "hdi 3 %": p["hdi_low"],
                                  "hdi 97 %": p["hdi_high"], "R-hat": p["r_hat"], "ESS bulk": p["ess_bulk"]}
                                 for k, p in js["params"].items()])
            body.append(table(post, 4))
            body.append(_p(f"{ensembles} independent emcee ensembles × {steps} steps × {sr.n_walkers} walkers; "
                           f"R-hat across ensembles; max autocorrelation time {js['tau_max']:.0f} steps. "
                           f"{html.escape(js['message'])}", "" if js["converged"] else "bad"))
            body.append(png(plots.plot_pair(sr)))
        except Exception as exc:  # noqa: BLE001 - one failed section must not lose the rest of the report
            body.append(_p(f"Posterior sampling failed: {html.escape(repr(exc))}", "bad"))
    else:
        body.append(_p("Skipped (--no-posterior)."))

    # 3. solution space
    body.append("<h2>3. Solution space (the paper's Fig. 2)</h2>")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(12, 4.8))
    for ax, axis in zip(axes, ("v", "w")):
        try:
            sp = conditioning.solution_space(ds, axis, weights_at=res)
            plots.plot_solution_space(sp, result=res, ax=ax)
        except Exception as exc:  # noqa: BLE001 - a failed section is reported, the rest still stands
            ax.text(0.5, 0.5, f"axis {axis}: {exc}", ha="center", wrap=True)
    body.append(png(fig))
    body.append(_p("Δχ² of the force misfit over (origin, gap) with the other parameters profiled; white "
                   "contours at Δχ² = 2.3, 6.2, 11.8 (68, 95, 99.7 % in 2-D); red: the least-squares point, its "
                   "ellipses and the weakest Fisher direction. A long valley means the design does not separate "
                   "gap from origin."))

    # 4. design
    body.append("<h2>4. What to measure next</h2>")
    try:
        recd = design.recommend(ds, n_steps=design_steps, target="g_v0", result=res, max_radius_um=max_radius_um)
        st = recd.steps.copy()
        st.insert(0, "step", np.arange(1, len(st) + 1))
        if "predicted_std_after" in st:
            st["g_v0 std after [µm]"] = st.pop("predicted_std_after") * 1e6
        body.append(table(st, 2))
        lim = "" if max_radius_um is None else f", kept within {max_radius_um:g} µm of the sensor origin"
        body.append(_p(f"Greedy A-optimal choice for g_v0 (now ± {recd.std_now * 1e6:.3g} µm) among set-points "
                       f"±50 µm around the estimated effective origin{lim}, and biases 0.8-1.8 A."))
        record["design"] = {"std_now": recd.std_now, "steps": recd.steps.to_dict(orient="records")}
    except Exception as exc:  # noqa: BLE001 - a failed section is reported, the rest still stands
        body.append(_p(f"Design recommendation failed: {html.escape(str(exc))}", "bad"))

    # 5. diagnosis
    body.append("<h2>5. Sim-to-real gap diagnosis</h2>")
    if do_diagnosis:
        from ambfit import diagnosis as gap

        try:
            dg = gap.diagnose(ds, bearing=bearing).to_json()
            record["diagnosis"] = dg
            nf = dg["noise_floor"]
            conf = ("the ideal model sits on the noise floor, so every candidate fits as well as it does"
                    if dg["verdict"] == "none" else
                    "confounded with: " + (", ".join(dg["confounded_with"]) or "none"))
            body.append(_p(f"Verdict: <b>{html.escape(dg['verdict'])}</b>; {html.escape(conf)}; "
                           f"shrink {dg['shrink']:.3f}. "
                           f"Noise floor ({html.escape(nf['source'])}): mean z² {nf['mean_z2']:.2f} (expected "
                           f"{nf['expected_mean_z2']:.2f}); held-out excess of the ideal model "
                           f"{dg['heldout_excess_before']:.2f} noise units (folds: {html.escape(dg['folds'])})."))
            rk = pd.DataFrame([{"effect": r["effect"], "held-out excess after": r["heldout_excess_after"],
                                "shrink": r["shrink"], "ΔAIC": r["delta_aic"]} for r in dg["ranking"]])
            body.append(table(rk, 3))
            body.append(png(plots.plot_ranking(dg)))
            if dg["where"]:
                body.append(table(pd.DataFrame([{"region": w["region"], "rows": w["rows"], "z": w["z"]}
                                                for w in dg["where"][:8]]), 2))
            for e in dg.get("parameter_gap", []):
                if e.get("flagged"):
                    why = "; ".join(f"{c['effect']}: {c['needs']}" + (" (implausible" + (f": {c['note']}" if "note"
                                    in c else "") + ")" if c.get("plausible") is False else "")
                                    for c in e.get("could_be", []))
                    body.append(_p(f"{html.escape(e['parameter'])}: identified {e['identified']:.4g} vs nominal "
                                   f"{e['nominal']:.4g} ({e['z']:+.1f} sd). Could be {html.escape(why)}."))
        except Exception as exc:  # noqa: BLE001 - a failed section is reported, the rest still stands
            body.append(_p(f"Diagnosis failed: {html.escape(str(exc))}", "bad"))
    else:
        body.append(_p("Skipped (--no-diagnosis)."))

    (out / "report.json").write_text(json.dumps(record, indent=2, default=float))
    html_path = out / "index.html"
    html_path.write_text(page(f"ambfit report: {Path(data_path).name}", body,
                              _footer(command or f"ambfit report {data_path} --out {out}", time.perf_counter() - t0)))
    return html_path, record


# --- the seed paper --------------------------------------------------------------------------------------

def _side_by_side(comp: pd.DataFrame, t: int) -> pd.DataFrame:
    sub = comp[comp["table"] == t]
    out = pd.DataFrame({
        "row": sub["row"].map(lambda r: "Average" if r == 0 else str(r)), "quantity": sub["quantity"],
        "paper": sub["paper"], "ambfit (this run)": sub["rig_run"], "rig predicted": sub["rig_mean"],
        "± sd": sub["rig_sd"], "paper − predicted [µm]": sub["diff"], "in sd": sub["z"]})
    if t != 2:
        out["ambfit least squares"] = sub["ls"]
        out["± se"] = sub["ls_std"]
    return out


def paper_report(out="reports/paper", *, replicates: int = 200, seed: int = 0, demonstration: bool = True,
                 command: str = "", progress: bool = False) -> Path:
    """Reproduce the seed paper on the rig and write ``out/``: ``index.html`` (self-contained),
    ``README.md``, ``comparison.csv`` (every row of Tables 1-4), ``spread.csv``, ``reproduction.json`` and
    the figures as PNG.  Returns the HTML path."""
    import matplotlib

    matplotlib.use("Agg", force=False)
    from ambfit.estimation import conditioning
    from ambfit.studies import paper
    from ambfit.faces import plots
    from ambfit.estimation.fit import FitError, fit

    t0 = time.perf_counter()
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    rep = paper.reproduce(replicates=replicates, seed=seed, progress=progress)
    comp = rep.comparison()
    spread = rep.spread()
    acf = rep.autocorrelation()
    extra = rep.between_experiment_sd()
    cal_noise = rep.noise_calibration()
    trend = rep.trend()
    comp.to_csv(out / "comparison.csv", index=False)
    spread.to_csv(out / "spread.csv", index=False)
    figs = {}

    # figures (PNG files and embedded copies)
    def keep(name, obj):   # render once: the PNG file and the page's embedded copy are the same bytes
        data = png_bytes(obj)
        (out / name).write_bytes(data)
        figs[name] = img(data)

    f2 = paper.fig2_data()
    sp = conditioning.solution_space(f2, "v")
    try:
        ls2 = fit(f2)
        fig2_ls = (ls2.value("g_v0") * 1e6, ls2.error("g_v0") * 1e6, ls2.value("v0") * 1e6, ls2.error("v0") * 1e6,
                   float(ls2.corr[ls2.names.index("g_v0"), ls2.names.index("v0")]))
    except FitError as exc:
        ls2, fig2_ls = None, str(exc)
    keep("fig2_solution_space.png", plots.plot_fig2_surface(sp))
    keep("fig2_map.png", plots.plot_solution_space(sp, result=ls2))
    j2 = rep.table2_index
    keep("fig3_position_pairs.png", plots.plot_fig3_positions(rep.searches[j2]))
    j4 = next(k for k, r in enumerate(rep.rows) if r.table == 4 and r.row == 3)
    keep("fig3_position_pairs_table4.png", plots.plot_fig3_positions(rep.searches[j4]))
    keep("fig5_iterations.png", plots.plot_fig5_iterations(rep))
    keep("spread.png", plots.plot_spread(spread))

    bpc = paper.bias_pair_check()
    pub = paper.published_gap()
    demo = paper.gap_demonstration(seed=seed) if demonstration else None

    # numbers for the text
    pred = spread[spread["role"] == "prediction"]
    gaps = pred[pred["quantity"].str.startswith("g_")]
    origins = pred[~pred["quantity"].str.startswith("g_")]
    cal = spread[spread["role"] == "calibration"]
    rec = {"replicates": int(rep.replicates.shape[0]), "failed": rep.failed, "seed": seed,
           "noise": {"current_mA": rep.noise.current * 1e3, "position_um": rep.noise.position * 1e6},
           "seconds_reproduction": rep.seconds, "comparison": comp.to_dict(orient="records"),
           "spread": spread.to_dict(orient="records"), "autocorrelation": acf.to_dict(orient="records"),
           "between_experiment_sd": extra.to_dict(orient="records"), "noise_calibration": cal_noise,
               "table2_trend": trend.to_dict(orient="records"), "fig2": {
               "grid": list(sp.chi2.shape), "minimum_um": [m * 1e6 for m in sp.minimum],
               "least_squares": fig2_ls}, "published_gap": pub, "gap_demonstration": demo,
               "bias_pair_check": bpc.to_dict(orient="records")}
    (out / "reproduction.json").write_text(json.dumps(rec, indent=2, default=float))

    t2 = cal.set_index("quantity")
    text = {
        "intro": (
            f"Every experiment of the paper's Tables 1, 3 and 4 was run on the virtual rig <code>PAPER_RIG</code> "
            f"as the paper ran it: the effective-origin search, Eq. 5-7 per iteration, 10 iterations, the row "
            f"being the mean over iterations (Table 2 is Table 1's experiment 2 iteration by iteration). The rig's "
            f"noise ({rep.noise.current * 1e3:.2f} mA per current reading, {rep.noise.position * 1e6:.2f} µm per "
            f"position reading) was calibrated once, on Table 2's per-iteration gap scatter, and not touched "
            f"after. The whole set of experiments was then repeated {rep.replicates.shape[0]} times "
            f"({rep.failed} rejected) to <i>predict</i> each row's standard deviation and each table's spread. "
            f"The rig's true gaps and origins are the paper's overall means (775/763 µm, 33.3/-11.3 µm; after the "
            f"reassembly of Table 4, -47.4/13.1 µm): agreement of the means is by construction, the spreads are "
            f"the test."),
        "calibration": (
            f"Calibration (Table 2, per-iteration sd): gap {t2.loc['g_v0_um', 'paper_sd']:.1f}/"
            f"{t2.loc['g_w0_um', 'paper_sd']:.1f} µm in the paper, rig median {t2.loc['g_v0_um', 'rig_median']:.1f}/"
            f"{t2.loc['g_w0_um', 'rig_median']:.1f} µm; origin {t2.loc['v0_um', 'paper_sd']:.2f}/"
            f"{t2.loc['w0_um', 'paper_sd']:.2f} µm against {t2.loc['v0_um', 'rig_median']:.2f}/"
            f"{t2.loc['w0_um', 'rig_median']:.2f} µm. Pooled over both axes, Table 2 calls for a current noise of "
            f"{cal_noise['calibrated_current_noise_mA']:.2f} mA (90 % interval {cal_noise['interval_mA'][0]:.2f}-"
            f"{cal_noise['interval_mA'][1]:.2f} mA from its 18 degrees of freedom); the rig's "
            f"{cal_noise['rig_current_noise_mA']:.2f} mA is {'inside' if cal_noise['rig_level_inside'] else 'OUTSIDE'}"
            f" that interval (it was chosen on the v axis, whose scatter is not inflated by iteration 8's 850.7 µm "
            f"on w). The paper's w0 scatter is inflated by its first iteration "
            f"(-7.18 µm, before the rotor was re-centred); without it the paper's w0 sd is "
            f"{np.std(paper.load_table(2)['w0_um'].to_numpy()[1:], ddof=1):.2f} µm."),
        "gaps": _gap_spread_text(gaps, acf, extra),
        "origins": _origin_spread_text(origins, extra, comp, t2, bpc, trend),
        "eq7_bias": _eq7_bias_text(comp, rep),
    }
    md = ["# The seed paper on the virtual rig", "",
          (f"Regenerate with `make paper` (`ambfit paper --out reports/paper --replicates {replicates}`). "
           f"{rep.replicates.shape[0]} replicates, {time.perf_counter() - t0:.0f} s. Open `index.html` for the "
           "figures; every row of Tables 1-4 is in `comparison.csv`."), ""]
    for k in ("intro", "calibration", "gaps", "origins", "eq7_bias"):
        md += [_strip(text[k]), ""]
    md += ["## Spread: paper vs prediction", "", _markdown(spread.drop(columns=["rig_run_sd"])), ""]
    for t in (1, 2, 3, 4):
        md += [f"## Table {t}: paper vs ambfit", "", _markdown(_side_by_side(comp, t)), ""]
    md += ["## The paper's own sim-to-real gap", "", _strip(_gap_text(pub, demo)), ""]
    (out / "README.md").write_text("\n".join(md) + "\n")

    body = [_p(text["intro"]),
            "<h2>Spread: paper vs the rig's prediction</h2>", figs["spread.png"],
            table(spread.drop(columns=["rig_run_sd"]), 2),
            _p(text["calibration"]), _p(text["gaps"]), _p(text["origins"]), _p(text["eq7_bias"]),
            "<h3>Lag-1 autocorrelation of Table 2's iterations</h3>", table(acf, 2),
            "<h3>Between-experiment sd not explained by reading noise [µm]</h3>", table(extra, 2),
            "<h3>Trend of Table 2's origins over its iterations [µm per iteration]</h3>", table(trend, 3),
            "<h3>Table 1's origin against the bias pair, noise-free rig with current-sensor errors [µm]</h3>",
            table(bpc, 2)]
    for t, title in ((1, "Table 1: three bias pairs, ±20 µm"), (2, "Table 2: 10 iterations of Table 1's experiment 2"),
                     (3, "Table 3: four initial rotor positions"),
                     (4, "Table 4: after rotor reassembly")):
        body += [f"<h2>{title}</h2>", table(_side_by_side(comp, t), 2)]
        if t == 2:
            body += [figs["fig5_iterations.png"],
                     _p("Fig. 5 as in the paper: origins (top) and gaps (bottom) over the iterations; squares are the "
                        "paper's Table 2, circles this reproduction, bands the rig's 5-95 % range per iteration.")]
    body += ["<h2>Fig. 2: solution space</h2>", figs["fig2_solution_space.png"], figs["fig2_map.png"],
             _p("The paper's axes: v-axis effective gap 600-1000 µm, origin -100...100 µm, 1 µm steps; vertical: RMS "
                "force error. Data: the paper's first iteration (pairs at ±20 µm in sensor coordinates, not symmetric "
                "about the effective origin) with one unknown load per position, as Eq. 5-7 see it. "
                + (f"Least squares: g_v0 = {fig2_ls[0]:.0f} ± {fig2_ls[1]:.0f} µm, v0 = {fig2_ls[2]:.1f} ± "
                   f"{fig2_ls[3]:.1f} µm, correlation {fig2_ls[4]:+.3f}. " if isinstance(fig2_ls, tuple) else "")
                + "At one position Eq. 6 fixes only the ratio of the two gaps, i.e. (x0 + x)/g0: every point on a "
                "line through the origin of the (gap, x0 + x) plane fits. Two positions close together compared "
                "with their distance from the effective origin give two nearly parallel lines, and noise slides the "
                "solution along the valley between them: the paper's \"wide range series of solutions\"."),
             "<h2>Fig. 3: position pairs</h2>", figs["fig3_position_pairs.png"], figs["fig3_position_pairs_table4.png"],
             _p("Symmetric pairs (v1, -v1) about each iteration's centre: Table 2 (±20 µm, first pair about the back-up "
                "bearing centre, then about the estimated effective origin) and Table 4 (±50 µm after reassembly). "
                "Table 4's ±50 µm pairs about the reassembled effective origin (47.4, -13.1 µm in sensor coordinates) "
                "reach about 98 µm from the back-up bearing centre, beyond the 60 µm clearance implied by the paper's "
                "\"±20 µm = one third of the radial distance\": either the clearance is larger than that sentence "
                "implies or the Table 4 pairs were taken about another centre. The rig has no back-up bearing and "
                "does not object."),
             "<h2>The paper's own sim-to-real gap</h2>", _p(_gap_text(pub, demo))]
    if demo is not None:
        rows = []
        for name, e in demo["scenarios"].items():
            pp = e["paper_protocol"]
            rows.append({"true effect (nominal 762 µm)": name, "design": "paper (Table 2)",
                         "g_v0 [µm]": pp["g_v0_um"][0], "± se": pp["g_v0_um"][1], "verdict": pp["verdict"]})
            if "bias_sweep" in e:
                bs = e["bias_sweep"]
                rows.append({"true effect (nominal 762 µm)": name, "design": "bias sweep 0.6-2.6 A",
                             "g_v0 [µm]": bs["g_v0_um"][0], "± se": bs["g_v0_um"][1], "verdict": bs["verdict"]})
        body.append(table(pd.DataFrame(rows), 1))
    html_path = out / "index.html"
    html_path.write_text(page("ambfit: the seed paper's Tables 1-4 and Figs. 2, 3, 5 on the virtual rig", body,
                              _footer(command or f"ambfit paper --out {out}", time.perf_counter() - t0)))
    return html_path


def _gap_spread_text(gaps, acf, extra) -> str:
    g_lo, g_hi = gaps["ratio"].min(), gaps["ratio"].max()
    low = gaps[gaps["percentile"] < 5]
    high = gaps[gaps["percentile"] > 95]
    a = acf.set_index("quantity")
    rho = float(a.loc["g_v0_um", "paper"])
    s = (f"Gap spread between rows (prediction): the paper's sd is {g_lo:.2f}-{g_hi:.2f} times the rig's median, "
         f"so the noise calibrated on Table 2 predicts it within a factor {max(1 / g_lo, g_hi):.1f}. ")
    t13 = gaps[gaps["table"] != 4]
    s += ("Percentiles of the paper's gap spread in the rig's distribution: "
          + ", ".join(f"Table {t} {q[:-3]} {p:.1f}" for t, q, p in zip(gaps["table"], gaps["quantity"],
                                                                          gaps["percentile"])) + ". ")
    if len(low) or (t13["percentile"] < 50).all():
        below = ", ".join(f"Table {t} {q[:-3]}" for t, q in zip(low["table"], low["quantity"]))
        s += (f"In Tables 1 and 3 the paper's rows agree better than predicted in {int((t13['percentile'] < 50).sum())} "
              f"of {len(t13)} cases{f' ({below} below the 5th percentile)' if len(low) else ''}. "
              f"A possible reason is that the paper's iterations are not independent: Table 2's v-axis gap has a lag-1 "
              f"autocorrelation of {rho:+.2f} (the {a.loc['g_v0_um', 'percentile']:.0f}th percentile of independent "
              f"iterations on the rig, so not significant on its own); errors alternating with that correlation make "
              f"the sd of a 10-iteration mean sqrt(1 + 2 · 0.9 · ρ) = {np.sqrt(max(1 + 1.8 * rho, 0.05)):.2f} times "
              f"the independent value. Table 2 may also simply have been a noisier experiment than the others. ")
    if len(high):
        e = extra.set_index(["table", "quantity"])
        s += ("Above the rig's 95th percentile: " + ", ".join(
            f"Table {t} {q[:-3]} (extra between-experiment sd {e.loc[(t, q), 'extra_sd']:.1f} µm)"
            for t, q in zip(high["table"], high["quantity"])) + "; Table 4's w-axis rows at 1.0/1.4 A read 750.7 and "
            "773.3 µm, where the rig predicts a row sd of about 3 µm for ±30/40 µm pairs. ")
    return s


def _eq7_bias_text(comp, rep) -> str:
    truth = {"g_v0_um": rep.spec.g0[0] * 1e6, "g_w0_um": rep.spec.g0[1] * 1e6}
    t1 = comp[(comp["table"] == 1) & (comp["row"] > 0) & comp["quantity"].isin(list(truth))]
    parts = []
    for r in sorted(t1["row"].unique()):
        sub = t1[t1["row"] == r].set_index("quantity")
        label = sub["label"].iloc[0].split(" ", 1)[1].split(" ±")[0]
        bias = [sub.loc[q, "rig_mean"] - truth[q] for q in truth]
        se = [sub.loc[q, "rig_sd"] / np.sqrt(rep.replicates.shape[0]) for q in truth]
        ls = [sub.loc[q, "ls"] - truth[q] for q in truth]
        parts.append(f"{label}: {bias[0]:+.1f} ± {se[0]:.1f} / {bias[1]:+.1f} ± {se[1]:.1f} µm "
                     f"(least squares on this run: {ls[0]:+.1f} / {ls[1]:+.1f} µm)")
    return ("The paper's estimator is itself biased. Eq. 7 is nonlinear in the currents, and its mean over "
            "iterations overestimates the gap (v / w, the rig's mean minus its true gap, ± Monte Carlo error): "
            + "; ".join(parts) + ". The bias grows as the two biases approach (the ratio P of Eq. 6 becomes a "
            "quotient of small differences), so Table 1's 0.1 A pairs are read high by several µm. With a predicted "
            "row sd of about 20 µm for those pairs, the paper's three rows can neither confirm nor exclude it. "
            "ambfit's least squares uses every reading at once; its bias at this noise level is below 0.15 of its "
            "standard error (reports/benchmarks/ls_bias.md).")


def _origin_spread_text(origins, extra, comp, t2, bpc, trend) -> str:
    o_lo, o_hi = origins["ratio"].min(), origins["ratio"].max()
    n_high = int((origins["percentile"] > 95).sum())
    ex = extra[~extra["quantity"].str.startswith("g_")]["extra_sd"]
    rng = {e: float(g["v0_um"].max() - g["v0_um"].min()) for e, g in bpc.groupby("effect", sort=False)}
    from ambfit.studies.paper import load_table

    v1 = load_table(1)["v0_um"].to_numpy(float)
    step_v = float(np.mean(np.diff(v1)))
    tv = trend.set_index("quantity").loc["v0_um"]
    need_v = step_v / (len(load_table(2)) - 1)
    z_v = abs(need_v - tv["paper_slope"]) / tv["paper_se"]
    zmax = comp[(comp["table"] != 2) & (comp["row"] > 0) & ~comp["quantity"].str.startswith("g_")]["z"].abs().max()
    return (f"Origin spread between rows (prediction): the paper's sd is {o_lo:.1f}-{o_hi:.1f} times the rig's "
            f"median ({n_high} of {len(origins)} table/axis cases above the rig's 95th percentile), so the rig "
            f"under-predicts it by up to a factor {o_hi:.0f}. Within one experiment the paper's origin scatters as "
            f"the rig's does (Table 2: {t2.loc['v0_um', 'paper_sd']:.2f} µm against {t2.loc['v0_um', 'rig_median']:.2f} "
            f"µm on v), but between experiments it moves by an extra {ex.min():.1f}-{ex.max():.1f} µm (sd), which "
            f"per-reading white noise cannot produce: the paper's noise is not white. Inside Table 2 the origin "
            f"trends by " + "; ".join(f"{r.quantity[:-3]} {r.paper_slope:+.2f} ± {r.paper_se:.2f} µm per iteration "
                                      f"({r.over_experiment:+.1f} µm over iterations {r.iterations}, percentile "
                                      f"{r.percentile:.0f} of the rig's)" for r in trend.itertuples())
            + f". On w a drift running during the experiments (thermal growth of rotor and sensor mounts moves the "
            f"origin 0.3-2 µm/K) is consistent with that trend. On v, Table 1's origin falls 35.08 → 31.75 → 28.77 µm "
            f"from experiment to experiment ({step_v:+.2f} µm each); drifting continuously, that would be "
            f"{need_v:+.2f} µm per iteration inside Table 2 (Table 1's experiment 2), {z_v:.1f} standard errors from "
            f"the measured trend. So on v the change happens between experiments (re-levitation, sensor re-zeroing, "
            f"temperature change during pauses) or depends on the bias pair (6.3 µm over Table 1), which a "
            f"current-sensor offset or gain mismatch on the rig does not "
            f"reproduce: noise-free, the rig's Table 1 origin varies across the three bias pairs by "
            + ", ".join(f"{v:.2f} µm with {e}" for e, v in rng.items()) + " (they shift the origin by about the "
            f"same amount at every bias pair). Row by row this shows as origins up "
            f"to {zmax:.0f} predicted sd from the rig's mean.")


def _strip(text: str) -> str:
    import re

    return re.sub(r"<[^>]+>", "", text)


def _gap_text(pub: list[dict], demo: dict | None) -> str:
    gv = next(e for e in pub if e["parameter"] == "g_v0_um")
    gw = next(e for e in pub if e["parameter"] == "g_w0_um")
    cb = {c["effect"]: c for c in gv.get("could_be", [])}
    s = (f"The paper's effective gaps, {gv['identified']:.1f} ± {gv['std']:.1f} µm (v) and {gw['identified']:.1f} ± "
         f"{gw['std']:.1f} µm (w) (mean of the Table 1, 3, 4 averages ± their standard error), exceed the nominal "
         f"762 µm by {gv['difference']:.1f} µm ({gv['z']:.0f} se) and {gw['difference']:.1f} µm ({gw['z']:.1f} se). "
         f"The v-axis excess is real. Candidates in ambfit's library: ")
    if cb:
        s += "; ".join(f"{k.replace('_', ' ')} ({c['needs']}{', implausible' if not c.get('plausible', True) else ''}"
                       f"{', ' + c['note'] if 'note' in c else ''})" for k, c in cb.items()) + ". "
    rel = gv["difference"] / gv["nominal"] * 100
    s += (f"A sensor gain error of {rel:.2f} % is {rel / 0.25:.1f} times the paper's micrometer calibration (0.25 %), "
          f"so it is unlikely. Iron reluctance is plausible on v, but the same iron on w would need a permeability "
          f"{gv['difference'] / max(gw['difference'], 1e-9):.1f} times higher for its {gw['difference']:.1f} µm "
          "excess: the two axes' different excesses point to a geometric difference (eccentric stator or sensor "
          "mount) on top of, or instead of, a common iron path. ")
    if demo is not None:
        sc = demo["scenarios"]
        ir, pg = sc["iron_reluctance"], sc["position_gain"]
        s += (f"On a rig with the nominal 762 µm gap, iron reluctance (μr {demo['implied']['iron_reluctance_mu_r'][0]:.0f}"
              f" over {demo['implied']['iron_path_mm']:.0f} mm) gives an effective g_v0 of "
              f"{ir['paper_protocol']['g_v0_um'][0]:.1f} ± {ir['paper_protocol']['g_v0_um'][1]:.1f} µm with the paper's "
              f"protocol and a {pg['paper_protocol'].get('verdict')} verdict; a +"
              f"{demo['implied']['position_gain_percent'][0]:.2f} % sensor gain gives "
              f"{pg['paper_protocol']['g_v0_um'][0]:.1f} ± {pg['paper_protocol']['g_v0_um'][1]:.1f} µm, also "
              f"'{pg['paper_protocol']['verdict']}'. The paper's data cannot separate them: at 1.4-1.6 A the iron's "
              f"extra gap is constant and is absorbed into g0, exactly like a sensor gain or fringing. ")
        if "bias_sweep" in ir:
            s += (f"A bias sweep 0.6-2.6 A (flux density up to about 1 T) separates them: the diagnosis names "
                  f"'{ir['bias_sweep']['verdict']}' for the iron (held-out excess {ir['bias_sweep']['heldout_excess']:.2f}"
                  f" noise units removed, shrink {ir['bias_sweep']['shrink']:.2f}) and '{pg['bias_sweep']['verdict']}' "
                  f"for the sensor gain, which then needs a known-displacement calibration to be seen at all.")
    return s
