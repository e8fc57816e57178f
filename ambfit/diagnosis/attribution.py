"""Which unmodelled effect explains where the model fails, judged on held-out readings.

:func:`diagnose` runs the diagnosis in four stages, each in a module of its own:

1. **score** (:mod:`ambfit.diagnosis.scoring`): the ideal law and every candidate effect fitted with each fold
   held out (block cross-validation over operating regions) and scored on it, ``excess = sqrt(max(mean(z^2) - 1,
   0))`` of the pooled held-out standardized residuals (contract section 3; :mod:`ambfit.diagnosis.heldout`); pairs
   and each family's law widened by its signature (:mod:`ambfit.diagnosis.signatures`) when the rules call for them;
2. **decide** (:func:`ambfit.diagnosis.verdict.decide`): the verdict from those scores and one
   :class:`~ambfit.diagnosis.verdict.Rules`, a pure function;
3. **check** (:mod:`ambfit.diagnosis.checks`, :mod:`ambfit.diagnosis.discrepancy`,
   :mod:`ambfit.diagnosis.circuit_families`): force measurement with each model, the discrepancy's ceiling, the
   magnetic circuit's pieces;
4. **say** (:mod:`ambfit.diagnosis.text`): the sentences, from the :class:`~ambfit.diagnosis.results.Diagnosis`
   record.
"""

from __future__ import annotations

import contextlib
import dataclasses

import numpy as np
import pandas as pd

from ambfit.data import Dataset, file_rows
from ambfit.diagnosis.checks import Pair, fold_fits, force_checks
from ambfit.diagnosis.circuit_families import circuit_families
from ambfit.diagnosis.discrepancy import ceiling
from ambfit.diagnosis.heldout import gross_errors
from ambfit.diagnosis.noise import UNESTIMATED, NoiseEstimate, Unestimated, from_neighbours, scatter
from ambfit.diagnosis.parameter_gap import parameter_gap
from ambfit.diagnosis.residuals import noise_floor, operating_variables, where
from ambfit.diagnosis.results import Diagnosis
from ambfit.diagnosis.scoring import Scorer
from ambfit.diagnosis.separation import separate_by
from ambfit.diagnosis.threads import _Each
from ambfit.diagnosis.verdict import Judge, Rules, decide, needs_pairs, needs_signatures, needs_widened_pairs
from ambfit.estimation.fit import fit
from ambfit.estimation.results import FitResult
from ambfit.physics.bearing import PAPER_BEARING, Bearing

BASELINE_EDM = 1e-2
"""The ideal law's fit is the diagnosis's reference, not an estimate to report: a point from which a Gauss-Newton
step would still gain less than this much χ² (its EDM) is taken as its minimum.  An estimate asks for
:data:`~ambfit.estimation.core.EDM_MAX` (1e-3 standard errors); a diagnosis compares χ² across models in noise
units, where 0.01 is nothing, and a law far from the readings (a mechanical spring, 18 σ off) can stall short of
the estimate's limit and still locate its misfit exactly."""

