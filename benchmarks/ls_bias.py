"""Bias and spread of the least-squares estimate on the paper's protocols: plain and with the default
second-order correction (``fit(debias="second-order")``), against the Cramér-Rao bound.

For each protocol, N data sets of the paper rig (gap 775/760 µm, origin 33.3/-11.3 µm) with its noise (0.6 mA,
0.1 µm), fitted together twice (``debias="none"`` and the default).  Per parameter: (mean - truth) in standard
deviations and in standard errors of the mean, and the spread against sqrt(CRLB) of the design at the truth
(:func:`ambfit.estimation.information.design_information`).  Targets (the issue's): |bias| <= 1.5 standard
errors and sd <= 1.05 x the bound with N >= 500 per protocol.  Two more: the centred Table 2 at three times the
current noise, where the plain bias is three times larger, and fitted with the current channels' zeros free
(``current_offset``; the rig has none), where the bound is the ideal law's and the origins' plain bias is larger
than their scatter.  The correction's cost is timed on one
warm fit of 936 readings (median of 60, plain and corrected alternating), in this run; ``--cost-only`` times it
again and keeps the studies of the last run's record.

    .venv/bin/python benchmarks/ls_bias.py [--sets 1000] [--cost-only]

Writes reports/benchmarks/ls_bias.{json,md}.
"""

import argparse
import json
import os
import time
from pathlib import Path

import numpy as np

from ambfit import rig
from ambfit.estimation import core, fit, information
from ambfit.estimation.debias import second_order_biases
from ambfit.physics.effects import CurrentOffset
from ambfit.rig import protocol as P

ROOT = Path(__file__).resolve().parents[1]
TARGETS = {"bias_se_max": 1.5, "sd_over_bound_max": 1.05, "sets_min": 500, "corrected_over_plain_max": 2.0}


def protocols(spec):
    centre = spec.centre
    first = P.perturbation((1.4, 1.6), (20e-6,), iterations=1, experiment="table2")
    rest = P.perturbation((1.4, 1.6), (20e-6,), center=centre, iterations=9, first_iteration=2, experiment="table2")
    return {
        "Table 2, centred on the origin": (P.paper_table2(center=centre), rig.Noise()),
        "Table 2 at the back-up bearing centre": (P.paper_table2(), rig.Noise()),
        "origin search (1 + 9 iterations)": (P.concat(first, rest), rig.Noise()),
        "Table 1 (three bias pairs), centred": (P.paper_table1(center=centre), rig.Noise()),
        "Table 4 (1.0-1.4 A, ±30-50 µm), centred": (P.paper_table4(center=centre, origin_shift=(0.0, 0.0)),
                                                    rig.Noise()),
        "Table 2, centred, 1.8 mA": (P.paper_table2(center=centre), rig.Noise(1.8e-3, 0.1e-6)),
        "Table 2, centred, fitted with current_offset": (P.paper_table2(center=centre), rig.Noise(), (CurrentOffset(),)),
    }


def _stats(values, truth, bound):
    sd = values.std(axis=0, ddof=1)
    bias = values.mean(axis=0) - truth
    return {"bias_sd": bias / sd, "bias_se": bias / (sd / np.sqrt(len(values))), "sd_over_bound": sd / bound}


def study(spec, proto, noise, sets, seed, effects=()):
    names = list(core.HEAD_NAMES)
    truth = np.array([spec.g0[0], spec.g0[1], spec.x0[0], spec.x0[1], spec.force_constant, spec.force_constant])
    info = information.design_information(spec, proto, noise)
    bound = np.array([info.std(n) for n in names])
    data = [rig.simulate(spec, proto, noise=noise, seed=seed + s).data for s in range(sets)]
    out = {"rows": len(data[0]), "sets": sets, "noise_mA": noise.current * 1e3, "bound": dict(zip(names, bound)),
           "effects": [type(e).name for e in effects]}
    for mode in ("none", "second-order"):
        results = fit.fit_many(data, effects, name_outliers=False, debias=mode)
        ok = [r for r in results if not isinstance(r, BaseException) and r.converged and r.names[:6] == names]
        values = np.array([r.values[:6] for r in ok])
        s = _stats(values, truth, bound)
        out[mode] = {"converged": len(ok), **{n: {k: float(v[j]) for k, v in s.items()} for j, n in enumerate(names)}}
    return out


