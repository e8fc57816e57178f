"""Which unmodelled effect explains where the model fails, judged on held-out readings.

For the baseline (the ideal law) and for each candidate effect, the model is fitted
by :func:`ambfit.fit` with each fold held out (block cross-validation over
operating regions) and scored on it: ``excess = sqrt(max(mean(z^2) - 1, 0))`` of the
pooled held-out standardized residuals (contract section 3; :mod:`ambfit.diagnosis.heldout`).
The verdict is the candidate that removes the structure; ``shrink = 1 - excess_after /
excess_before``.  :func:`diagnose` returns a :class:`~ambfit.diagnosis.results.Diagnosis`.
"""

from __future__ import annotations

import dataclasses
import threading

import numpy as np
import pandas as pd

from ambfit.data import Dataset, load_groups
from ambfit.diagnosis.circuit_families import circuit_families
from ambfit.diagnosis.discrepancy import SIGNATURES, _discrepancy, _law_differs
from ambfit.diagnosis.heldout import Candidate, excess, folds, heldout_residuals
from ambfit.diagnosis.parameter_gap import parameter_gap
from ambfit.diagnosis.residuals import noise_floor, operating_variables, where
from ambfit.diagnosis.results import Diagnosis
from ambfit.diagnosis.threads import _Each
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

    Verdict: ``none`` when the baseline's held-out residuals sit on the noise floor
    (excess below ``floor_tolerance`` and no structured region); otherwise the best
    candidate (default: every effect in :data:`ambfit.physics.effects.EFFECTS`) if it
    removes at least ``min_shrink`` of the excess *and* leaves the held-out residuals
    within ``floor_tolerance`` of the floor; when no single effect does, the best single
    plus each other candidate are tried the same way (``pairs=True``) and a pair can be
    the verdict (``pair_verdict=True``, the default: real bearings often carry two effects at once; with False the
    pair is only reported as ``best_pair``); otherwise ``unexplained``.  ``max_steps`` is the Levenberg-Marquardt budget of each candidate fit;
    ``baseline`` is the ideal fit of these data when the caller already has it.  ``progress``, if given, is
    called as ``progress("candidate effects", done, total)`` after each model's held-out fits (from a worker
    thread).  ``threads``: how many fits run at once (each compiled solve releases the interpreter while it runs;
    1: one after another, the same results to round-off).  A model's fold refits leave out the readings its fit
    of every row named outliers (one outlier test per model; that fit saw the held-out rows too).

    **A family whose law differs from the library's**: when the verdict would be ``unexplained`` and the best
    single candidate has a residual signature of its own
    (:data:`~ambfit.diagnosis.discrepancy.SIGNATURES`: hysteresis, residuals that depend on the approach
    direction; cross-coupling, residuals that depend on the other axis), that signature's group of the
    discrepancy basis is fitted on the candidate's residuals.  When the data want it clearly (log Bayes factor
    above :data:`~ambfit.diagnosis.discrepancy.LOG_BAYES_CLEAR`) and the candidate with it explains the
    held-out data, the family is the verdict; ``law`` says how much the library's own law left.

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
            _Each(threads) as each:
        return _diagnose(df, cands, bearing=bearing, floor_tolerance=floor_tolerance, min_shrink=min_shrink,
                         pairs=pairs, pair_verdict=pair_verdict, max_steps=max_steps, baseline=baseline,
                         progress=progress, check_force=check_force, discrepancy=discrepancy, noise=noise, each=each)