MAX_SEPARATED = 4
"""The protocol that separates an ``undecided`` verdict's candidates is sought for its best few (every ordered pair
of them is a comparison on every protocol scored)."""


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
             rules: Rules | None = None, floor_tolerance: float | None = None, pairs: bool | None = None,
             pair_verdict: bool | None = None, max_steps: int = 60,
             baseline: FitResult | None = None, progress=None, check_force: bool = True, discrepancy: bool = True,
             threads: int = 2, folds: str = "regions", **noise) -> Diagnosis:
    """Where the ideal model fails, which candidate effect explains it on held-out data, how far the gap shrinks.

    Every model is scored on held-out folds (block cross-validation over operating regions, and over time when
    the readings have a clock; readings every model at the noise floor names outliers,
    :func:`ambfit.diagnosis.heldout.gross_errors`, count in no score) and the verdict decided from the scores by
    :func:`ambfit.diagnosis.verdict.decide`,
    every threshold a field of ``rules`` (default :class:`Rules`; ``floor_tolerance``, ``pairs`` and
    ``pair_verdict`` set those fields of it).

    - ``none``: the ideal law's held-out residuals sit on the noise floor.
    - A family (or a ``+``-joined set) is *named* only when its model *explains* the data (its held-out score at
      the noise floor, within its standard error, where the ideal law's is not) and is clearly better, reading by
      reading, than every other family's model that explains them too.  Models are tried simplest first: each
      candidate effect's library law (default: every effect in :data:`ambfit.physics.effects.EFFECTS`, and the
      magnetic circuit of a bearing with a B-H curve); when none explains, the best single plus each other
      candidate (``pairs``); when no pair explains either, each family's law widened by its signature
      (:mod:`ambfit.diagnosis.signatures`: the discrepancy's groups of the variables the family acts through),
      whose signature the data must want clearly.  ``law`` then says how much the library's own law leaves.
    - ``undecided``: several families explain the data and these data cannot tell them apart: ``candidates``
      lists them, best first.  Or, with the widened laws set aside, one family's law explains them and the
      families sharing its signature, whose broader forms these data cannot test, follow it
      (``candidates_untested``).
    - ``unexplained``: nothing reaches the floor; the model that removes most is reported (``grade``, and its
      force check as ``force_check.best``).

    **The noise.**  The std columns', or the declared ``sigma_i`` / ``sigma_x`` (``noise``).  Without a current
    noise, from each reading against its neighbours (:mod:`ambfit.diagnosis.noise`, in the residuals of the law that
    fits every row best), and every fit of the diagnosis is given that level (``noise_estimate``).

    ``max_steps`` is the Levenberg-Marquardt budget of each candidate fit; ``baseline`` is the ideal fit of these
    data when the caller already has it (fitted again at the current noise from the neighbours when it estimated
    its noise from its residuals).  ``progress``, if given, is called as ``progress("candidate effects",
    done, total)`` after each model's held-out fits.  ``threads``: how many fits run at once (each compiled solve
    releases the interpreter while it runs; 1: one after another, the same results to round-off).  A model's fold
    refits leave out the readings its fit of every row named outliers (one outlier test per model; that fit saw
    the held-out rows too).

    **The discrepancy** (``discrepancy=True``, :mod:`ambfit.estimation.discrepancy`): the ideal law and the
    verdict's model each get the nonparametric correction on the same folds; its held-out shrink is the
    ceiling of what any effect expressible in flux density, gap, the other axis and approach direction could
    explain.  Its force check joins ``force_check`` as ``"discrepancy"``.
    """
    from ambfit.estimation.core import Model
    from ambfit.estimation.lm import compiled_together
    from ambfit.estimation.problem import owned

    given = {"floor_tolerance": floor_tolerance, "pairs": pairs, "pair_verdict": pair_verdict}
    rules = dataclasses.replace(rules or Rules(), **{k: v for k, v in given.items() if v is not None})
    df = (data.frame if isinstance(data, Dataset) else data).reset_index(drop=True)   # its own copy (see owned)
    cands = list(candidates) if candidates is not None else default_candidates(df, bearing)
    # the ideal law and every candidate share one compiled solve (a cold diagnosis is dominated by compiling)
    with compiled_together([Model.of((), bearing)] + [Model.of((e,), bearing) for e in cands]), owned(df), \
            _Each(threads) as each, contextlib.ExitStack() as later:
        base = baseline if baseline is not None else _baseline(df, bearing, noise)
        estimate = None
        if base.noise_estimated and noise.get("sigma_i") is None:
            # a noise level the model's error does not enter, from neighbouring readings; the diagnosis then runs as
            # with that level declared (against the fit's own estimate every model would sit on the floor); too few
            # readings for it leave the unit level, which the record says
            estimate = _noise_from_neighbours(df, base, cands, bearing, noise, max_steps, each,
                                              progress) or UNESTIMATED
            if estimate is not UNESTIMATED:
                noise = {**noise, "sigma_i": estimate.sigma_i}
                base = _baseline(df, bearing, noise)
        scorer = Scorer(df, base, bearing=bearing, noise=noise, max_steps=max_steps, each=each, progress=progress,
                        scheme=folds)
        return _diagnose(scorer, cands, rules, check_force=check_force, discrepancy=discrepancy, later=later,
                         estimate=estimate)