def sources(spec, proto, noise):
    """The expansion's bias at the truth (noise-free readings of the design, the noise declared) from the current
    noise alone, the position noise alone and both (the fit's weights always from both), in standard deviations
    of the estimate: where the bias comes from."""
    import jax

    clean = rig.simulate(spec, proto, noise=rig.NOISE_FREE).data
    res = fit.fit(clean, sigma_i=noise.current, sigma_x=noise.position, debias="none")
    prob, meta = core.build_problem(clean, sigma_i=noise.current, sigma_x=noise.position)
    free = core.free_mask(prob, meta)
    scale = core.si_scale(prob)[0][free]
    cov = np.zeros((len(free), len(free)))
    cov[np.ix_(free, free)] = res.cov / np.outer(scale, scale)
    one = jax.tree.map(lambda a: np.asarray(a)[None], prob)
    out = {}
    for label, share in {"currents": (1, 1, 0), "positions": (0, 0, 1), "both": (1, 1, 1)}.items():
        bias = second_order_biases(res.theta[None], one, core.IDEAL, free[None], cov[None], share)[0]
        out[label] = {n: float(b * sc / s) for n, b, sc, s in zip(res.names, bias[free], scale, res.std)}
    return out


def correction_cost(spec, repeats=60):
    """Median warm time of one fit of 936 readings, plain and corrected (the same data set), the two alternating so
    that a machine whose speed drifts slows both alike."""
    d = rig.simulate(spec, P.paper_table2(iterations=117, center=spec.centre), seed=7).data
    modes = ("none", "second-order")
    times = {mode: [] for mode in modes}
    for mode in modes:
        fit.fit(d, debias=mode)
    for _ in range(repeats):
        for mode in modes:
            t0 = time.perf_counter()
            fit.fit(d, debias=mode)
            times[mode].append(time.perf_counter() - t0)
    plain, corrected = (float(np.median(times[mode])) for mode in modes)
    return {"readings": len(d), "repeats": repeats, "plain_s": plain, "corrected_s": corrected,
            "ratio": corrected / plain, "load_at_start": os.getloadavg()[0]}


def _table(title: str, rows: dict) -> list[str]:
    """A Markdown table of one row of cells per protocol, under ``title``."""
    names = list(core.HEAD_NAMES)
    return ([title, "", "| protocol | " + " | ".join(names) + " |", "|---|" + "---|" * len(names)]
            + [f"| {name} | " + " | ".join(cells) + " |" for name, cells in rows.items()] + [""])


