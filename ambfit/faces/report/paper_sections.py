"""The sections of the paper report: one function of a result per section, returning its macro's context.

Most take the :class:`ambfit.studies.paper.Reproduction` and read the paper's numbers
from its tables (``data/paper/*.csv`` through :func:`ambfit.studies.paper.load_table`
and :func:`~ambfit.studies.paper.settings`); the rig's from its spec and bearing.  The
prose is in ``templates/paper_sections.html.j2``.  ``low`` and ``high`` are the
percentiles of the rig's distribution beyond which a paper value counts as unusual.
"""

from __future__ import annotations

import numpy as np
import pandas as pd

from ambfit.faces.report.render import table
from ambfit.physics.bearing import PAPER_BEARING
from ambfit.studies import paper as study

ITERATIONS_TABLE = 2
"""The table whose rows are the iterations of one experiment (Table 1's row 2), not experiments."""


def _prediction(spread: pd.DataFrame, gaps: bool) -> pd.DataFrame:
    pred = spread[spread["role"] == "prediction"]
    return pred[pred["quantity"].str.startswith("g_") == gaps]


def _calibration(rep) -> pd.DataFrame:
    sp = rep.spread()
    return sp[sp["role"] == "calibration"].set_index("quantity")


def _shifted(rep):
    """The first row after the reassembly (an origin shift), or None."""
    return next((r for r in rep.rows if r.origin_shift != (0.0, 0.0)), None)


def widest_shifted_row(rep) -> int:
    """Index of the reassembled row with the widest position pairs (the Fig. 3 example of Table 4)."""
    shifted = [j for j, r in enumerate(rep.rows) if r.origin_shift != (0.0, 0.0)]
    return max(shifted, key=lambda j: rep.rows[j].offset)


def intro(rep) -> dict:
    """How the reproduction was run: protocol, noise, replicates and the rig's truth (µm, mA)."""
    shifted = _shifted(rep)
    source = rep.rows[rep.table2_index]
    return {"tables": sorted({r.table for r in rep.rows}), "iterations": int(rep.run.shape[1]),
            "source": {"table": source.table, "row": source.row},
            "current_noise_mA": rep.noise.current * 1e3, "position_noise_um": rep.noise.position * 1e6,
            "replicates": int(rep.replicates.shape[0]), "failed": rep.failed,
            "gap_um": [g * 1e6 for g in rep.spec.g0], "origin_um": [x * 1e6 for x in rep.spec.x0],
            "shifted": None if shifted is None else {
                "table": shifted.table,
                "origin_um": [(x + s) * 1e6 for x, s in zip(rep.spec.x0, shifted.origin_shift)]}}


def spread(rep) -> dict:
    """The paper's spread against the rig's prediction, per table and quantity."""
    frame = rep.spread().drop(columns=["rig_run_sd"])
    return {"frame": frame, "table": table(frame, 2)}


def calibration(rep) -> dict:
    """Table 2's per-iteration scatter, the current noise it calls for, and the iterations that inflate it."""
    cal = _calibration(rep)
    t2 = study.load_table(ITERATIONS_TABLE)
    g_w, w0 = t2["g_w0_um"].to_numpy(float), t2["w0_um"].to_numpy(float)
    k = int(np.argmax(np.abs(g_w - g_w.mean())))
    noise = rep.noise_calibration()
    return {"paper_sd": cal["paper_sd"].to_dict(), "rig_median": cal["rig_median"].to_dict(), "noise": noise,
            "interval_percent": noise["prob"] * 100,
            "outlier": {"iteration": int(t2["iteration"].iloc[k]), "g_w0_um": float(g_w[k])},
            "first": {"iteration": int(t2["iteration"].iloc[0]), "w0_um": float(w0[0]),
                      "w0_sd_without": float(np.std(w0[1:], ddof=1))}}


def _row_pair(comp: pd.DataFrame, t: int, quantity: str) -> dict | None:
    """The two rows of table ``t`` at one bias pair that differ most in ``quantity``, with the rig's row sd."""
    tab = study.load_table(t)
    if "bias_low_A" not in tab:
        return None
    axis = quantity.removeprefix("g_")[0]
    best = None
    for biases, group in tab.groupby(["bias_low_A", "bias_high_A"], sort=False):
        if len(group) > 1 and (best is None or np.ptp(group[quantity]) > np.ptp(best[1][quantity])):
            best = (biases, group)
    if best is None:
        return None
    rows = best[1].loc[sorted([best[1][quantity].idxmin(), best[1][quantity].idxmax()])]
    sel = (comp["table"] == t) & (comp["quantity"] == quantity) & comp["row"].isin(rows["source_row"].astype(int))
    return {"table": t, "axis": axis, "biases": [float(b) for b in best[0]], "values_um": rows[quantity].tolist(),
            "pairs_um": rows[f"pair_{axis}_um"].tolist(), "rig_sd": float(comp.loc[sel, "rig_sd"].mean())}