def _noise_from_neighbours(df: pd.DataFrame, base: FitResult, cands: list, bearing: Bearing, noise: dict,
                           max_steps: int, each: _Each, progress=None) -> NoiseEstimate | None:
    """The current noise from each reading against its neighbours (:mod:`ambfit.diagnosis.noise`), in the residuals
    of the model that fits every row best at the unit noise (the smallest χ² per degree of freedom of the ideal law
    and each candidate's law that converged): it leaves the neighbours the least of the model's error, which they
    cancel only where it is smooth.  With a position noise known (declared, or std columns) the residuals' scale is
    not the current noise's alone: the level is the one at which that law, fitted again there, leaves pseudo-residuals
    of unit mean square, found by secant steps (at most :data:`NOISE_ROUNDS` refits).  ``progress``: as
    :func:`diagnose`'s, the phase "the readings' noise"."""
    from ambfit.diagnosis.residuals import noise_parts
    from ambfit.diagnosis.scoring import step_budget

    def told(done):
        if progress is not None:
            progress("the readings' noise", done, len(cands))

    def law(effects, more=None):
        if not effects and more is None:
            return base
        return fit(df, effects, bearing=bearing, start_from=base, max_steps=step_budget(effects, max_steps),
                   throw=False, debias="none", **{**noise, **(more or {})})

    told(0)
    # the first on this thread: a solve not yet compiled (a diagnosis given its baseline) is compiled once
    fitted = [((), base)]
    if cands:
        fitted += [((cands[0],), law((cands[0],)))] + list(zip([(e,) for e in cands[1:]],
                                                                 each(lambda e: law((e,)), cands[1:])))
    usable = [(e, f) for e, f in fitted if f.converged and np.isfinite(f.reduced_chi2)] or [((), base)]
    effects, best = min(usable, key=lambda ef: ef[1].reduced_chi2)
    estimate = from_neighbours(df, best, ideal=base)
    if estimate is not None and _position_noise_known(df, noise):
        estimate = _settled(estimate, lambda level: from_neighbours(df, law(effects, {"sigma_i": level}), level=level,
                                                                    ideal=base))
    told(len(cands))
    if estimate is None:
        return None
    current = noise_parts(base.noise_source)[0]
    return dataclasses.replace(estimate, gaps=current[current.index("("):] if "(" in current else "")


def _position_noise_known(df: pd.DataFrame, noise: dict) -> bool:
    """Whether the fits are given a position noise above 0 (declared, or complete std columns), as the problem built
    for them holds it."""
    from ambfit.estimation.problem import build_problem

    return bool(np.any(np.asarray(build_problem(df, sigma_x=noise.get("sigma_x"))[0].s_x) > 0))


def _settled(first: NoiseEstimate, at) -> NoiseEstimate:
    """The current noise at which ``at(level)`` (the estimate from a fit at ``level``) gives ``level`` back: the
    root of ``f(s) = at(s) / s - 1`` (the pseudo-residuals' root mean square, less 1) by secant steps from ``first``
    and the fixed-point step after it, at most :data:`NOISE_ROUNDS` refits; ``settled`` when ``|f|`` is below
    :data:`NOISE_TOLERANCE`."""
    points = []                                  # (level, f, the estimate there)
    level = first.sigma_i
    for k in range(1, NOISE_ROUNDS + 1):
        found = at(level)
        if found is None or not np.isfinite(found.sigma_i):
            break
        points.append((level, found.sigma_i / level - 1.0, found))
        if abs(points[-1][1]) < NOISE_TOLERANCE:
            return dataclasses.replace(found, sigma_i=level, settled=True, refits=k)
        if len(points) == 1:
            level = found.sigma_i                    # the fixed-point step
        else:
            (s0, f0, _), (s1, f1, _) = points[-2:]
            step = f1 * (s1 - s0) / (f1 - f0) if f1 != f0 else 0.0
            level = s1 - step if step and 0.0 < s1 - step < 10.0 * first.sigma_i else found.sigma_i
    if not points:
        return dataclasses.replace(first, settled=False)
    best_level, _, found = min(points, key=lambda p: abs(p[1]))
    return dataclasses.replace(found, sigma_i=best_level, settled=False, refits=len(points))


NOISE_ROUNDS = 6
"""Most refits of the best-fitting law at a current noise, when a position noise shares the residuals."""

NOISE_TOLERANCE = 0.01
"""The current noise found holds when a refit there leaves pseudo-residuals whose root mean square is within this
of 1."""


def _stated_current(df: pd.DataFrame, noise: dict) -> float:
    """The data's stated current noise [A] (declared, or the std columns), the median of the problem built for the
    fits."""
    from ambfit.estimation.problem import build_problem

    prob = build_problem(df, sigma_i=noise.get("sigma_i"), sigma_x=noise.get("sigma_x"))[0]
    return float(np.median(np.concatenate([np.asarray(prob.s_top), np.asarray(prob.s_bottom)])))


def _baseline(df: pd.DataFrame, bearing: Bearing, noise: dict) -> FitResult:
    """The ideal law's fit of every row: raises :class:`~ambfit.FitError` when the design does not identify it or
    it stopped further than :data:`BASELINE_EDM` from its minimum."""
    res = fit(df, bearing=bearing, throw=False, debias="none", **noise)
    if not (res.well_conditioned and res.edm < BASELINE_EDM):
        res.raise_for_health()
    return res