def render(out: dict, sets: int) -> list[str]:
    """The Markdown report of a run's record (``ls_bias.json``), as lines."""
    names = list(core.HEAD_NAMES)
    md = ["# Least-squares bias on the paper's protocols, plain and second-order corrected", "",
          f"{sets} data sets per protocol (paper rig, noise 0.6 mA and 0.1 µm unless named); each cell: "
          "bias in standard errors of the mean [in standard deviations], and sd / sqrt(CRLB). Targets: |bias| ≤ "
          f"{TARGETS['bias_se_max']} se, sd ≤ {TARGETS['sd_over_bound_max']}x the bound. Load average at start "
          f"{out['load_at_start']:.2f} (2 cores); {out['seconds']:.0f} s in all.", ""]
    for name, r in out["protocols"].items():
        md += [f"## {name} ({r['rows']} readings, {r['noise_mA']:.1f} mA)", "",
               "| param | plain bias | corrected bias | sd / bound (corrected) | meets |", "|---|---|---|---|---|"]
        for n in names:
            a, c = r["none"][n], r["second-order"][n]
            meets = abs(c["bias_se"]) <= TARGETS["bias_se_max"] and (
                r["effects"] or c["sd_over_bound"] <= TARGETS["sd_over_bound_max"])
            md.append(f"| {n} | {a['bias_se']:+.1f} [{a['bias_sd']:+.3f}] | {c['bias_se']:+.1f} [{c['bias_sd']:+.3f}] "
                      f"| {c['sd_over_bound']:.3f} | {'yes' if meets else 'no'} |")
        md.append("")
    md += _table("Where the bias comes from: the expansion at the truth (noise-free readings, the noise declared), "
                 "in standard deviations, from the current noise alone / the position noise alone / both:",
                 {name: [f"{src['currents'][n]:+.3f} / {src['positions'][n]:+.3f} / {src['both'][n]:+.3f}"
                         for n in names] for name, src in out["sources"].items()})
    if out["rechecked"]:
        md += _table(f"Protocols with a corrected bias beyond {TARGETS['bias_se_max']} se, again on {4 * sets} fresh "
                     "sets (corrected bias in se [sd]; about five of the 36 cells above cross 1.5 se by chance):",
                     {name: [f"{r['second-order'][n]['bias_se']:+.1f} [{r['second-order'][n]['bias_sd']:+.3f}]"
                             for n in names] for name, r in out["rechecked"].items()})
    md += ["(With current_offset the bound is the ideal law's: the offsets' priors widen the estimate beyond it, "
           "so there the sd column is no target and 'meets' is the bias alone.)", ""]
    c = out["cost"]
    md += [f"One warm fit of {c['readings']} readings (median of {c.get('repeats', 30)}, plain and corrected "
           f"alternating; load {c.get('load_at_start', out['load_at_start']):.2f}): plain {c['plain_s'] * 1e3:.2f} ms, "
           f"corrected {c['corrected_s'] * 1e3:.2f} ms ({c['ratio']:.2f}x; target: the correction costs no more "
           f"than the fit, at most {TARGETS['corrected_over_plain_max']:g}x).", "",
           "Rerun: `.venv/bin/python benchmarks/ls_bias.py`."]
    return md


def main():
    ap = argparse.ArgumentParser(description="LS bias with and without the second-order correction")
    ap.add_argument("--sets", type=int, default=1000)
    ap.add_argument("--out", type=Path, default=ROOT / "reports" / "benchmarks")
    ap.add_argument("--cost-only", action="store_true",
                    help="measure the correction's cost again and keep the studies of the last run's ls_bias.json")
    args = ap.parse_args()
    spec = rig.PAPER_RIG
    if args.cost_only:
        out = json.loads((args.out / "ls_bias.json").read_text())
        out["cost"] = correction_cost(spec)
        (args.out / "ls_bias.json").write_text(json.dumps(out, indent=2))
        md = render(out, next(iter(out["protocols"].values()))["sets"])
        (args.out / "ls_bias.md").write_text("\n".join(md) + "\n")
        print("\n".join(md[-3:]))
        return
    load = os.getloadavg()[0]
    t0 = time.perf_counter()
    out = {"targets": TARGETS, "load_at_start": load, "protocols": {}}
    cases = protocols(spec)
    for k, (name, (proto, noise, *effects)) in enumerate(cases.items()):
        out["protocols"][name] = study(spec, proto, noise, args.sets, seed=500_000 + 10_000 * k,
                                       effects=effects[0] if effects else ())
    out["sources"] = {name: sources(spec, proto, noise) for name, (proto, noise, *effects) in cases.items()
                      if not effects}
    # 36 cells at 1.5 standard errors: about five would cross it by chance alone.  A protocol of the ideal law with
    # a corrected bias beyond it is run again on four times the sets with fresh seeds.
    out["rechecked"] = {}
    for k, (name, (proto, noise, *effects)) in enumerate(cases.items()):
        r = out["protocols"][name]
        if not effects and any(abs(r["second-order"][n]["bias_se"]) > TARGETS["bias_se_max"] for n in core.HEAD_NAMES):
            out["rechecked"][name] = study(spec, proto, noise, 4 * args.sets, seed=2_000_000 + 100_000 * k)
    out["cost"] = correction_cost(spec)
    out["seconds"] = time.perf_counter() - t0
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "ls_bias.json").write_text(json.dumps(out, indent=2))
    md = render(out, args.sets)
    (args.out / "ls_bias.md").write_text("\n".join(md) + "\n")
    print("\n".join(md))


if __name__ == "__main__":
    main()
