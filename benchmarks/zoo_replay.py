"""The verdict's rules replayed on the law zoo's stored scores: a rule study in seconds, not a zoo run an hour.

``collect`` diagnoses the zoo's draws (:func:`ambfit.rig.zoo.draw`, each from its own seed as
``benchmarks/gap_zoo.py`` does) up to the decision and stores what :func:`ambfit.diagnosis.verdict.decide` is given:
the ideal law's held-out score, every library law's, every pair's (scored whenever the ideal law is off the floor,
so that rules deciding when pairs are needed can be replayed too), every widened law's and every widened pair's
(whenever pairs are), each reduced to its held-out residuals and predictive variances.  ``replay`` applies
:class:`~ambfit.diagnosis.verdict.Rules` to them, gating the pairs with :func:`~ambfit.diagnosis.verdict.needs_pairs`
and the widened pairs with :func:`~ambfit.diagnosis.verdict.needs_widened_pairs` as the diagnosis does, and scores
each verdict with ``gap_zoo.score``.

    .venv/bin/python benchmarks/zoo_replay.py collect --seed 3131 --draws 300 --workers 2 --into /tmp/zoo3131
    .venv/bin/python benchmarks/zoo_replay.py replay /tmp/zoo3131 [--rule ahead_se=1.5 ...]
    .venv/bin/python benchmarks/zoo_replay.py replay /tmp/zoo7373 --variant occam=all --variant occam=none --md T.md

A replay is what the diagnosis would say only up to what follows the decision (a magnetic circuit's pieces; the
zoo's bearing has no B-H curve, so none).
"""

import argparse
import dataclasses
import pickle
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from gap_zoo import CATEGORIES, fractions, score  # noqa: E402


def _light(model):
    """``model`` without its fits: what the decision reads."""
    from ambfit.diagnosis.heldout import Candidate
    from ambfit.diagnosis.signatures import Signature

    if isinstance(model, Signature):
        return Signature(law=_light(model.law), groups=model.groups, log_bayes=dict(model.log_bayes),
                         heldout_z=np.asarray(model.heldout_z), folds=(), full=None,
                         heldout_var=None if model.heldout_var is None else np.asarray(model.heldout_var),
                         widens=model.widens)
    return Candidate(effect=model.effect, heldout_z=np.asarray(model.heldout_z), before=model.before, fit=None,
                     kind=model.kind,
                     heldout_var=None if model.heldout_var is None else np.asarray(model.heldout_var))


def one_draw(job: tuple, into: str, folds: str = "regions") -> dict:
    """Draw case ``job = (item, seed)``, diagnose it up to the decision (held out on ``folds``), store the scores in
    ``into``."""
    import jax

    import ambfit
    from ambfit.diagnosis import attribution, verdict
    from ambfit.rig import zoo

    item, seed = job
    case, data = zoo.draw(np.random.default_rng(seed))
    seen = {}

    def record(rules, ideal, candidates, *, structured=False):
        seen.update(ideal=_light(ideal), candidates=[_light(c) for c in candidates], structured=structured)
        return verdict.Verdict("none")

    def every_pair(rules, ideal, singles, structured):
        return bool(singles) and not verdict.on_floor(rules, ideal, structured)

    def any_pair(rules, ideal, models):
        return any(c.kind == "pair" for c in models)

    real = attribution.decide, attribution.needs_pairs, attribution.needs_widened_pairs
    attribution.decide, attribution.needs_pairs, attribution.needs_widened_pairs = record, every_pair, any_pair
    error = None
    try:
        ambfit.diagnose(data, check_force=False, discrepancy=False, folds=folds)
    except ambfit.FitError as exc:
        error = str(exc).splitlines()[0]
    finally:
        attribution.decide, attribution.needs_pairs, attribution.needs_widened_pairs = real
        jax.clear_caches()
    out = {"index": item, "folds": folds, "kind": case.kind, "truth": case.truth, "label": case.label,
           "laws": case.describe()["laws"], "protocol": case.protocol_kind, "rows": len(data), "error": error, **seen}
    Path(into, f"{item:04d}.pkl").write_bytes(pickle.dumps(out))
    return {"index": item, "error": error}


def load(into: Path) -> list[dict]:
    return [pickle.loads(p.read_bytes()) for p in sorted(into.glob("*.pkl"))]


def verdict_of(draw: dict, rules):
    """The verdict ``rules`` give ``draw``'s stored scores (None when the diagnosis stopped with an error)."""
    from ambfit.diagnosis.verdict import decide, needs_pairs, needs_widened_pairs

    if draw["error"] is not None:
        return None
    cands = draw["candidates"]
    singles = [c for c in cands if c.kind == "law"]
    keep = needs_pairs(rules, draw["ideal"], singles, draw["structured"])
    cands = [c for c in cands if c.kind != "pair" or keep]
    if not needs_widened_pairs(rules, draw["ideal"], [c for c in cands if c.kind != "widened_pair"]):
        cands = [c for c in cands if c.kind != "widened_pair"]
    return decide(rules, draw["ideal"], cands, structured=draw["structured"])


