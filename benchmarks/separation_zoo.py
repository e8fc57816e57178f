"""Does the experiment ``separate_by`` recommends separate the candidates?  Run on the law zoo (issue 31, item 3).
A measuring instrument: it changes nothing in how the diagnosis decides.

Each draw of :func:`ambfit.rig.zoo.draw` (the same cases as ``benchmarks/gap_zoo.py``: each draw's seed depends on
its index only) is diagnosed blind.  Where the verdict is ``undecided``, the rig that made the data (the same laws,
gaps, origins, heating and recorded columns) runs the protocol the diagnosis recommends
(:attr:`ambfit.diagnosis.separation.Separation.design`), and the new readings alone are diagnosed blind again; then
the rig runs the first protocol and the recommended one after it (one run, the first readings drawn anew), and
those readings are diagnosed together.  Each follow-up's verdict is scored against the truth as ``gap_zoo`` scores
verdicts, apart for the draws whose recommendation says it separates the candidates (its expected log Bayes factor
clears ``Rules.separate_log_bayes``) and those whose does not.  The recommendation is judged on laws unlike the
library's: it is computed from the candidates' library laws as fitted, which stand in for their widened forms.

    .venv/bin/python benchmarks/separation_zoo.py [--draws 300] [--seed 3131] [--workers 2] [--out reports/gap]

Writes separation.json and separation.md to ``--out``.
"""

import argparse
import dataclasses
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from gap_zoo import CATEGORIES, fractions, score  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]


def one_draw(item: int, seed) -> dict:
    """Draw case ``item`` from its own seed and diagnose it; when undecided, run the recommended protocol on its rig
    and diagnose the new readings, alone and after the first protocol's."""
    import jax

    import ambfit
    from ambfit.rig import protocol as protocols
    from ambfit.rig import zoo

    rng = np.random.default_rng(seed)
    case, data = zoo.draw(rng)
    out = {"index": item, "kind": case.kind, "truth": case.label, "laws": [law.name for law in case.laws],
           "protocol": case.protocol_kind, "rows": len(data)}
    try:
        first = ambfit.diagnose(data, check_force=False, discrepancy=False)
    except ambfit.FitError as exc:
        jax.clear_caches()
        return out | {"verdict": "error", "error": str(exc).splitlines()[0]}
    sep = first.separation
    out |= {"verdict": first.verdict, "candidates": list(first.decision.candidates),
            "category": score(case.truth, first.verdict, first.decision.candidates)}
    if first.decision.kind != "undecided" or sep is None or sep.design is None:
        jax.clear_caches()
        return out
    out |= {"recommended": sep.protocol, "expected_log_bayes": sep.expected_log_bayes, "separates": sep.separates,
            "on_these_data": sep.on_these_data, "follow_up_steps": len(sep.design)}
    out |= _diagnosed(case, sep.design, rng, "follow_up")
    if "follow_up_category" not in out:
        return out
    # the first protocol and the recommended one run one after the other on the rig, and diagnosed together: its
    # experiments named apart from the first protocol's, a load by the first's name when it is the same load
    design, first_loads = sep.design, case.protocol.loads
    renamed = {k: k if first_loads.get(k, v) == v else f"follow-up {k}" for k, v in design.loads.items()}
    later = dataclasses.replace(design, experiment=np.array([f"follow-up {e}" for e in design.experiment]),
                                load_id=np.array([renamed[k] for k in design.load_id]),
                                loads={renamed[k]: v for k, v in design.loads.items()})
    # (a noise of its own: what the follow-up drew does not move it)
    return out | _diagnosed(case, protocols.concat(case.protocol, later), np.random.default_rng(seed.spawn(1)[0]),
                            "joined")


def _diagnosed(case, proto, rng, key: str) -> dict:
    """``case``'s rig running ``proto``, its readings diagnosed blind: the verdict as ``key``, with its candidates,
    rows and category, or why it did not run (``key`` ``rig_error`` or ``error``, the message as ``{key}_error``)."""
    import jax

    import ambfit
    from ambfit.rig import zoo
    from ambfit.rig.virtual import RigError

    try:
        data = zoo.simulate_case(dataclasses.replace(case, protocol=proto), rng)
        dg = ambfit.diagnose(data, check_force=False, discrepancy=False)
    except RigError as exc:
        return {key: "rig_error", f"{key}_error": str(exc).splitlines()[0]}
    except ambfit.FitError as exc:
        return {key: "error", f"{key}_error": str(exc).splitlines()[0]}
    finally:
        jax.clear_caches()
    return {key: dg.verdict, f"{key}_candidates": list(dg.decision.candidates), f"{key}_rows": len(data),
            f"{key}_category": score(case.truth, dg.verdict, dg.decision.candidates)}


