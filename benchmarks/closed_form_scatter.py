"""Closed-form (Eq. 5-7) scatter on the paper's Table 2 protocol vs the paper's Table 2.

Checks the rig's default noise calibration: the per-iteration gap and origin scatter
of Eq. 7 on the virtual rig, with pairs centred on the effective origin (as after the
first iteration of the paper's origin search), against the sample std of the paper's
10 iterations.  Writes reports/benchmarks/closed_form_scatter.{json,md}.

    .venv/bin/python benchmarks/closed_form_scatter.py [--datasets 200]
"""

import argparse
import json
import time
from pathlib import Path

import numpy as np

from ambfit import rig
from ambfit.estimation import closed_form
from ambfit.rig import protocol

# The seed paper's Table 2 (10 iterations of experiment 2 of Table 1), µm.
PAPER_TABLE2 = {
    "g_v0": [784.44, 813.22, 746.59, 858.65, 759.45, 773.46, 738.01, 773.46, 747.11, 793.98],
    "g_w0": [765.42, 782.07, 732.63, 728.96, 695.12, 742.76, 709.65, 850.73, 743.12, 779.59],
    "v0": [31.92, 33.67, 30.47, 31.41, 31.58, 32.08, 31.46, 31.96, 31.56, 31.43],
    "w0": [-7.18, -11.06, -9.75, -11.40, -10.73, -9.92, -10.78, -11.78, -12.71, -11.91],
}


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--datasets", type=int, default=200)
    ap.add_argument("--out", type=Path, default=Path(__file__).resolve().parents[1] / "reports" / "benchmarks")
    args = ap.parse_args()
    spec = rig.PAPER_RIG
    center = spec.centre
    proto = protocol.paper_table2(iterations=10, center=center)
    per = {k: [] for k in PAPER_TABLE2}
    t0 = time.perf_counter()
    rejected = 0
    for seed in range(args.datasets):
        sim = rig.simulate(spec, proto, seed=seed)
        res = closed_form.identify(sim.data)
        for ax, gk, xk in (("v", "g_v0", "v0"), ("w", "g_w0", "w0")):
            est = res.estimates[("all", ax)]
            rejected += len(est.rejected)
            per[gk] += [s.g0 * 1e6 for s in est.iterations.values()]
            per[xk] += [s.x0 * 1e6 for s in est.iterations.values()]
    elapsed = time.perf_counter() - t0
    truth = {"g_v0": spec.g0[0] * 1e6, "g_w0": spec.g0[1] * 1e6, "v0": spec.x0[0] * 1e6, "w0": spec.x0[1] * 1e6}
    rows = []
    for k, paper in PAPER_TABLE2.items():
        sim_v = np.asarray(per[k])
        paper_std = float(np.std(paper, ddof=1))
        # 90 % interval of the std of 10 iterations if the rig's noise were the paper's (chi-square, 9 dof)
        from scipy.stats import chi2
        s = float(np.std(sim_v, ddof=1))
        lo, hi = s * np.sqrt(chi2.ppf([0.05, 0.95], 9) / 9)
        rows.append({"param": k, "truth_um": truth[k], "rig_mean_um": float(sim_v.mean()),
                     "rig_iteration_std_um": s, "paper_iteration_std_um": paper_std,
                     "ratio_paper_over_rig": paper_std / s, "rig_10_iteration_std_90pct": [float(lo), float(hi)],
                     "n_iterations": int(sim_v.size)})
    out = {"protocol": "paper Table 2: 1.4/1.6 A, ±20 µm centred on the effective origin, 10 iterations",
           "noise": {"current_mA": rig.Noise().current * 1e3, "position_um": rig.Noise().position * 1e6},
           "datasets": args.datasets, "rejected_iterations": rejected, "seconds": elapsed, "rows": rows}
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "closed_form_scatter.json").write_text(json.dumps(out, indent=2))
    md = ["# Closed-form scatter: virtual rig vs the paper's Table 2", "",
          f"{args.datasets} data sets x 10 iterations, default noise "
          f"({out['noise']['current_mA']:.2f} mA, {out['noise']['position_um']:.2f} µm), {elapsed:.1f} s; "
          f"{rejected} iterations rejected by the validity checks.", "",
          "| param | truth µm | rig mean µm | rig per-iteration std µm | paper per-iteration std µm | "
          "90 % range of a 10-iteration std on the rig |", "|---|---|---|---|---|---|"]
    for r in rows:
        lo, hi = r["rig_10_iteration_std_90pct"]
        md.append(f"| {r['param']} | {r['truth_um']:.2f} | {r['rig_mean_um']:.2f} | {r['rig_iteration_std_um']:.2f} | "
                  f"{r['paper_iteration_std_um']:.2f} | {lo:.2f} – {hi:.2f} |")
    (args.out / "closed_form_scatter.md").write_text("\n".join(md) + "\n")
    print("\n".join(md))


if __name__ == "__main__":
    main()
