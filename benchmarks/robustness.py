"""Outliers: the gap's error with the outlier test / robust losses against plain least squares.

Design: the paper's Table 2 protocol on the virtual rig (80 readings, 0.6 mA, 0.1 µm).  In each data set a
fraction of the readings (1-5 %) is damaged the way files get damaged: a position typed as 0, a position
off by 10-40 µm, or a current off by 20-100 mA (30-170 σ).  Reported per fraction, over N data sets: the RMS
error of g_v0 and g_w0 against the truth for plain least squares (``loss="linear"``), the default outlier
test (``auto``) and the Huber and Cauchy losses, as a multiple of the clean-data RMS error; how many
damaged readings the test found and how many clean ones it wrongly left out.  On clean data: the
false-alarm rate of the test (data sets with at least one reading left out; target <= 1 %).

    .venv/bin/python benchmarks/robustness.py [--n 100] [--clean 400]

Writes reports/benchmarks/robustness.{json,md}.
"""

import argparse
import json
import time
from pathlib import Path

import numpy as np

from ambfit import rig
from ambfit.estimation import fit
from ambfit.rig import protocol

ROOT = Path(__file__).resolve().parents[1]
FRACTIONS = (0.01, 0.025, 0.05)
LOSSES = ("linear", "auto", "huber", "cauchy")


def damage(frame, fraction, rng):
    """A copy with ``round(fraction * n)`` (at least one) readings damaged; returns it and the damaged rows."""
    d = frame.copy()
    n = max(1, int(round(fraction * len(d))))
    rows = rng.choice(len(d), size=n, replace=False)
    for r in rows:
        own = f"{d.loc[r, 'axis']}_um"
        kind = rng.integers(3)
        if kind == 0:
            d.loc[r, own] = 0.0
        elif kind == 1:
            d.loc[r, own] += rng.choice([-1, 1]) * rng.uniform(10.0, 40.0)
        else:
            col = rng.choice(["i_top_A", "i_bottom_A"])
            d.loc[r, col] += rng.choice([-1, 1]) * rng.uniform(0.02, 0.1)
    return d, set(int(r) + 1 for r in rows)


def main():
    ap = argparse.ArgumentParser(description="robust least squares against outliers")
    ap.add_argument("--n", type=int, default=100, help="data sets per outlier fraction")
    ap.add_argument("--clean", type=int, default=400, help="clean data sets for the false-alarm rate")
    ap.add_argument("--out", type=Path, default=ROOT / "reports" / "benchmarks")
    args = ap.parse_args()
    spec = rig.PAPER_RIG
    proto = protocol.paper_table2(center=spec.centre)
    truth = np.array([spec.g0[0], spec.g0[1]])
    t0 = time.perf_counter()

    def gaps(res):
        return np.array([res.value("g_v0"), res.value("g_w0")])

    clean_err, alarms = [], 0
    for s in range(args.clean):
        res = fit.fit(rig.simulate(spec, proto, seed=500_000 + s).data, throw=False)
        alarms += bool(res.outliers)
        if s < args.n:
            clean_err.append(gaps(res) - truth)
    clean_rms = np.sqrt(np.mean(np.square(clean_err), axis=0))
    out = {"design": "paper Table 2, centred, 80 readings, 0.6 mA, 0.1 µm", "clean_datasets": args.clean,
           "false_alarm_rate": alarms / args.clean, "clean_rms_um": (clean_rms * 1e6).tolist(), "fractions": {}}
    rng = np.random.default_rng(7)
    for frac in FRACTIONS:
        err = {loss: [] for loss in LOSSES}
        found = wrong = planted = failed = 0
        for s in range(args.n):
            d, bad = damage(rig.simulate(spec, proto, seed=500_000 + s).data, frac, rng)
            planted += len(bad)
            for loss in LOSSES:
                try:
                    res = fit.fit(d, loss=loss, throw=False)
                except fit.FitError:
                    failed += 1
                    continue
                err[loss].append(gaps(res) - truth)
                if loss == "auto":
                    rows = {o.row for o in res.outliers}
                    found += len(rows & bad)
                    wrong += len(rows - bad)
        out["fractions"][f"{100 * frac:g} %"] = {
            "damaged_per_set": max(1, int(round(frac * 80))),
            "rms_over_clean": {loss: (np.sqrt(np.mean(np.square(e), axis=0)) / clean_rms).tolist()
                               for loss, e in err.items()},
            "found": found / planted, "clean_readings_left_out_per_set": wrong / args.n, "failed_fits": failed}
    out["seconds"] = time.perf_counter() - t0
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "robustness.json").write_text(json.dumps(out, indent=2))
    md = ["# Outliers: gap error with the outlier test and robust losses vs plain least squares", "",
          f"Table 2 protocol on the virtual rig, {args.n} data sets per fraction; damaged readings: a position "
          "typed as 0, a position off by 10-40 µm, or a current off by 20-100 mA.  Entries: RMS error of "
          "g_v0 / g_w0 against the truth as a multiple of the clean-data RMS error "
          f"({out['clean_rms_um'][0]:.2f} / {out['clean_rms_um'][1]:.2f} µm); target for the default: <= 1.2.",
          "", "| outliers | " + " | ".join(LOSSES) + " | damaged readings found (auto) | clean readings left out "
          "per set |", "|---|" + "---|" * (len(LOSSES) + 2)]
    for key, f in out["fractions"].items():
        cells = " | ".join(f"{v[0]:.2f} / {v[1]:.2f}" for v in f["rms_over_clean"].values())
        md.append(f"| {key} ({f['damaged_per_set']} of 80) | {cells} | {100 * f['found']:.0f} % | "
                  f"{f['clean_readings_left_out_per_set']:.2f} |")
    md += ["", f"False alarms on clean data (a data set with any reading left out): "
           f"{100 * out['false_alarm_rate']:.2f} % of {args.clean} (target <= 1 %).",
           "", f"Run time {out['seconds']:.0f} s."]
    (args.out / "robustness.md").write_text("\n".join(md) + "\n")
    print("\n".join(md))


if __name__ == "__main__":
    main()