def gap_spread(rep, *, low: float = 5.0, high: float = 95.0) -> dict:
    """The paper's between-row gap spread against the rig's prediction, and what may explain the misses."""
    gaps = _prediction(rep.spread(), gaps=True)
    acf = rep.autocorrelation().set_index("quantity")
    extra = rep.between_experiment_sd().set_index(["table", "quantity"])
    comp = rep.comparison()
    shifted = {r.table for r in rep.rows if r.origin_shift != (0.0, 0.0)}
    before = gaps[~gaps["table"].isin(shifted)]     # the tables before the reassembly
    below, above = gaps[gaps["percentile"] < low], gaps[gaps["percentile"] > high]
    n = len(study.load_table(ITERATIONS_TABLE))
    rho = float(acf.loc["g_v0_um", "paper"])
    weight = (n - 1) / n                            # var of an n-mean: (1 + 2 (n-1)/n rho) sigma^2 / n
    better = None
    if len(below) or (before["percentile"] < 50).all():
        better = {"tables": sorted(before["table"].unique().tolist()), "count": int((before["percentile"] < 50).sum()),
                  "of": len(before), "below": [{"table": t, "quantity": q.removesuffix("_um")}
                                               for t, q in zip(below["table"], below["quantity"])]}
    return {"ratio": (float(gaps["ratio"].min()), float(gaps["ratio"].max())),
            "factor": float(max(1 / gaps["ratio"].min(), gaps["ratio"].max())), "low": low, "high": high,
            "percentiles": [{"table": t, "quantity": q.removesuffix("_um"), "percentile": p}
                            for t, q, p in zip(gaps["table"], gaps["quantity"], gaps["percentile"])],
            "better": better, "rho": rho, "rho_percentile": float(acf.loc["g_v0_um", "percentile"]), "iterations": n,
            "weight": weight, "sd_factor": float(np.sqrt(max(1 + 2 * weight * rho, 0.05))),
            "above": [{"table": t, "quantity": q.removesuffix("_um"), "extra_sd": float(extra.loc[(t, q), "extra_sd"]),
                       "example": _row_pair(comp, t, q)} for t, q in zip(above["table"], above["quantity"])]}


def origin_spread(rep, bias_check: pd.DataFrame, *, low: float = 5.0, high: float = 95.0) -> dict:
    """The paper's origin spread: within and between experiments, the trend inside Table 2 and the step across
    Table 1, against what current-sensor errors on the rig produce (``bias_check``:
    :func:`ambfit.studies.paper_gap.bias_pair_check`)."""
    origins = _prediction(rep.spread(), gaps=False)
    extra = rep.between_experiment_sd()
    extra = extra[~extra["quantity"].str.startswith("g_")]["extra_sd"]
    comp = rep.comparison()
    cal = _calibration(rep)
    trend = rep.trend()
    t1 = study.load_table(1)["v0_um"].to_numpy(float)
    step = float(np.mean(np.diff(t1)))
    need = step / (len(study.load_table(ITERATIONS_TABLE)) - 1)
    tv = trend.set_index("quantity").loc["v0_um"]
    rig_range = {e: float(np.ptp(g["v0_um"])) for e, g in bias_check.groupby("effect", sort=False)}
    rows = comp[(comp["table"] != ITERATIONS_TABLE) & (comp["row"] > 0) & ~comp["quantity"].str.startswith("g_")]
    source = rep.rows[rep.table2_index]
    return {"ratio": (float(origins["ratio"].min()), float(origins["ratio"].max())),
            "n_high": int((origins["percentile"] > high).sum()), "n": len(origins), "low": low, "high": high,
            "within": {"paper_sd": float(cal.loc["v0_um", "paper_sd"]),
                       "rig_median": float(cal.loc["v0_um", "rig_median"])},
            "extra_sd": (float(extra.min()), float(extra.max())),
            "trend": [{"quantity": r.quantity.removesuffix("_um"), "slope": r.paper_slope, "se": r.paper_se,
                       "over": r.over_experiment, "iterations": r.iterations, "percentile": r.percentile,
                       "unusual": not low <= r.percentile <= high} for r in trend.itertuples()],
            "table1_v0_um": t1.tolist(), "step": step, "need": need,
            "z_step": float(abs(need - tv["paper_slope"]) / tv["paper_se"]), "table1_range": float(np.ptp(t1)),
            "source": {"table": source.table, "row": source.row},
            "rig_range": rig_range, "n_bias_pairs": int(bias_check["bias_pair"].nunique()),
            "z_max": float(rows["z"].abs().max())}


