"""Which unmodelled effect explains where the model fails, judged on held-out readings.

For the baseline (the ideal law) and for each candidate effect, the model is fitted
by :func:`ambfit.fit` with each fold held out (block cross-validation over
operating regions) and scored on it: ``excess = sqrt(max(mean(z^2) - 1, 0))`` of the
pooled held-out standardized residuals (contract section 3; :mod:`ambfit.diagnosis.heldout`).
The verdict names the families that remove the structure: a library law or a pair of them, or a family's law
widened by its signature (:mod:`ambfit.diagnosis.signatures`), graded by what it leaves
(:mod:`ambfit.diagnosis.verdict`); ``shrink = 1 - excess_after / excess_before``.  :func:`diagnose` returns a
:class:`~ambfit.diagnosis.results.Diagnosis`.
"""

from __future__ import annotations

import contextlib
import dataclasses
import threading

import numpy as np
import pandas as pd

from ambfit.data import Dataset, load_groups
from ambfit.diagnosis.circuit_families import circuit_families
from ambfit.diagnosis.discrepancy import _discrepancy
from ambfit.diagnosis.heldout import Candidate, excess, folds, heldout_residuals
from ambfit.diagnosis.parameter_gap import parameter_gap
from ambfit.diagnosis.residuals import noise_floor, operating_variables, where
from ambfit.diagnosis.results import Diagnosis
from ambfit.diagnosis.signatures import Signature, signatures
from ambfit.diagnosis.threads import _Each
from ambfit.diagnosis.verdict import Judge, choose_law, confounded, family_names
from ambfit.estimation.fit import fit
from ambfit.estimation.results import FitResult
from ambfit.physics.bearing import PAPER_BEARING, Bearing


def default_candidates(data: pd.DataFrame, bearing: Bearing = PAPER_BEARING) -> list:
    """Every contract effect; plus the magnetic circuit of the whole bearing when the bearing description gives
    the lamination's B-H curve and every row has the other axis' currents read at the same moment."""
    from ambfit.physics.effects import EFFECTS, MagneticCircuit, effect_by_name
    from ambfit.rows import other_axis_currents

    cands = [effect_by_name(name, bearing=bearing) for name in EFFECTS]
    if bearing.b_curve and np.isfinite(other_axis_currents(data)[0]).all():
        cands.append(MagneticCircuit())
    return cands


def diagnose(data: Dataset | pd.DataFrame, *, candidates=None, bearing: Bearing = PAPER_BEARING,
             floor_tolerance: float = 1.0, min_shrink: float = 0.5, pairs: bool = True, pair_verdict: bool = True,
             max_steps: int = 60, baseline: FitResult | None = None, progress=None, check_force: bool = True,
             discrepancy: bool = True, threads: int = 2, **noise) -> Diagnosis:
    """Where the ideal model fails, which candidate effect explains it on held-out data, how far the gap shrinks.

    Verdict (:mod:`ambfit.diagnosis.verdict` gives the thresholds): ``none`` when the baseline's held-out
    residuals sit on the noise floor (excess below ``floor_tolerance`` and no structured region).  Otherwise the
    best candidate (default: every effect in :data:`ambfit.physics.effects.EFFECTS`) if it *explains* the data
    (removes at least ``min_shrink`` of the excess, or reaches the floor where the ideal law does not, and leaves
    less than ``floor_tolerance``); when no single effect reaches the floor, the best single plus each other
    candidate are tried the same way (``pairs=True``), and a pair is the verdict when no single explains or the pair
    is significantly better (``pair_verdict=True``, the default: real bearings often carry two effects at once;
    with False the pair is only reported as ``best_pair``).  ``max_steps`` is the Levenberg-Marquardt budget of each candidate fit;
    ``baseline`` is the ideal fit of these data when the caller already has it.  ``progress``, if given, is
    called as ``progress("candidate effects", done, total)`` after each model's held-out fits (from a worker
    thread).  ``threads``: how many fits run at once (each compiled solve releases the interpreter while it runs;
    1: one after another, the same results to round-off).  A model's fold refits leave out the readings its fit
    of every row named outliers (one outlier test per model; that fit saw the held-out rows too).

    **A family whose law differs from the library's**: when no law reaches the floor, every family's law is
    widened by its signature (:mod:`ambfit.diagnosis.signatures`: the discrepancy's groups of the variables the
    family acts through) and scored on the same folds.  A family whose signature the data want clearly and whose
    widened law explains the data (when no law does, or reaching the floor when the law does not) is the verdict;
    ``law`` says how much the library's own law leaves, and the families sharing its signature that explain the
    data too are listed as confounded.

    **Graded**: when nothing explains the data, the model that removes most of the excess (a law, a pair or a
    widened law) is the verdict if it removes at least ``min_shrink``, with ``grade`` saying what it leaves (noise
    units, at the floor or not); ``unexplained`` only when nothing does.  The force check of the model that removes
    most is always reported (``force_check.best`` when it is not the verdict's law).

    **The discrepancy** (``discrepancy=True``, :mod:`ambfit.estimation.discrepancy`): the ideal law and the
    verdict's model each get the nonparametric correction on the same folds; its held-out shrink is the
    ceiling of what any effect expressible in flux density, gap, the other axis and approach direction could
    explain.  Its force check joins ``force_check`` as ``"discrepancy"``.
    """
    from ambfit.estimation.core import Model
    from ambfit.estimation.lm import compiled_together
    from ambfit.estimation.problem import owned

    df = (data.frame if isinstance(data, Dataset) else data).reset_index(drop=True)   # its own copy (see owned)
    cands = list(candidates) if candidates is not None else default_candidates(df, bearing)
    # the ideal law and every candidate share one compiled solve (a cold diagnosis is dominated by compiling)
    with compiled_together([Model.of((), bearing)] + [Model.of((e,), bearing) for e in cands]), owned(df), \
            _Each(threads) as each, contextlib.ExitStack() as later:
        return _diagnose(df, cands, bearing=bearing, floor_tolerance=floor_tolerance, min_shrink=min_shrink,
                         pairs=pairs, pair_verdict=pair_verdict, max_steps=max_steps, baseline=baseline,
                         progress=progress, check_force=check_force, discrepancy=discrepancy, noise=noise, each=each,
                         later=later)