def _row(title: str, draws: list, key: str = "follow_up_category") -> str:
    f = fractions([{"category": d[key]} for d in draws])
    cells = [f"{100 * f[c]:.0f} %" if f["n"] else "-" for c in CATEGORIES]
    return f"| {title} | {len(draws)} | " + " | ".join(cells) + " |"


def markdown(draws: list, args) -> list[str]:
    undecided = [d for d in draws if "recommended" in d]
    run = [d for d in undecided if "follow_up_category" in d]
    failed = [d for d in undecided if "follow_up_category" not in d]
    md = ["# The recommended experiment, run on the law zoo", "",
          f"{len(draws)} draws of the law zoo (study seed {args.seed}, the cases of `benchmarks/gap_zoo.py`); "
          f"{len(undecided)} were `undecided` with a recommendation.  The rig that made each ran the recommended "
          "protocol and the new readings were diagnosed alone, blind; the follow-up's verdict is scored as the zoo "
          "scores verdicts (`benchmarks/gap_zoo.py`).", "",
          "| recommendation | draws | " + " | ".join(CATEGORIES) + " |",
          "|---|---|" + "---|" * len(CATEGORIES),
          _row("says it separates them", [d for d in run if d["separates"]]),
          _row("says it does not", [d for d in run if not d["separates"]]),
          _row("all", run), ""]
    both = [d for d in run if "joined_category" in d]
    md += ["The same draws with the first readings and the recommended ones diagnosed together (the rig runs the "
           "first protocol, then the recommended one; the first readings are a new run of the same protocol):", "",
           "| recommendation | draws | " + " | ".join(CATEGORIES) + " |", "|---|---|" + "---|" * len(CATEGORIES),
           _row("says it separates them", [d for d in both if d["separates"]], "joined_category"),
           _row("says it does not", [d for d in both if not d["separates"]], "joined_category"),
           _row("all", both, "joined_category"), ""]
    if failed:
        md += [f"Not run: {len(failed)} (" + "; ".join(f"#{d['index']} {d['follow_up']}" for d in failed) + ").", ""]
    if missing := [d for d in run if "joined_category" not in d]:
        md += [f"Joined runs not run: {len(missing)} (" + "; ".join(f"#{d['index']} {d['joined']}" for d in missing)
               + ").", ""]
    md += ["| # | truth | candidates | expected log Bayes factor | follow-up verdict | category | joined verdict | "
           "category |", "|---|---|---|---|---|---|---|---|"]
    for d in run:
        md.append(f"| {d['index']} | `{d['truth']}` | {', '.join(d['candidates'])} | {d['expected_log_bayes']:.1f} | "
                  f"`{d['follow_up']}` {', '.join(d['follow_up_candidates'])} | {d['follow_up_category']} | "
                  f"`{d.get('joined', '-')}` {', '.join(d.get('joined_candidates', []))} | "
                  f"{d.get('joined_category', '-')} |")
    workers = f" --workers {args.workers}" if args.workers else ""
    md += ["", f"Rerun: `.venv/bin/python benchmarks/separation_zoo.py --draws {args.draws} --seed {args.seed}"
           f"{workers}`."]
    return md


def main():
    ap = argparse.ArgumentParser(description="the recommended experiment run on the law zoo (issue 31, item 3)")
    ap.add_argument("--draws", type=int, default=300, help="number of drawn data sets")
    ap.add_argument("--seed", type=int, default=3131, help="the study's seed (each draw gets its own from it)")
    ap.add_argument("--workers", type=int, default=None, help="local worker processes (default: this process)")
    ap.add_argument("--out", type=Path, default=ROOT / "reports" / "gap")
    args = ap.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    from ambfit.engine import Engine

    with Engine(workers=args.workers) as engine:
        draws = engine.map(one_draw, list(range(args.draws)), seed=args.seed, chunk_size=1,
                           what="draws")
    (args.out / "separation.json").write_text(json.dumps({"seed": args.seed, "draws": draws}, indent=1,
                                                         default=float))
    md = markdown(draws, args)
    (args.out / "separation.md").write_text("\n".join(md) + "\n")
    print("\n".join(md))


if __name__ == "__main__":
    main()
