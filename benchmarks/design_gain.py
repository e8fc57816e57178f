"""Does following ambfit's design recommendation shrink the gap's uncertainty faster than the paper's protocol?

Both arms start from one iteration of the paper's perturbation at the back-up bearing
centre (1.4/1.6 A, ±20 µm, 4 steps).  Then, for R rounds of 4 steps each:
(a) the paper: the next iteration centred on the current estimate of the effective
origin; (b) ambfit: the 4 steps ``design.recommend`` picks (A-optimal for the v-axis gap)
from a grid of set-points within ±50 µm of the estimated origin and biases 0.8-1.8 A, kept among the
positions already run while an axis has fewer than three biases (the origin may then carry an effect the
data cannot show): its first rounds spend steps on biases, not on lever arm.
After each round both arms are refitted by least squares; the gap's 94 % interval
half-width (1.88 standard errors; the posterior is near-Gaussian here, see ls_efficiency)
is recorded.  Averaged over S seeds of the rig noise.

    .venv/bin/python benchmarks/design_gain.py [--seeds 10] [--rounds 9] [--workers 2 | --scheduler ADDRESS]

Each seed is one item of :class:`ambfit.engine.Engine` (in this process by default): the same numbers
wherever it runs.

Writes reports/benchmarks/design_gain.{json,md,png}.
"""

import argparse
import functools
import json
from pathlib import Path

import numpy as np

from ambfit import rig
from ambfit.engine import Engine
from ambfit.estimation import design, fit
from ambfit.rig import protocol

ROOT = Path(__file__).resolve().parents[1]


def run(seed, rounds):
    spec = rig.PAPER_RIG
    rng = np.random.default_rng(seed)
    first = rig.simulate(spec, protocol.paper_table2(iterations=1), seed=rng)
    arms = {"paper": (first.data, first.state), "ambfit": (first.data, first.state)}
    widths = {k: [] for k in arms}
    for r in range(rounds + 1):
        for name, (data, state) in list(arms.items()):
            res = fit.fit(data)
            widths[name].append(1.88 * res.error("g_v0") * 1e6)
            if r == rounds:
                continue
            centre = (-res.value("v0"), -res.value("w0"))
            if name == "paper":
                proto = protocol.perturbation((1.4, 1.6), (20e-6,), center=centre, iterations=1, first_iteration=r + 2,
                                              experiment="design")
            else:
                rec = design.recommend(data, n_steps=4, result=res)
                pts = [(s.v_set_um * 1e-6, s.w_set_um * 1e-6) for s in rec.steps.itertuples()]
                parts = [protocol.grid([p], [s.bias_A], iteration=r + 2, experiment="design")
                         for p, s in zip(pts, rec.steps.itertuples())]
                proto = protocol.concat(*parts)
            sim = rig.simulate(spec, proto, seed=rng, state=state)
            import pandas as pd
            arms[name] = (pd.concat([data, sim.data], ignore_index=True), sim.state)
    return widths


def main():
    ap = argparse.ArgumentParser(description="design recommendation vs the paper's protocol")
    ap.add_argument("--seeds", type=int, default=10)
    ap.add_argument("--rounds", type=int, default=9)
    ap.add_argument("--out", type=Path, default=ROOT / "reports" / "benchmarks")
    ap.add_argument("--workers", type=int, default=None, help="local worker processes (default: this process)")
    ap.add_argument("--scheduler", default=None, help="address of a running Dask scheduler")
    args = ap.parse_args()
    with Engine(workers=args.workers, scheduler=args.scheduler) as engine:
        runs = engine.map(functools.partial(run, rounds=args.rounds), range(args.seeds), chunk_size=1,
                          what="seeds")
    out = {k: np.mean([r[k] for r in runs], axis=0).tolist() for k in ("paper", "ambfit")}
    out["steps"] = [4 * (i + 1) for i in range(args.rounds + 1)]
    out["seeds"] = args.seeds
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "design_gain.json").write_text(json.dumps(out, indent=2))
    md = ["# Gap interval: ambfit's recommended perturbations vs the paper's protocol", "",
          f"Mean over {args.seeds} rig noise seeds of the v-axis gap's 94 % interval half-width [µm] (least "
          "squares, 1.88 standard errors) after each round of 4 steps (8 readings).", "",
          "| steps run | paper protocol | ambfit design | ratio |", "|---|---|---|---|"]
    for s, a, b in zip(out["steps"], out["paper"], out["ambfit"]):
        md.append(f"| {s} | {a:.2f} | {b:.2f} | {a / b:.2f} |")
    (args.out / "design_gain.md").write_text("\n".join(md) + "\n")
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 4))
    ax.plot(out["steps"], out["paper"], "o-", label="paper protocol (±20 µm, 1.4/1.6 A, re-centred)")
    ax.plot(out["steps"], out["ambfit"], "s-", label="ambfit design (A-optimal for g_v0)")
    ax.set_xlabel("steps run (2 readings each)")
    ax.set_ylabel("94 % interval half-width of g_v0 [µm]")
    ax.set_yscale("log")
    ax.legend()
    fig.tight_layout()
    fig.savefig(args.out / "design_gain.png", dpi=120)
    print("\n".join(md))


if __name__ == "__main__":
    main()