def origins_over_time(alpha: float | None = None) -> dict:
    """The paper's Tables 1 and 2 as a campaign over iterations (:func:`ambfit.studies.campaign.paper_origins`):
    the drift inside Table 2, the moves between Table 1's experiments against noise alone and with that drift
    removed, and (when no move survives the drift) how well the drift would have to be known for the largest
    to be flagged.  Numbers in µm; needs no reproduction (the paper's own numbers)."""
    from scipy import stats

    from ambfit.studies import campaign

    alpha = campaign.ALPHA if alpha is None else alpha
    po = campaign.paper_origins(alpha=alpha)
    um = 1e6

    def steps(cp):
        return [{"at": s.at, "after": s.before, "size": s.size * um, "se": s.std * um, "z": s.z, "p": s.p_bound,
                 "flagged": s.flagged} for s in cp.tests]

    def flags(result):
        return [{"quantity": q, "at": s.at, "z": s.z, "p": s.p_bound} for q, cp in result.items() for s in cp.flagged]

    drifts = {q: {"quantity": q, "slope": d.slope * um, "se": d.std * um, "over": d.slope * po.iterations * um,
                  "over_se": d.std * po.iterations * um, "reduced_chi2": d.reduced_chi2, "inflated": d.inflated}
              for q, d in po.drifts.items()}
    origins = [q for q in campaign.PARAMS if not q.startswith("g_")]
    best = max(((q, s) for q in origins for s in po.changes[q].tests), key=lambda qs: abs(qs[1].z))
    q, s = best
    needed = None
    if not s.flagged:
        z_crit = float(stats.norm.isf(alpha / (2 * s.m)))
        noise = po.sd[q] / np.sqrt(po.iterations)
        room = (s.size / z_crit) ** 2 - 2 * noise**2            # what is left for the drift's error over Δt
        dt = float(po.iterations)
        if room > 0:
            se_needed = np.sqrt(room) / dt
            needed = {"quantity": q, "at": s.at, "z": s.z, "p": s.p_bound, "se": s.std * um,
                      "noise_se": float(np.sqrt(2) * noise * um), "se_slope": float(se_needed * um),
                      "factor": float((po.drifts[q].std / se_needed) ** 2)}
    rows = []
    for q in campaign.PARAMS:
        for mv, ch in zip(po.moves[q].tests, po.changes[q].tests):
            rows.append({"quantity": q, "experiments": f"{mv.before} → {mv.at}", "move [µm]": mv.size * um,
                         "se": mv.std * um, "z": mv.z, "p (Bonferroni)": mv.p_bound,
                         "flagged": "yes" if mv.flagged else "no", "beyond drift [µm]": ch.size * um,
                         "se (drift)": ch.std * um, "z (drift)": ch.z, "p (drift, Bonferroni)": ch.p_bound,
                         "flagged (drift)": "yes" if ch.flagged else "no"})
    frame = pd.DataFrame(rows)
    shown = frame.assign(**{c: frame[c].map(lambda v: f"{v:.2g}") for c in frame.columns if c.startswith("p (")})
    k = po.iterations
    drift_frame = pd.DataFrame([{"quantity": d["quantity"], "drift [µm/iteration]": d["slope"], "se": d["se"],
                                 f"over {k} iterations [µm]": d["over"], f"se ({k})": d["over_se"],
                                 "χ²/dof": d["reduced_chi2"]} for d in drifts.values()])
    t1 = study.load_table(1)
    return {"first": po.first, "iterations": po.iterations, "source": po.source, "alpha": alpha,
            "n_boundaries": len(po.moves["v0"].tests),
            "sd": {q: v * um for q, v in po.sd.items()},
            "mean_se": {q: float(v * um / np.sqrt(po.iterations)) for q, v in po.sd.items()},
            "drift": drifts, "origin_drift": [drifts[q] for q in origins],
            "moves": {q: steps(po.moves[q]) for q in campaign.PARAMS},
            "changes": {q: steps(po.changes[q]) for q in campaign.PARAMS},
            "flagged_moves": flags(po.moves), "flagged_changes": flags(po.changes),
            "gaps_flagged": any(f["quantity"].startswith("g_") for f in flags(po.moves)),
            "table1": {q: t1[f"{q}_um"].tolist() for q in origins}, "needed": needed,
            "frame": frame, "shown": shown, "table": table(shown, 2), "drift_frame": drift_frame,
            "drift_table": table(drift_frame, 2)}


