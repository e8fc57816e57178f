"""The diagnosis on data as a new user would bring it: laws other than the library's, another protocol, no
thermometer, two effects at once.  A measuring instrument: it changes nothing in how the diagnosis decides.

Eight families, three data sets each (24 cases, issue 23), every one on the serpentine protocol
(:func:`ambfit.rig.protocol.serpentine`: a 5 x 3 grid of set-points walked as a serpentine, biases 1.0-1.6 A in
0.1 A steps in an order shuffled at every set-point, four known loads; 840 rows) with its own shuffle, true
air gaps within ±2 µm of the nominal 762 µm and random origins (±40 µm), and written without the
``temperature_C`` column (:func:`ambfit.rig.laws.as_recorded`):

| case | truth on the rig (:mod:`ambfit.rig.laws`) | right when |
|---|---|---|
| none | no effect | the verdict is ``none`` |
| drift_time | origin and gap drifting with ``time_s`` (linear, exponential, linear) | the verdict names ``thermal_drift`` |
| hysteresis_memory | a wide play felt in part: memory over several steps | the verdict names ``hysteresis`` |
| coupling_currents | the other axis' control current acting on this axis | the verdict names ``cross_coupling`` |
| saturation+current_offset | the library's saturation and current offset together | the verdict names both |
| position_sensor | position sensor gain error and quadratic curve | ``position_gain`` is named in the verdict or the confounded set (the library's position gain is absorbed by gap and origin: the diagnosis reports it as confounded) |
| current_offset | each current channel off in offset and gain | the verdict names ``current_offset`` |
| saturation_curve | saturation with a tanh curve | the verdict names ``saturation`` |

"Names" means: the family is one of the verdict's ``+``-joined names (a pair that includes the family counts
for a single-family case).  Per case the report gives the truth and its parameters, the verdict, the confounded
set, whether it is right, the held-out shrink and excess before, and the time of the diagnosis; then a table per
family and the total right out of 24.

    .venv/bin/python benchmarks/gap_hidden_like.py [--seeds 3] [--workers 2 | --scheduler ADDRESS]

Writes reports/gap/hidden_like.{json,md}.
"""

import argparse
import json
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]

CASES = {
    "none": ("none", [()]),
    "drift_time": ("thermal_drift", [("drift_time_linear",), ("drift_time_exponential",)]),
    "hysteresis_memory": ("hysteresis", [("hysteresis_minor_loops",)]),
    "coupling_currents": ("cross_coupling", [("cross_coupling_currents",)]),
    "saturation+current_offset": ("saturation+current_offset", [("saturation", "current_offset")]),
    "position_sensor": ("position_gain", [("position_nonlinear",)]),
    "current_offset": ("current_offset", [("current_offset_calibration",)]),
    "saturation_curve": ("saturation", [("saturation_tanh",)]),
}
"""Each case: the family (or ``+``-joined families) a right verdict names, and the laws of its data sets (the
k-th data set takes the k-th entry, cyclically)."""


def is_right(case: str, verdict: str, confounded_with) -> bool:
    """Whether a verdict is right for a case (the table of the module docstring)."""
    want = CASES[case][0]
    named = set(verdict.split("+"))
    if want == "none":
        return verdict == "none"
    if want == "position_gain":
        return "position_gain" in named or "position_gain" in set(confounded_with)
    return set(want.split("+")) <= named


def one_case(item: tuple, seed) -> dict:
    """Simulate the data set ``item = (case, index)`` from its own seed and diagnose it blind."""
    from ambfit import diagnosis as gap
    from ambfit import rig
    from ambfit.rig import laws, protocol

    case, k = item
    variants = CASES[case][1]
    names = variants[k % len(variants)]
    rng = np.random.default_rng(seed)
    while True:
        spec = rig.PAPER_RIG.with_truth(g0=rng.uniform(760e-6, 764e-6, 2), x0=rng.uniform(-40e-6, 40e-6, 2))
        proto = protocol.serpentine(seed=int(rng.integers(2**31)))
        effects = laws.draw(names, rng)
        try:
            data = laws.as_recorded(rig.simulate(spec, proto, effects, seed=rng).data)
            break
        except rig.RigError:
            continue
    t0 = time.perf_counter()
    rec = gap.diagnose(data).to_json()   # the bearing description defaults to the paper's
    seconds = time.perf_counter() - t0
    return {"case": case, "index": k, "laws": list(names), "want": CASES[case][0], "verdict": rec["verdict"],
            "confounded_with": rec["confounded_with"],
            "right": is_right(case, rec["verdict"], rec["confounded_with"]),
            "shrink": rec["shrink"], "excess_before": rec["heldout_excess_before"],
            "effect_params": [{"name": e.name, **e.describe()} for e in effects], "rows": len(data),
            "columns": list(data.columns), "seconds": seconds}


