"""Second-order bias of the least-squares estimator and its bootstrap correction.

The paper's Table 2 design centred on the effective origin (1.4/1.6 A, ±20 µm, 10
iterations, one known load).  Part 1: the plain estimator on N_raw data sets at
0.6 mA and at 1.8 mA (bias in standard deviations and in standard errors of the
mean).  Part 2: the same and the bootstrap-corrected estimator
(``fit(debias=1000)``) on N_debiased data sets at 0.6 mA.

    .venv/bin/python benchmarks/ls_bias.py [--raw 3000] [--debiased 1000]

Writes reports/benchmarks/ls_bias.{json,md}.
"""

import argparse
import json
import time
from pathlib import Path

import numpy as np

from ambfit import rig
from ambfit.estimation import core, fit
from ambfit.estimation.results import table
from ambfit.rig import protocol

ROOT = Path(__file__).resolve().parents[1]


def _row(c, t):
    sd = float(np.std(c, ddof=1))
    return {"bias_sd": float((np.mean(c) - t) / sd), "bias_se": float((np.mean(c) - t) / (sd / np.sqrt(len(c)))),
            "std": sd}


def main():
    ap = argparse.ArgumentParser(description="LS bias and its bootstrap correction")
    ap.add_argument("--raw", type=int, default=3000)
    ap.add_argument("--debiased", type=int, default=1000)
    ap.add_argument("--out", type=Path, default=ROOT / "reports" / "benchmarks")
    args = ap.parse_args()
    spec = rig.PAPER_RIG
    proto = protocol.paper_table2(center=(-spec.x0[0], -spec.x0[1]))
    truth = dict(zip(core.HEAD_NAMES, [spec.g0[0], spec.g0[1], spec.x0[0], spec.x0[1], spec.force_constant,
                                      spec.force_constant]))
    out = {"design": "paper Table 2, centred, 1 known load", "raw": {}, "debiased": {}}
    for current in (0.6e-3, 1.8e-3):
        noise = rig.Noise(current, 0.1e-6)
        data = [rig.simulate(spec, proto, noise=noise, seed=200_000 + s).data for s in range(args.raw)]
        b = table(fit.fit_many(data, name_outliers=False))
        out["raw"][f"{current * 1e3:.1f} mA"] = {p: _row(b[p].to_numpy(), t) for p, t in truth.items()}
    t0 = time.perf_counter()
    plain, corrected = [], []
    for s in range(args.debiased):
        d = rig.simulate(spec, proto, seed=300_000 + s).data
        r = fit.fit(d, debias=1000, seed=s)
        corrected.append(r.values[:6])
        plain.append([r.values[j] + r.bias_correction[n]["subtracted"] for j, n in enumerate(r.names[:6])])
    plain, corrected = np.array(plain), np.array(corrected)
    out["debiased"] = {"datasets": args.debiased, "bootstrap_sets": 1000, "seconds": time.perf_counter() - t0,
                       "plain": {p: _row(plain[:, j], t) for j, (p, t) in enumerate(truth.items())},
                       "corrected": {p: _row(corrected[:, j], t) for j, (p, t) in enumerate(truth.items())}}
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "ls_bias.json").write_text(json.dumps(out, indent=2))
    md = ["# Least-squares bias and its bootstrap correction (Table 2 design, centred)", "",
          f"Plain estimator, {args.raw} data sets per noise level: (mean - truth) in standard deviations "
          "[standard errors of the mean].", "", "| param | " + " | ".join(out["raw"]) + " |",
          "|---|" + "---|" * len(out["raw"])]
    for p in truth:
        md.append(f"| {p} | " + " | ".join(f"{v[p]['bias_sd']:+.3f} [{v[p]['bias_se']:+.1f}]"
                                           for v in out["raw"].values()) + " |")
    dd = out["debiased"]
    md += ["", f"Plain vs bootstrap-corrected (`fit(debias=1000)`), {args.debiased} data sets at 0.6 mA "
           f"({dd['seconds']:.0f} s):", "", "| param | plain | corrected | std plain | std corrected |",
           "|---|---|---|---|---|"]
    for p in truth:
        a, c = dd["plain"][p], dd["corrected"][p]
        md.append(f"| {p} | {a['bias_sd']:+.3f} [{a['bias_se']:+.1f}] | {c['bias_sd']:+.3f} [{c['bias_se']:+.1f}] | "
                  f"{a['std']:.3e} | {c['std']:.3e} |")
    (args.out / "ls_bias.md").write_text("\n".join(md) + "\n")
    print("\n".join(md))


if __name__ == "__main__":
    main()