def eq7_bias(rep) -> dict:
    """The bias of the paper's estimator on Table 1's bias pairs: the rig's mean minus its truth, µm."""
    comp = rep.comparison()
    truth = {"g_v0_um": rep.spec.g0[0] * 1e6, "g_w0_um": rep.spec.g0[1] * 1e6}
    n_rep = rep.replicates.shape[0]
    rows = [r for r in rep.rows if r.table == 1]
    out = []
    for r in rows:
        sub = comp[(comp["table"] == 1) & (comp["row"] == r.row)].set_index("quantity")
        out.append({"biases": list(r.biases), "bias": [float(sub.loc[q, "rig_mean"] - truth[q]) for q in truth],
                    "se": [float(sub.loc[q, "rig_sd"] / np.sqrt(n_rep)) for q in truth],
                    "ls": [float(sub.loc[q, "ls"] - truth[q]) for q in truth]})
    diffs = np.array([r.biases[1] - r.biases[0] for r in rows])
    closest = np.isclose(diffs, diffs.min())
    close_rows = [r.row for r, c in zip(rows, closest) if c]
    sel = (comp["table"] == 1) & comp["row"].isin(close_rows) & comp["quantity"].isin(list(truth))
    return {"rows": out, "min_difference_A": float(diffs.min()), "n_rows": len(rows),
            "mean_bias": float(np.mean([e["bias"] for e, c in zip(out, closest) if c])),
            "overall_bias": float(np.mean([e["bias"] for e in out])), "row_sd": float(comp.loc[sel, "rig_sd"].mean())}


def supplements(rep, bias_check: pd.DataFrame) -> dict:
    """The tables behind the prose: autocorrelation, between-experiment sd, Table 2 trend, bias-pair check."""
    return {"autocorrelation": table(rep.autocorrelation(), 2), "between": table(rep.between_experiment_sd(), 2),
            "trend": table(rep.trend(), 3), "bias_check": table(bias_check, 2)}


def side_by_side(rep, t: int) -> dict:
    """Table ``t``: every row, paper against this run, the rig's prediction and (Tables 1, 3, 4) least squares."""
    comp = rep.comparison()
    sub = comp[comp["table"] == t]
    out = pd.DataFrame({
        "row": sub["row"].map(lambda r: "Average" if r == 0 else str(r)), "quantity": sub["quantity"],
        "paper": sub["paper"], "ambfit (this run)": sub["rig_run"], "rig predicted": sub["rig_mean"],
        "± sd": sub["rig_sd"], "paper − predicted [µm]": sub["diff"], "in sd": sub["z"]})
    if t != ITERATIONS_TABLE:
        out["ambfit least squares"] = sub["ls"]
        out["± se"] = sub["ls_std"]
    paper_rows = study.load_table(t)
    protocol = [r for r in rep.rows if r.table == t] or [rep.rows[rep.table2_index]]
    source = rep.rows[rep.table2_index]
    return {"number": t, "iterations": t == ITERATIONS_TABLE, "frame": out, "table": table(out, 2),
            "n_rows": len(paper_rows),
            "n_bias_pairs": len({r.biases for r in protocol}), "n_starts": len({r.start for r in protocol}),
            "pairs_um": sorted({round(r.offset * 1e6, 6) for r in protocol}),
            "shifted": any(r.origin_shift != (0.0, 0.0) for r in protocol),
            "source": {"table": source.table, "row": source.row}}


