"""Sim-to-real on physics nobody here wrote: the FEM development data of an 8-pole bearing.

``../shared/fem/fem_dev.csv`` comes from an independent 2-D nonlinear finite-element model (fringing,
slot leakage, finite iron with a B-H curve, flux shared between horseshoes); its bearing description
``fem_dev.toml`` and the sensor offsets in ``fem_dev_meta.json`` are what a rig engineer would know.
This script reports:

1. least squares with the ideal law and with the magnetic circuit (``magnetic_circuit``): χ²/dof,
   gaps and origins against the drawing (762 µm) and the sensor offsets;
2. ``ambfit.diagnose`` with the bearing description: verdict, the circuit's pieces and their χ² rise,
   held-out shrink;
3. leave-one-load-out force measurement (contract ``force_check``) for the ideal law and the circuit,
   with the noise floor of that figure (the RMS of each reading's force noise over its load);
4. the circuit's identified parameters next to what the drawing implies (``MECParams.drawing``);
5. wall times.

    .venv/bin/python benchmarks/fem.py [--data ../shared/fem/fem_dev.csv] [--bearing ../shared/fem/fem_dev.toml]

Writes reports/benchmarks/fem.{json,md}.
"""

import argparse
import json
import time
from pathlib import Path

import jax.numpy as jnp
import numpy as np

import ambfit
from ambfit.data import read_csv
from ambfit.diagnosis import Rules, circuit_families
from ambfit.estimation.measure import force_check, force_noise
from ambfit.physics.circuit import MECParams
from ambfit.physics.effects import MagneticCircuit

ROOT = Path(__file__).resolve().parents[1]
SHARED = ROOT.parent / "shared" / "fem"


def head(res) -> dict:
    return {n: {"value": float(v), "std": float(s)} for n, v, s in zip(res.names, res.values, res.std)
            if not n.startswith("load[")}


def noise_floor_rel(res, df) -> float:
    """RMS over the known-load readings of (force noise / load): the best any model's force check can do.

    The force noise of a reading is its effective-variance std (current and position noise propagated
    through the model, :func:`ambfit.estimation.measure.force_noise`)."""
    s = force_noise(res, df)
    load = df["load_N"].to_numpy(float)
    ok = np.isfinite(load) & (np.abs(load) > 0)
    return float(np.sqrt(np.mean((s[ok] / load[ok]) ** 2)))


