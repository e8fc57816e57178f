"""Coverage of the closed form's (Eq. 5-7) interval on the paper's Table 2 protocol, and how often a wrong answer
is flagged.

Many data sets of the paper's Table 2 protocol (1.4/1.6 A, ±20 µm centred on the effective origin, 10
iterations) on the virtual rig at the default noise (1x: 0.6 mA, 0.1 µm) and at 3x.  For each axis' gap and
origin: how often the truth lies in mean ± 1.96 sem (the normal quantile) and in mean ± t(0.975, n - 1) sem (what
``ambfit identify --method closed-form`` reports), the mean error in µm and in standard errors (the
errors-in-variables bias), how often the result fails the ``agrees_with_least_squares`` check, how often it is
trusted (exit 0), and how often an interval misses the truth while the result is trusted: a silently wrong answer.
Writes reports/benchmarks/closed_form_coverage.{json,md}.

    .venv/bin/python benchmarks/closed_form_coverage.py [--datasets 300] [--scales 1,3]
"""

import argparse
import json
import time
from pathlib import Path

import numpy as np

from ambfit import rig
from ambfit.estimation import closed_form
from ambfit.estimation.fit import fit_many
from ambfit.rig import protocol


def run(scale: float, datasets: int) -> dict:
    spec = rig.PAPER_RIG
    proto = protocol.paper_table2(iterations=10, center=spec.centre)
    base = rig.Noise()
    noise = rig.Noise(base.current * scale, base.position * scale)
    truth = {("v", "g0"): spec.g0[0], ("v", "x0"): spec.x0[0], ("w", "g0"): spec.g0[1], ("w", "x0"): spec.x0[1]}
    rows = []
    failed = 0
    for seed in range(datasets):
        sim = rig.simulate(spec, proto, noise=noise, seed=seed)
        try:
            res = closed_form.identify(sim.data, reference=lambda rows: fit_many([rows])[0])
        except closed_form.ClosedFormError:
            failed += 1
            continue
        for ax in ("v", "w"):
            est = res.estimates[("all", ax)]
            flagged = next(ok for name, ok, _ in est.checks() if name == "agrees_with_least_squares") is False
            for name in ("g0", "x0"):
                value, sem = getattr(est, name), getattr(est, f"{name}_sem")
                lo, hi = est.interval(name)
                err = value - truth[(ax, name)]
                rows.append({"axis": ax, "param": name, "err": err, "pull": err / sem,
                             "in_normal": abs(err) <= 1.959964 * sem, "in_t": lo <= truth[(ax, name)] <= hi,
                             "flagged": flagged, "trusted": res.trusted, "rejected": len(est.rejected)})
    out = {"noise_scale": scale, "current_mA": noise.current * 1e3, "position_um": noise.position * 1e6,
           "datasets": datasets, "unsolvable": failed, "params": {}}
    for key in ("g0", "x0"):
        sel = [r for r in rows if r["param"] == key]
        arr = {k: np.array([r[k] for r in sel]) for k in sel[0]}
        trusted = arr["trusted"]
        out["params"][key] = {
            "n": len(sel), "coverage_normal_1.96": float(arr["in_normal"].mean()),
            "coverage_t": float(arr["in_t"].mean()),
            "coverage_t_when_trusted": float(arr["in_t"][trusted].mean()) if trusted.any() else None,
            "mean_error_um": float(arr["err"].mean() * 1e6),
            "mean_error_mc_error_um": float(arr["err"].std(ddof=1) / np.sqrt(len(sel)) * 1e6),
            "median_pull": float(np.median(arr["pull"])), "pull_sd": float(arr["pull"].std(ddof=1)),
            "beyond_3_sem": float((np.abs(arr["pull"]) > 3).mean()),
            "beyond_3_sem_flagged": float(arr["flagged"][np.abs(arr["pull"]) > 3].mean())
            if (np.abs(arr["pull"]) > 3).any() else None,
            "flagged_vs_least_squares": float(arr["flagged"].mean()),
            "trusted": float(trusted.mean()),
            "silently_wrong": float((~arr["in_t"] & trusted).mean()),
        }
    return out


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--datasets", type=int, default=300)
    ap.add_argument("--scales", default="1,3", help="noise multiples of the default rig noise, comma separated")
    ap.add_argument("--out", type=Path, default=Path(__file__).resolve().parents[1] / "reports" / "benchmarks")
    args = ap.parse_args()
    t0 = time.perf_counter()
    studies = [run(float(s), args.datasets) for s in args.scales.split(",")]
    elapsed = time.perf_counter() - t0
    out = {"protocol": "paper Table 2: 1.4/1.6 A, ±20 µm centred on the effective origin, 10 iterations",
           "interval": "mean ± t(0.975, n - 1) x standard error of the mean over iterations",
           "flag": f"agrees_with_least_squares fails (alpha {closed_form.agreement.AGREEMENT_ALPHA} per axis)",
           "seconds": elapsed, "studies": studies}
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "closed_form_coverage.json").write_text(json.dumps(out, indent=2))
    md = ["# Closed form (Eq. 5-7): interval coverage and flagged answers", "",
          f"{out['protocol']}; {args.datasets} data sets per noise level, both axes ({elapsed:.0f} s).  Nominal "
          "coverage 95 %.  *silently wrong*: the t interval misses the truth and the result is trusted "
          "(`ambfit identify --method closed-form` exits 0).", "",
          "| noise | param | coverage ±1.96 sem | coverage ±t sem | mean error µm | median pull | pull sd | "
          "beyond 3 sem | of those flagged | flagged | trusted | silently wrong |",
          "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for s in studies:
        for key, p in s["params"].items():
            b3f = "–" if p["beyond_3_sem_flagged"] is None else f"{100 * p['beyond_3_sem_flagged']:.0f} %"
            md.append(f"| {s['noise_scale']:g}x ({s['current_mA']:.1f} mA) | {key} | "
                      f"{100 * p['coverage_normal_1.96']:.1f} % | {100 * p['coverage_t']:.1f} % | "
                      f"{p['mean_error_um']:+.2f} ± {p['mean_error_mc_error_um']:.2f} | {p['median_pull']:+.2f} | "
                      f"{p['pull_sd']:.2f} | {100 * p['beyond_3_sem']:.1f} % | {b3f} | "
                      f"{100 * p['flagged_vs_least_squares']:.1f} % | {100 * p['trusted']:.0f} % | "
                      f"{100 * p['silently_wrong']:.1f} % |")
    (args.out / "closed_form_coverage.md").write_text("\n".join(md) + "\n")
    print("\n".join(md))


if __name__ == "__main__":
    main()