def _diagnose(df, cands, *, bearing, floor_tolerance, min_shrink, pairs, pair_verdict, max_steps, baseline, progress,
              check_force, discrepancy, noise, each, later) -> Diagnosis:
    base = baseline if baseline is not None else fit(df, bearing=bearing, **noise)
    fold_name, tests = folds(df)
    groups = load_groups(df).to_numpy()
    count = {"done": 0, "total": 1 + len(cands)}

    lock = threading.Lock()

    def heldout(effect_sets, before) -> list:
        """Each model fitted to every row, then with each fold held out and scored on it (``before``: the ideal
        law's held-out excess, None for the ideal law itself, whose fit of every row is ``base``)."""
        # each fold starts from the model's fit of every row (the same model, so its effect parameters too); a
        # circuit of the whole bearing starts further from the ideal law: it gets the default step budget
        steps = [_budget(effects, max_steps) for effects in effect_sets]
        full = [None] * len(effect_sets)
        left = [len(tests)] * len(effect_sets)

        def refit(job):
            k, test = job
            # the readings the model's fit of every row named outliers are left out of every fold, which is not
            # tested again (alpha=0): one outlier test per model, not one per fold, whose Cauchy-weighted anchor
            # would cost a solve per fold of a misfitting candidate only to conclude that it does not fit
            f = fit(df, effect_sets[k], bearing=bearing, mask=(~test & full[k].fitted_rows).astype(float),
                    start_from=full[k], max_steps=steps[k], throw=False, alpha=0.0, **noise)
            with lock:
                left[k] -= 1
                if left[k] == 0:
                    count["done"] += 1
                    if progress is not None:
                        progress("candidate effects", count["done"], count["total"])
            return f

        def fit_all(k):
            full[k] = base if not effect_sets[k] else fit(
                df, effect_sets[k], bearing=bearing, start_from=base, max_steps=steps[k], throw=False, **noise)

        def fit_all_then_folds(k):
            fit_all(k)
            return [each.submit(refit, (k, test)) for test in tests]     # a model's folds as soon as it is fitted

        # the first refit runs on this thread: a solve not yet compiled (a diagnosis given its baseline) is then
        # compiled once, not by two threads at the same time
        fit_all(0)
        first = refit((0, tests[0]))
        queued = [[each.submit(refit, (0, test)) for test in tests[1:]]]
        heads = [each.submit(fit_all_then_folds, k) for k in range(1, len(effect_sets))]
        queued += [h.result() for h in heads]
        refits = [first] + [f.result() for q in queued for f in q]
        out = []
        for k, effects in enumerate(effect_sets):
            fitted = refits[k * len(tests):(k + 1) * len(tests)]
            z = np.concatenate([heldout_residuals(f, df, test, groups) for test, f in zip(tests, fitted)])
            out.append(Candidate("+".join(type(e).name for e in effects) or "ideal", z,
                                 excess(z) if before is None else before, full[k], tuple(zip(tests, fitted))))
        return out

    # the ideal law and every candidate at once; the candidates' "before" is the ideal law's held-out excess
    ideal, *singles = heldout([()] + [(e,) for e in cands], None)
    before = ideal.after
    singles = [dataclasses.replace(c, before=before) for c in singles]
    loc = where(df, base)
    on_floor = before < floor_tolerance and not loc.regions

    judge = Judge(len(ideal.heldout_z), ideal.score, floor_tolerance, min_shrink)
    ranking = sorted(singles, key=lambda c: c.score)
    if not on_floor and ranking and pairs and not (judge.explains(ranking[0]) and judge.at_floor(ranking[0])):
        # no single effect reaches the floor: forward selection, the best single plus each other candidate
        first = ranking[0].effect
        best_single = next(e for e in cands if type(e).name == first)
        # the circuit already holds iron, fringing, leakage and coupling: it is not paired
        partners = [e for e in cands if type(e).name != first and not getattr(e, "needs_other_axis", False)]
        if not getattr(best_single, "needs_other_axis", False):
            count["total"] += len(partners)
            from ambfit.estimation.core import Model
            from ambfit.estimation.lm import compiled_together

            # the pairs as one compiled set of their own, for the rest of the diagnosis (``later`` closes it)
            later.enter_context(compiled_together([Model.of((best_single, e), bearing) for e in partners]))
            ranking += heldout([(best_single, e) for e in partners], before)
        ranking.sort(key=lambda c: c.score)
    pair_list = [c for c in ranking if "+" in c.effect]
    singles = [c for c in ranking if "+" not in c.effect]
    model = None if on_floor else choose_law(judge, singles, pair_list, pair_verdict)
    # each family's law widened by its signature, when no law reaches the floor: a law other than the library's
    sigs = [] if on_floor or (model is not None and judge.at_floor(model)) else signatures(df, singles, noise, each)
    clear = [s for s in sigs if s.clear]
    laws = ranking if pair_verdict else singles
    law = grade = None
    if on_floor:
        verdict = "none"
        confounded_with = [c.effect for c in ranking if judge.close(c, ideal.score)]
    else:
        if clear and judge.explains(clear[0]) and (model is None or (
                judge.at_floor(clear[0]) and judge.better(clear[0], model))):
            # a family's law widened by its signature: when no law explains, or it reaches the floor and they not;
            # of families that share the signature and cannot be told apart by it, the one whose own law goes furthest
            model = min((s for s in clear if s.groups == clear[0].groups and judge.close(s, clear[0].score)),
                        key=lambda s: s.law.score)
        if model is None:
            # graded: the model that removes most of the excess, if it removes at least min_shrink of it
            pool = sorted(laws + clear, key=lambda m: m.score)
            model = pool[0] if pool and pool[0].shrink >= min_shrink else None
        verdict = "+".join(family_names(model)) if model is not None else "unexplained"
        confounded_with = [] if model is None else confounded(judge, model, laws + clear)
        if model is not None:
            by = "signature" if isinstance(model, Signature) else "pair" if "+" in model.effect else "law"
            grade = judge.grade(model, by, family_names(model))
        if isinstance(model, Signature):
            law = model.to_json()
            # the families whose laws widened by the same signature explain the data too: it cannot tell them apart
            twins = [s.family for s in clear if s.groups == model.groups and judge.explains(s)]
            confounded_with = [f for f in dict.fromkeys(confounded_with + twins) if f != model.family]
    verdict_law = model.law if isinstance(model, Signature) else model
    verdict_fit = verdict_law.fit if verdict_law is not None else None
    best_pair = None
    if pair_list:
        bp = pair_list[0]
        best_pair = {"effect": bp.effect, "heldout_excess_after": bp.after, "shrink": bp.shrink,
                     "explains": bool(judge.explains(bp))}
    disc = _discrepancy(df, ideal, verdict_law, before, noise, progress, each) if discrepancy else None
    families = None
    if verdict == "magnetic_circuit":
        # the circuit is physics, the verdict names its families: each piece's contribution, largest first
        families = circuit_families(df, verdict_fit, bearing, **noise)
        named = [f["family"] for f in families if f["significant"]]
        verdict = "+".join(dict.fromkeys(named)) or verdict
        if grade is not None:
            grade["families"] = verdict.split("+")
    # the force check of the model that removes most: the verdict's signature model, or the best law when none
    best = model if isinstance(model, Signature) else singles[0] if singles and model is None and not on_floor \
        else None
    return Diagnosis(
        baseline=base, noise_floor=noise_floor(base), where=loc, folds=fold_name, ideal=ideal, ranking=ranking,
        verdict=verdict, confounded_with=confounded_with,
        # for "unexplained" this is the best candidate's partial shrink; for "none" there is nothing to shrink
        shrink=0.0 if on_floor or not singles else (model.shrink if model is not None else singles[0].shrink),
        verdict_fit=verdict_fit, operating=operating_variables(df, base),
        parameter_gap=parameter_gap(base, bearing, model_fit=verdict_fit),
        best_pair=best_pair, families=families, law=law, discrepancy=disc, grade=grade,
        signatures=[s.to_json() for s in sigs] or None,
        force_check=_force_checks(df, base, verdict_fit, bearing, noise, discrepancy, max_steps,
                                  _fold_fits([ideal] + ranking, disc), each, best=best)
        if check_force else None)