def main():
    ap = argparse.ArgumentParser(description="ambfit on the FEM development data")
    ap.add_argument("--data", type=Path, default=SHARED / "fem_dev.csv")
    ap.add_argument("--bearing", type=Path, default=SHARED / "fem_dev.toml")
    ap.add_argument("--meta", type=Path, default=SHARED / "fem_dev_meta.json")
    ap.add_argument("--out", type=Path, default=ROOT / "reports" / "benchmarks")
    args = ap.parse_args()
    bearing = ambfit.Bearing.from_toml(args.bearing)
    ds = read_csv(args.data)
    df = ds.frame
    meta = json.loads(args.meta.read_text()) if args.meta.exists() else {}
    out = {"data": str(args.data), "bearing": str(args.bearing), "rows": len(df), "times_s": {}}

    t = time.perf_counter()
    ideal = ambfit.fit(ds, bearing=bearing, throw=False)
    out["times_s"]["fit ideal"] = time.perf_counter() - t
    t = time.perf_counter()
    mec = ambfit.fit(ds, [MagneticCircuit()], bearing=bearing, start_from=ideal, throw=False)
    out["times_s"]["fit circuit (cold)"] = time.perf_counter() - t
    t = time.perf_counter()
    ambfit.fit(ds, [MagneticCircuit()], bearing=bearing, start_from=ideal, throw=False)
    out["times_s"]["fit circuit (warm)"] = time.perf_counter() - t
    out["fits"] = {name: {"model": r.model, "reduced_chi2": r.reduced_chi2, "dof": r.dof, "converged": r.converged,
                          "params": head(r)} for name, r in (("ideal", ideal), ("circuit", mec))}
    out["drawing"] = {"nominal_gap_um": bearing.nominal_gap * 1e6, "sensor_offset_um": meta.get("sensor_offset_um"),
                      "k_geometric": bearing.force_constant(1.0)}
    drawn = MECParams.drawing(bearing)
    out["circuit_vs_drawing"] = {
        "fringe_depth_mm": {"identified": mec.value("magnetic_circuit.fringe_depth") * 1e3,
                            "drawing": float(drawn.fringe_depth) * 1e3,
                            "note": "half the slot opening at the bore, capped at 3 mm"},
        "leakage": {"identified": mec.value("magnetic_circuit.leakage"), "drawing": float(drawn.leakage),
                    "note": "slot leakage shape factor of open slots (0.2-1)"},
        "iron_scale": {"identified": mec.value("magnetic_circuit.iron_scale"), "drawing": 1.0,
                       "note": "B-H curve's H times this over the drawn iron path"},
        "pole_area_ratio": {"identified": mec.value("magnetic_circuit.pole_area_ratio"), "drawing": None,
                            "note": "pole body over pole face; not in the description"},
        "k_factor": {"identified": [mec.value(f"k_{a}") / bearing.force_constant(1.0) for a in "vw"],
                     "drawing": 1.0, "note": "k over MU_0 A (2N)^2 cos(alpha) / 4"},
    }
    # the fringe depth, the gap and k share a valley: the fit with the depth held at the drawing's value and at
    # the designer range's upper end, next to the free fit
    profile = []
    for label, depth in (("drawing", float(drawn.fringe_depth)), ("3 mm", 3e-3), ("5 mm", 5e-3), ("free", None)):
        r = mec if depth is None else ambfit.fit(
            ds, [MagneticCircuit(fringe_depth=jnp.asarray(depth), held=("fringe_depth",))], bearing=bearing,
            start_from=ideal, throw=False)
        profile.append({"fringe_depth": label, "fringe_depth_mm": (r.value("magnetic_circuit.fringe_depth")
                                                                   if depth is None else depth) * 1e3,
                        "reduced_chi2": r.reduced_chi2, "converged": r.converged,
                        "g_v0_um": r.value("g_v0") * 1e6, "g_w0_um": r.value("g_w0") * 1e6,
                        "k_factor": r.value("k_v") / bearing.force_constant(1.0),
                        "leakage": r.value("magnetic_circuit.leakage"),
                        "iron_scale": r.value("magnetic_circuit.iron_scale")})
    out["fringe_profile"] = profile
    t = time.perf_counter()
    out["force_check"] = {"ideal": force_check(ds, (), bearing=bearing, base=ideal, discrepancy=True),
                          "circuit": force_check(ds, mec.effects, bearing=bearing, base=mec, discrepancy=True)}
    out["times_s"]["force checks"] = time.perf_counter() - t
    out["force_noise_floor_rms_rel"] = noise_floor_rel(mec, df)
    t = time.perf_counter()
    dg = ambfit.diagnose(ds, bearing=bearing, check_force=False)
    out["times_s"]["diagnose (first in this process)"] = time.perf_counter() - t
    t = time.perf_counter()
    ambfit.diagnose(ds, bearing=bearing, check_force=False)
    out["times_s"]["diagnose (again, warm)"] = time.perf_counter() - t
    rec = dg.to_json()
    out["diagnose"] = {"verdict": dg.verdict, "shrink": dg.shrink, "heldout_excess_before": dg.heldout_excess_before,
                       "families": rec.get("families"), "ranking": [{"effect": c.effect, "shrink": c.shrink,
                                                             "heldout_excess_after": c.after} for c in dg.ranking],
                       "discrepancy": rec.get("discrepancy"), "parameter_gap": rec.get("parameter_gap")}
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "fem.json").write_text(json.dumps(out, indent=2, default=float))

    fi, fc = out["fits"]["ideal"], out["fits"]["circuit"]
    off = meta.get("sensor_offset_um", {})
    md = ["# FEM development data (8-pole bearing, independent nonlinear FEM)", "",
          f"`{args.data.name}`, {len(df)} readings, bearing `{args.bearing.name}`.", "",
          "| model | χ²/dof | g_v0 [µm] | g_w0 [µm] | v0 [µm] | w0 [µm] | k_v / k_geom | LOLO force RMS | LOLO max "
          "| LOLO beyond the readings' noise | LOLO RMS of each load's mean |",
          "|---|---|---|---|---|---|---|---|---|---|---|"]
    for name, f in (("ideal law", fi), ("magnetic circuit", fc)):
        p = f["params"]
        chk = out["force_check"]["ideal" if name == "ideal law" else "circuit"]
        md.append(f"| {name} | {f['reduced_chi2']:.2f} | {p['g_v0']['value'] * 1e6:.1f} ± {p['g_v0']['std'] * 1e6:.1f} | "
                  f"{p['g_w0']['value'] * 1e6:.1f} ± {p['g_w0']['std'] * 1e6:.1f} | "
                  f"{p['v0']['value'] * 1e6:.2f} | {p['w0']['value'] * 1e6:.2f} | "
                  f"{p['k_v']['value'] / bearing.force_constant(1.0):.3f} | {100 * chk['rms_rel']:.2f} % | "
                  f"{100 * chk['max_rel']:.2f} % | {100 * chk['model_error_rel']:.3f} % | "
                  f"{100 * chk['rms_rel_mean']:.3f} % |")
        d = chk["discrepancy"]
        md.append(f"| {name} + discrepancy | | (same) | | | | | {100 * d['rms_rel']:.2f} % | {100 * d['max_rel']:.2f} % | "
                  f"{100 * d['model_error_rel']:.3f} % | {100 * d['rms_rel_mean']:.3f} % |")
    md += [f"| drawing / meta | | {bearing.nominal_gap * 1e6:.0f} | {bearing.nominal_gap * 1e6:.0f} | "
           f"{off.get('v', '–')} | {off.get('w', '–')} | 1 | noise floor {100 * out['force_noise_floor_rms_rel']:.2f} % | "
           "| | |",
           "", "LOLO: each known load left out, the model fitted to the others, the left-out readings' force predicted "
           "(contract `force_check`, per reading). The readings' own noise sets the per-reading floor: no model's "
           "per-reading RMS can go below it, so the issue's 0.15 % per reading is out of reach on this file. "
           "*Beyond the readings' noise* is the per-reading RMS less that floor in quadrature, "
           "sqrt(RMS² − floor²): the model's own error. A load's mean over its readings averages the noise away "
           "and shows the model's error too.", "",
           f"Diagnose: verdict **{dg.verdict}**, held-out shrink {dg.shrink:.3f} (held-out excess before "
           f"{dg.heldout_excess_before:.1f} noise units).", ""]
    disc = rec.get("discrepancy")
    if disc:
        md += [f"Discrepancy (orthogonal to every fitted parameter): held-out shrink {disc['ideal']['shrink']:.3f} on "
               "the ideal law" + (f", {disc['verdict']['shrink']:.3f} on {disc['verdict']['model']}"
                                  if "verdict" in disc else "") + f"; log Bayes factor per group on {disc.get('fitted_on', 'the model')}'s "
               "residuals (above 10: clearly wanted): "
               + ", ".join(f"{k} {v:.1f}" for k, v in disc["log_bayes"].items()) + ".", ""]
    flagged = [e for e in rec.get("parameter_gap", []) if e.get("flagged") and e["parameter"].startswith("g_")]
    if flagged:
        md += ["| ideal law's gap | identified [µm] | drawing [µm] | explanation | plausible |", "|---|---|---|---|---|"]
        for e in flagged:
            for c in e.get("could_be", []):
                md.append(f"| {e['parameter']} | {e['identified']:.1f} | {e['nominal']:.0f} | {c['effect']}: "
                          f"{c['needs']} | {c.get('plausible', '–')} |")
        md.append("")
    if rec.get("families"):
        md += ["| circuit piece | family | χ² rise when off | bounds (refit not settled) | counts |",
               "|---|---|---|---|---|"]
        md += [f"| {f['piece']} | {f['family']} | {f['delta_chi2']:.0f} | "
               + ("settled" if f["delta_chi2_bounds"][0] == f["delta_chi2_bounds"][1] else
                  "{:.0f} – {:.0f}".format(*f["delta_chi2_bounds"]))
               + f" | {'yes' if f['significant'] else 'no'} |" for f in rec["families"]]
        md += ["", "Each piece switched off, the circuit refitted with the full model's noise weights held (every χ² "
               "weighs the readings alike). A refit runs until its χ² is settled (EDM below "
               f"{100 * circuit_families.SETTLED_EDM:g} % of the threshold, {Rules().circuit_dchi2:g} sd of χ²) or "
               "its piece's significance is decided, taking its χ² to fall by at most "
               f"{circuit_families.EDM_MARGIN:g} EDMs more; iron_reluctance is the ideal-iron refit (started from the "
               "constant-permeability one, the nearer model) less the constant-permeability one."]
        md.append("")
    md += ["| circuit parameter | identified | drawing implies | note |", "|---|---|---|---|"]
    for k, v in out["circuit_vs_drawing"].items():
        ident = ", ".join(f"{x:.3g}" for x in v["identified"]) if isinstance(v["identified"], list) else f"{v['identified']:.3g}"
        md.append(f"| {k} | {ident} | {v['drawing'] if v['drawing'] is not None else '–'} | {v['note']} |")
    md += ["", "The fringe depth, the gap and k share a valley: the circuit fitted with the depth held (the drawing "
           "implies half the slot opening at the bore), and free:", "",
           "| fringe depth | [mm] | χ²/dof | g_v0 [µm] | g_w0 [µm] | k_v / k_geom | leakage | iron_scale |",
           "|---|---|---|---|---|---|---|---|"]
    md += [f"| {p['fringe_depth']} | {p['fringe_depth_mm']:.2f} | {p['reduced_chi2']:.3f} | {p['g_v0_um']:.1f} | "
           f"{p['g_w0_um']:.1f} | {p['k_factor']:.3f} | {p['leakage']:.2f} | {p['iron_scale']:.3f} |" for p in profile]
    md += ["", "Wall times [s]: " + ", ".join(f"{k} {v:.1f}" for k, v in out["times_s"].items()) + "."]
    (args.out / "fem.md").write_text("\n".join(md) + "\n")
    print("\n".join(md))


if __name__ == "__main__":
    main()