def _num(value, digits: int) -> str:
    return "-" if value is None else f"{value:.{digits}f}"


def main():
    ap = argparse.ArgumentParser(description="the diagnosis on hidden-like data (issue 23)")
    ap.add_argument("--seeds", type=int, default=3, help="data sets per case")
    ap.add_argument("--seed", type=int, default=2323, help="the study's seed (each data set gets its own from it)")
    ap.add_argument("--workers", type=int, default=None, help="local worker processes (default: this process)")
    ap.add_argument("--scheduler", default=None, help="address of a running Dask scheduler")
    ap.add_argument("--out", type=Path, default=ROOT / "reports" / "gap")
    args = ap.parse_args()
    from ambfit.engine import Engine

    items = [(case, k) for case in CASES for k in range(args.seeds)]
    with Engine(workers=args.workers, scheduler=args.scheduler) as engine:
        cases = engine.map(one_case, items, seed=args.seed, chunk_size=1, what="data sets")
    per = {c: {"right": sum(x["right"] for x in cases if x["case"] == c),
               "of": sum(x["case"] == c for x in cases)} for c in CASES}
    times = [c["seconds"] for c in cases]
    summary = {"right": sum(c["right"] for c in cases), "of": len(cases), "per_case": per,
               "seconds_median": float(np.median(times)), "seconds_max": float(np.max(times)),
               "seconds_first": times[0], "rows": cases[0]["rows"],
               "engine": {"workers": args.workers, "scheduler": args.scheduler, "seed": args.seed}}
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "hidden_like.json").write_text(json.dumps({"summary": summary, "cases": cases}, indent=2,
                                                          default=float))
    md = ["# The diagnosis on hidden-like data", "",
          f"{args.seeds} data sets per case ({summary['rows']} rows each: serpentine set-points, shuffled biases, "
          "four known loads, no `temperature_C` column; laws of `ambfit.rig.laws`, most unlike the library's); "
          "the diagnosis is not told the effect.  What counts as right is in the docstring of "
          "`benchmarks/gap_hidden_like.py`.", "",
          "| case | right when the verdict names | right | verdicts |", "|---|---|---|---|"]
    for c in CASES:
        verdicts = ", ".join(f"`{x['verdict']}`" for x in cases if x["case"] == c)
        md.append(f"| {c} | `{CASES[c][0]}` | {per[c]['right']}/{per[c]['of']} | {verdicts} |")
    md += [f"| **total** | | **{summary['right']}/{summary['of']}** | |", "",
           "| case | laws | verdict | confounded with | right | held-out shrink | excess before | seconds |",
           "|---|---|---|---|---|---|---|---|"]
    for x in cases:
        md.append(f"| {x['case']} #{x['index']} | {'+'.join(x['laws']) or '-'} | `{x['verdict']}` | "
                  f"{', '.join(x['confounded_with']) or '-'} | {'yes' if x['right'] else 'no'} | "
                  f"{_num(x['shrink'], 3)} | {_num(x['excess_before'], 2)} | {x['seconds']:.1f} |")
    md += ["", f"Time per diagnosis: median {summary['seconds_median']:.1f} s, largest {summary['seconds_max']:.1f} s "
           f"(the first in each worker includes compilation; JAX's persistent cache may already hold it).",
           "", f"Run on {'a Dask scheduler' if args.scheduler else f'{args.workers} local worker processes' if args.workers else 'one process'}"
           f" (`ambfit.engine.Engine`), study seed {args.seed}: each data set has its own seed, so the cases do not "
           "depend on where they ran."]
    (args.out / "hidden_like.md").write_text("\n".join(md) + "\n")
    print("\n".join(md))


if __name__ == "__main__":
    main()