def fig2(space, result, data: pd.DataFrame) -> dict:
    """The Fig. 2 map's grid, the data's position pairs and the least-squares point.

    ``space``: :class:`~ambfit.estimation.conditioning.SolutionSpace`; ``result``: the
    :class:`~ambfit.estimation.results.FitResult` of ``data`` or the FitError that stopped it."""
    ls = None
    if not isinstance(result, Exception):
        ls = {"g_v0": (result.value("g_v0") * 1e6, result.error("g_v0") * 1e6),
              "v0": (result.value("v0") * 1e6, result.error("v0") * 1e6),
              "corr": float(result.corr[result.names.index("g_v0"), result.names.index("v0")])}
    own = data[data["axis"] == space.axis][f"{space.axis}_set_um"]
    return {"axis": space.axis, "gap_um": (space.gap.min() * 1e6, space.gap.max() * 1e6),
            "origin_um": (space.origin.min() * 1e6, space.origin.max() * 1e6),
            "step_um": float(np.diff(space.origin[:2])[0] * 1e6), "pairs_um": sorted(set(np.abs(own).round(6))),
            "least_squares": ls}


def fig3(rep) -> dict:
    """The position pairs of Table 2 and of the widest reassembled row, against the back-up bearing clearance."""
    source = rep.rows[rep.table2_index]
    wide = rep.rows[widest_shifted_row(rep)]
    centre = [-(x + s) * 1e6 for x, s in zip(rep.spec.x0, wide.origin_shift)]   # sensor coordinates
    reach = max(abs(c) for c in centre) + wide.offset * 1e6
    clearance = rep.spec.bearing.backup_clearance * 1e6
    quote = study.settings().set_index("quantity").loc["backup_clearance", "source"].split(": ", 1)[-1]
    return {"table2_pair_um": source.offset * 1e6, "table": wide.table, "pair_um": wide.offset * 1e6,
            "centre_um": centre, "reach_um": reach, "clearance_um": clearance, "quote": quote,
            "beyond": reach > clearance}


def own_gap(published: list, demo: dict | None = None, *, biases=(np.nan, np.nan), bearing=PAPER_BEARING) -> dict:
    """The paper's effective gaps against its nominal gap, the candidate effects and (``demo``) what the rig
    shows of them.

    ``published``: :func:`ambfit.studies.paper_gap.published_gap`; ``demo``:
    :func:`ambfit.studies.paper_gap.gap_demonstration` or None; ``biases``: the paper protocol's bias pair [A];
    ``bearing``: the calibration tolerance and current limit."""
    pg = {e["parameter"]: e for e in published}
    gv, gw = pg["g_v0_um"], pg["g_w0_um"]
    cands = [{"effect": c["effect"], "name": c["effect"].replace("_", " "), "needs": c["needs"],
              "implausible": c.get("plausible", True) is False, "note": c.get("note")} for c in gv.get("could_be", [])]
    rel = gv["difference"] / gv["nominal"] * 100
    tol = bearing.position_gain_tolerance * 100
    out = {"v": gv, "w": gw, "candidates": cands, "gain_percent": rel, "tolerance_percent": tol,
           "gain_implausible": any(c["implausible"] for c in cands if c["effect"] == "position_gain"),
           "iron_plausible": any(not c["implausible"] for c in cands if c["effect"] == "iron_reluctance"),
           "permeability_ratio": gv["difference"] / gw["difference"] if gw["difference"] > 0 else None,
           "demo": None, "demo_table": None}
    if demo is not None:
        sc = demo["scenarios"]
        out["demo"] = {"nominal_um": demo["nominal_gap_um"], "mu_r": demo["implied"]["iron_reluctance_mu_r"][0],
                       "iron_path_mm": demo["implied"]["iron_path_mm"],
                       "gain_percent": demo["implied"]["position_gain_percent"][0], "biases": list(biases),
                       "iron": sc["iron_reluctance"], "gain": sc["position_gain"], "max_current_A": bearing.max_current}
        out["demo_table"] = table(demo_frame(demo), 1)
    return out


def demo_frame(demo: dict) -> pd.DataFrame:
    """The gap demonstration as a table: each true effect, each design, the effective g_v0 and the verdict."""
    effect = f"true effect (nominal {demo['nominal_gap_um']:.0f} µm)"
    rows = []
    for name, e in demo["scenarios"].items():
        designs = [("paper (Table 2)", e["paper_protocol"])]
        if "bias_sweep" in e:
            designs.append((f"bias sweep ({e['bias_sweep']['n_rows']} readings)", e["bias_sweep"]))
        rows += [{effect: name, "design": d, "g_v0 [µm]": r["g_v0_um"][0], "± se": r["g_v0_um"][1],
                  "verdict": r["verdict"]} for d, r in designs]
    return pd.DataFrame(rows)