def _diagnose(scorer: Scorer, cands: list, rules: Rules, *, check_force: bool, discrepancy: bool,
              later, estimate: NoiseEstimate | Unestimated | None = None) -> Diagnosis:
    from ambfit.estimation.core import Model
    from ambfit.estimation.lm import compiled_together

    df, base, bearing, noise, each = scorer.df, scorer.base, scorer.bearing, scorer.noise, scorer.each
    # score: the ideal law and every candidate at once; the candidates' "before" is the ideal law's held-out excess
    scorer.expect(1 + len(cands))
    ideal, *singles = scorer.laws([()] + [(e,) for e in cands])
    # readings no model at the noise floor fits (a sensor's spikes, or an effect confined to them) count in no score
    gross = gross_errors([ideal, *singles])
    if gross.any():
        ideal, *singles = scorer.leave_out(gross, [ideal, *singles])
        ideal = dataclasses.replace(ideal, before=ideal.after)
    singles = [dataclasses.replace(c, before=ideal.after) for c in singles]
    # data with a stated noise: how the best-fitting law's residuals scatter between neighbours, against it
    spread = None
    if estimate is None:
        fitted = [c.fit for c in [ideal, *singles] if c.fit is not None and c.fit.converged
                  and np.isfinite(c.fit.reduced_chi2)]
        spread = scatter(df, min(fitted, key=lambda f: f.reduced_chi2), _stated_current(df, noise),
                         positions_unstated=not _position_noise_known(df, noise),
                         declared=noise.get("sigma_i") is not None) if fitted else None
    loc = where(df, base, alpha=rules.structure_alpha, rows=scorer.scored)
    structured = bool(loc.regions)
    pairs = []
    if needs_pairs(rules, ideal, singles, structured):
        # no single effect reaches the floor: forward selection, the best single plus each other candidate; the
        # circuit already holds iron, fringing, leakage and coupling: it is not paired
        first = min(singles, key=lambda c: c.score).effect
        best_single = next(e for e in cands if type(e).name == first)
        partners = [e for e in cands if type(e).name != first and not getattr(e, "needs_other_axis", False)]
        if partners and not getattr(best_single, "needs_other_axis", False):
            scorer.expect(len(partners))
            # the pairs as one compiled set of their own, for the rest of the diagnosis (``later`` closes it)
            later.enter_context(compiled_together([Model.of((best_single, e), bearing) for e in partners]))
            pairs = scorer.laws([(best_single, e) for e in partners], before=ideal.after)
    # each family's law widened by its signature whenever the ideal law is off the floor: a law other than the
    # library's, which a library law that explains must still beat
    sigs = scorer.signatures(sorted(singles, key=lambda c: c.score)) if needs_signatures(rules, ideal, structured) \
        else []
    # with pairs: each pair with one of its families' laws widened by its signature (a law other than the library's
    # beside a second effect)
    if needs_widened_pairs(rules, ideal, singles + pairs + sigs):
        sigs = sigs + scorer.widened_pairs(pairs)
    # decide
    verdict = decide(rules, ideal, singles + pairs + sigs, structured=structured)
    ranking = sorted(singles + pairs, key=lambda c: c.score)
    # check
    law = verdict.law
    verdict_fit = law.fit if law is not None else None
    ceil = ceiling(df, ideal, law, ideal.after, noise, scorer.progress, each, scored=scorer.scored) \
        if discrepancy else None
    families = None
    if verdict.name == "magnetic_circuit":
        # the circuit is physics, the verdict names its families: each piece's contribution, largest first
        families = circuit_families(df, verdict_fit, bearing, significance=rules.circuit_dchi2, each=each, **noise)
        verdict = verdict.with_families(dict.fromkeys(f.family for f in families if f.significant))
    separation = None
    if verdict.kind == "undecided":
        # what would tell the candidates apart: each one's library law or pair as fitted here (a widened law's
        # own law stands in for it), on protocols within the limits
        by_name = {"+".join(c.families): c for c in ranking}
        fits = [by_name[n].fit for n in verdict.candidates[:MAX_SEPARATED] if n in by_name]
        separation = separate_by(fits, df, bearing, noise, enough=rules.separate_log_bayes)
    judge = Judge(len(ideal.heldout_z), ideal.score, rules)
    best_pair = next((Pair(c.effect, c.after, c.shrink, bool(judge.explains(c))) for c in ranking if c.kind == "pair"),
                     None)
    return Diagnosis(
        baseline=base, noise_floor=noise_floor(base, estimate), noise_estimate=estimate, scatter=spread, where=loc,
        folds=scorer.fold_name, ideal=ideal,
        ranking=ranking, decision=verdict, rules=rules, verdict_fit=verdict_fit,
        operating=operating_variables(df, base), parameter_gap=parameter_gap(base, bearing, model_fit=verdict_fit),
        best_pair=best_pair, families=families, ceiling=ceil, signatures=sigs or None, separation=separation,
        left_out=tuple(int(r) for r in file_rows(df)[gross]),
        force_check=force_checks(df, base, verdict_fit, bearing, noise, discrepancy, scorer.max_steps,
                                 fold_fits([ideal] + ranking, ceil), each, best=verdict.best)
        if check_force else None)