def _budget(effects, max_steps: int) -> int:
    """Levenberg-Marquardt steps per round for a model's fits: a circuit of the whole bearing starts further from
    the ideal law and gets at least the default budget of :func:`ambfit.fit` (200)."""
    return max(max_steps, 200) if any(getattr(e, "needs_other_axis", False) for e in effects) else max_steps


def _fold_fits(cands, disc) -> dict:
    """Each model's cross-validation refits as ``(held-out mask, fit, discrepancy or None)``, by the fit's model
    name: a force check whose left-out load is a fold reuses them (the same model, start and step budget)."""
    out = {c.fit.model: [(t, f, None) for t, f in c.folds] for c in cands}
    names = {c.effect: c.fit.model for c in cands}
    for effect, folds_ in ((disc or {}).get("folds") or {}).items():
        out[names[effect]] = folds_
    return out


def _force_checks(df, base, verdict_fit, bearing, noise, discrepancy: bool = True, max_steps: int = 60,
                  fitted=None, each=None, best=None) -> dict | None:
    """Contract section 3's ``force_check``: leave-one-load-out for the ideal law, the verdict's model and the
    discrepancy model (the verdict's model with the correction, or the ideal law's when the verdict has no
    effects), from the same refits.  Each refit gets the step budget its model had in the diagnosis; a left-out
    load that is one of the diagnosis' folds reuses that fold's refit (``fitted``, by model name).  ``each``: how
    each check's left-out loads are run (:class:`_Each`; default one after the other).  ``best``: the model that
    removes most of the excess when it is not the verdict's law (a family's law widened by its signature, or the
    best law when nothing is the verdict): its check is reported as ``best``, so force measurement can judge it
    even when it does not reach the floor."""
    from ambfit.estimation.core import FitError
    from ambfit.estimation.measure import force_check

    with_effects = verdict_fit is not None and bool(verdict_fit.effects)
    fitted = fitted or {}
    jobs = [((), base, discrepancy and not with_effects, max_steps, fitted.get(base.model, ()))]
    if with_effects:
        jobs.append((verdict_fit.effects, verdict_fit, discrepancy, _budget(verdict_fit.effects, max_steps),
                     fitted.get(verdict_fit.model, ())))
    widened = isinstance(best, Signature)
    best_fit = best.law.fit if widened else best.fit if best is not None else None
    if best_fit is not None and best_fit.effects:
        jobs.append((best_fit.effects, best_fit, best.groups if widened else False,
                     _budget(best_fit.effects, max_steps), best.folds if widened else fitted.get(best_fit.model, ())))

    def check(job):
        effects, fitted_all, with_discrepancy, steps, folds_ = job
        try:
            return force_check(df, effects, bearing=bearing, base=fitted_all, discrepancy=with_discrepancy,
                               max_steps=steps, fitted=folds_, each=each, **noise)
        except FitError as exc:
            return exc

    # one check after the other, each spreading its left-out loads over the threads
    ideal, *verdict = [check(job) for job in jobs]
    best_check = verdict.pop() if len(jobs) > 1 + with_effects else None
    if isinstance(ideal, FitError):
        return {"method": "leave-one-load-out", "error": str(ideal)}
    if ideal is None:
        return None
    keys = ("rms_rel", "max_rel", "rms_rel_mean", "model_error_rel", "n_loads", "n_not_converged", "noise_floor_rel")
    out = {"method": ideal["method"], "ideal": {k: ideal[k] for k in keys}}
    if "discrepancy" in ideal:
        out["discrepancy"] = ideal["discrepancy"]
    if verdict and isinstance(verdict[0], FitError):
        out["verdict"] = {"model": verdict_fit.model, "error": str(verdict[0])}
    elif verdict and verdict[0] is not None:
        v = verdict[0]
        out["verdict"] = {"model": verdict_fit.model, **{k: v[k] for k in keys}}
        if "discrepancy" in v:
            out["discrepancy"] = v["discrepancy"]
    name = best.model if widened else best_fit.model if best_fit is not None else None
    if isinstance(best_check, FitError):
        out["best"] = {"model": name, "error": str(best_check)}
    elif best_check is not None:
        # a widened law's figures are those of the law with its signature's correction
        figures = best_check["discrepancy"] if widened else best_check
        out["best"] = {"model": name, **{k: figures.get(k, best_check[k]) for k in keys}}
    return out