def replay(draws: list[dict], rules) -> list[dict]:
    rows = []
    for d in draws:
        v = verdict_of(d, rules)
        name = "error" if v is None else v.name
        cands = () if v is None else v.candidates
        rows.append({"index": d["index"], "kind": d["kind"], "truth": d["label"], "verdict": name,
                     "candidates": cands, "category": score(d["truth"], name, cands),
                     "excess": None if v is None else d["ideal"].after, "laws": d["laws"]})
    return rows


def _shares(rows: list[dict]) -> list[str]:
    """Each category's share of ``rows`` (:func:`gap_zoo.fractions`), to a tenth of a per cent."""
    f = fractions(rows)
    return [f"{100 * f[c]:.1f} %" if f["n"] else "-" for c in CATEGORIES]


def table(rows: list[dict]) -> str:
    return " ".join(f"{c} {s}" for c, s in zip(CATEGORIES, _shares(rows))) + f" (n={len(rows)})"


def compare(draws: list[dict], rules, variants: list[str], into) -> str:
    """A Markdown table: each category's share of ``draws`` under each variant of ``rules``, overall and by kind."""
    md = [f"Rules replayed on the stored scores of {len(draws)} law-zoo draws ({', '.join(f'`{p}`' for p in into)}; "
          "`benchmarks/zoo_replay.py`).", "",
          "| rules | draws | " + " | ".join(CATEGORIES) + " |", "|---|---|" + "---|" * len(CATEGORIES)]
    for spec in variants:
        rows = replay(draws, with_fields(rules, spec.split(",")))
        for kind in (None, "single", "pair", "no_family", "none"):
            sel = [r for r in rows if kind is None or r["kind"] == kind]
            md.append(f"| `{spec}` | {kind or 'all'} ({len(sel)}) | " + " | ".join(_shares(sel)) + " |")
    return "\n".join(md)


def with_fields(rules, items: list[str]):
    """``rules`` with the fields ``items`` (``field=value`` each) set."""
    return dataclasses.replace(rules, **{k: _value(v) for k, v in (s.split("=", 1) for s in items if s)})


def _value(text: str):
    for kind in (int, float):
        try:
            return kind(text)
        except ValueError:
            pass
    return {"true": True, "false": False}.get(text.lower(), text)


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = ap.add_subparsers(dest="what", required=True)
    c = sub.add_parser("collect")
    c.add_argument("--seed", type=int, default=3131)
    c.add_argument("--draws", type=int, default=300)
    c.add_argument("--first", type=int, default=0)
    c.add_argument("--workers", type=int, default=None)
    c.add_argument("--into", type=Path, required=True)
    c.add_argument("--folds", default="regions", choices=("regions", "time"), help="the diagnosis' held-out folds")
    r = sub.add_parser("replay")
    r.add_argument("into", type=Path, nargs="+")
    r.add_argument("--rule", action="append", default=[], help="a Rules field=value")
    r.add_argument("--list", action="store_true", help="every draw whose category is not right")
    r.add_argument("--variant", action="append", default=[],
                   help="a rule set to compare, 'field=value,field=value' on top of --rule (repeatable)")
    r.add_argument("--md", type=Path, default=None, help="write the comparison of the variants here (Markdown)")
    args = ap.parse_args()
    if args.what == "collect":
        from functools import partial

        from ambfit.engine import Engine

        args.into.mkdir(parents=True, exist_ok=True)
        # each draw's seed depends on its index only (gap_zoo's: the study seed's child of that index)
        seeds = np.random.SeedSequence(args.seed).spawn(args.first + args.draws)
        jobs = [(i, seeds[i]) for i in range(args.first, args.first + args.draws)
                if not (args.into / f"{i:04d}.pkl").exists()]
        mixed = {d.get("folds", "regions") for d in load(args.into)} - {args.folds}
        if mixed:
            sys.exit(f"{args.into} holds scores of other folds ({', '.join(sorted(mixed))}): collect into a new folder")
        with Engine(workers=args.workers) as engine:
            engine.map(partial(one_draw, into=str(args.into), folds=args.folds), jobs, chunk_size=1, what="draws")
        return
    from ambfit.diagnosis.verdict import Rules

    rules = with_fields(Rules(), args.rule)
    draws = [d for into in args.into for d in load(into)]
    if args.variant:
        md = compare(draws, rules, args.variant, args.into)
        print(md)
        if args.md is not None:
            args.md.write_text(md + "\n")
        return
    rows = replay(draws, rules)
    print(table(rows))
    for kind in ("none", "single", "pair", "no_family"):
        print(f"  {kind:10s}", table([r for r in rows if r["kind"] == kind]))
    if args.list:
        for r in rows:
            if r["category"] != "right":
                print(r["index"], r["truth"], "->", r["verdict"], list(r["candidates"]), r["category"],
                      f"excess {r['excess'] or 0:.2f}")


if __name__ == "__main__":
    main()