def _diagnose(df, cands, *, bearing, floor_tolerance, min_shrink, pairs, pair_verdict, max_steps, baseline, progress,
              check_force, discrepancy, noise, each) -> Diagnosis:
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

    def explains_after(after, shrunk):
        return shrunk >= min_shrink and after < floor_tolerance

    def explains(c):
        return explains_after(c.after, c.shrink)

    ranking = sorted(singles, key=lambda c: c.score)
    if not on_floor and ranking and not explains(ranking[0]) and pairs:
        # no single effect removes the structure: forward selection, the best single plus each other candidate
        first = ranking[0].effect
        best_single = next(e for e in cands if type(e).name == first)
        # the circuit already holds iron, fringing, leakage and coupling: it is not paired
        partners = [e for e in cands if type(e).name != first and not getattr(e, "needs_other_axis", False)]
        if not getattr(best_single, "needs_other_axis", False):
            count["total"] += len(partners)
            ranking += heldout([(best_single, e) for e in partners], before)
        ranking.sort(key=lambda c: c.score)
    pair_list = [c for c in ranking if "+" in c.effect]
    singles = [c for c in ranking if "+" not in c.effect]
    best = (ranking if pair_verdict else singles)[0] if (ranking if pair_verdict else singles) else None
    if on_floor:
        verdict, ref = "none", float(np.mean(ideal.heldout_z**2))
    elif best is not None and explains(best):
        verdict, ref = best.effect, best.score
    else:
        verdict, ref = "unexplained", None
    # sd of a mean of n squared standard normals is sqrt(2 / n); scaled by the level when above the floor
    se = np.sqrt(2.0 / len(ideal.heldout_z)) * max(ref, 1.0) if ref is not None else np.inf
    confounded = [] if ref is None else [c.effect for c in ranking if c.effect != verdict and abs(c.score - ref) < 3 * se]
    best_pair = None
    if pair_list:
        bp = pair_list[0]
        best_pair = {"effect": bp.effect, "heldout_excess_after": bp.after, "shrink": bp.shrink,
                     "explains": bool(explains(bp))}
    verdict_fit = next((c.fit for c in ranking if c.effect == verdict), None)
    law = None
    if verdict == "unexplained" and singles and singles[0].effect in SIGNATURES:
        # the best family's law may differ from the library's: its signature, widened by the discrepancy
        law = _law_differs(df, singles[0], before, noise)
        if law["signature_clear"] and explains_after(law["heldout_excess_after"], law["shrink"]):
            verdict, verdict_fit = singles[0].effect, singles[0].fit
            confounded = []
    disc = _discrepancy(df, ideal, next((c for c in ranking if c.effect == verdict), None), before, noise,
                        progress, each) if discrepancy else None
    families = None
    if verdict == "magnetic_circuit":
        # the circuit is physics, the verdict names its families: each piece's contribution, largest first
        families = circuit_families(df, verdict_fit, bearing, **noise)
        named = [f["family"] for f in families if f["significant"]]
        verdict = "+".join(dict.fromkeys(named)) or verdict
    return Diagnosis(
        baseline=base, noise_floor=noise_floor(base), where=loc, folds=fold_name, ideal=ideal, ranking=ranking,
        verdict=verdict, confounded_with=confounded,
        # for "unexplained" this is the best candidate's partial shrink; for "none" there is nothing to shrink
        shrink=0.0 if verdict == "none" or best is None else (
            law["shrink"] if law is not None and verdict == law["family"] else best.shrink),
        verdict_fit=verdict_fit, operating=operating_variables(df, base),
        parameter_gap=parameter_gap(base, bearing, model_fit=verdict_fit),
        best_pair=best_pair, families=families, law=law, discrepancy=disc,
        force_check=_force_checks(df, base, verdict_fit, bearing, noise, discrepancy, max_steps,
                                  _fold_fits([ideal] + ranking, disc), each,
                                  best_fit=best.fit if best is not None and verdict_fit is None else None)
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
                  fitted=None, each=None, best_fit=None) -> dict | None:
    """Contract section 3's ``force_check``: leave-one-load-out for the ideal law, the verdict's model and the
    discrepancy model (the verdict's model with the correction, or the ideal law's when the verdict has no
    effects), from the same refits.  Each refit gets the step budget its model had in the diagnosis; a left-out
    load that is one of the diagnosis' folds reuses that fold's refit (``fitted``, by model name).  ``each``: how
    each check's left-out loads are run (:class:`_Each`; default one after the other).  ``best_fit``: the best
    candidate's fit when no model is the verdict (``unexplained``): its check is reported as ``best``, so force
    measurement can judge the model that removes most of the excess even when it does not remove all of it."""
    from ambfit.estimation.core import FitError
    from ambfit.estimation.measure import force_check

    with_effects = verdict_fit is not None and bool(verdict_fit.effects)
    fitted = fitted or {}
    jobs = [((), base, discrepancy and not with_effects, max_steps)]
    if with_effects:
        jobs.append((verdict_fit.effects, verdict_fit, discrepancy, _budget(verdict_fit.effects, max_steps)))
    with_best = best_fit is not None and bool(best_fit.effects)
    if with_best:
        jobs.append((best_fit.effects, best_fit, False, _budget(best_fit.effects, max_steps)))

    def check(job):
        effects, fitted_all, with_discrepancy, steps = job
        try:
            return force_check(df, effects, bearing=bearing, base=fitted_all, discrepancy=with_discrepancy,
                               max_steps=steps, fitted=fitted.get(fitted_all.model, ()), each=each, **noise)
        except FitError as exc:
            return exc

    # one check after the other, each spreading its left-out loads over the threads
    ideal, *verdict = [check(job) for job in jobs]
    best = verdict.pop() if with_best else None
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
    if isinstance(best, FitError):
        out["best"] = {"model": best_fit.model, "error": str(best)}
    elif best is not None:
        out["best"] = {"model": best_fit.model, **{k: best[k] for k in keys}}
    return out
