"""The verdict as a pure function of scores (issue 30): :func:`ambfit.diagnosis.verdict.decide` driven by hand-made
candidates, no fit run.  Each candidate is a real :class:`Candidate` / :class:`Signature` record whose held-out
residuals have the mean square the test names (``score``); the ideal law's is ``IDEAL`` unless said otherwise."""

import dataclasses

import numpy as np
import pytest

from ambfit.diagnosis.heldout import Candidate
from ambfit.diagnosis.signatures import Signature
from ambfit.diagnosis.verdict import Judge, Rules, Verdict, decide, needs_pairs, needs_signatures

N = 800
IDEAL = 4.0
SE = np.sqrt(2 / N)      # the standard error of a mean of N squared standard normals at the floor


def _z(score: float, n: int = N) -> np.ndarray:
    return np.full(n, np.sqrt(score))


def ideal(score: float = IDEAL) -> Candidate:
    z = _z(score)
    return Candidate("ideal", z, float(np.sqrt(max(score - 1, 0))), fit=None, kind="ideal")


def law(name: str, score: float, before: float = IDEAL) -> Candidate:
    return Candidate(name, _z(score), float(np.sqrt(before - 1)), fit=None, kind="pair" if "+" in name else "law")


def widened(family: str, score: float, law_score: float, groups=("shape",), log_bayes: float = 50.0,
            before: float = IDEAL) -> Signature:
    return Signature(law=law(family, law_score, before), groups=tuple(groups), log_bayes={groups[0]: log_bayes},
                     heldout_z=_z(score), folds=(), full=None)


def test_judge_thresholds_follow_the_standard_error_of_a_mean_of_squares():
    judge = Judge(n=N, ideal_score=IDEAL)
    assert judge.floor == pytest.approx(1 + 3 * SE)
    assert judge.at_floor(law("a", 1 + 2.9 * SE)) and not judge.at_floor(law("a", 1 + 3.1 * SE))
    # better: lower by more than three standard errors of the other's score (1.2 - 3 se(1.2) = 1.02)
    assert judge.better(law("a", 1.01), law("b", 1.2)) and not judge.better(law("a", 1.03), law("b", 1.2))
    # explains: half the excess removed and less than one noise unit left (after 0.89 / 1.10 of before 3)
    assert judge.explains(law("a", 1.8, 10.0)) and not judge.explains(law("a", 2.2, 10.0))
    assert not judge.explains(law("a", 1.5, before=1.6))                        # removes 0.09 only


def test_a_weak_effect_is_explained_by_reaching_the_floor():
    # the ideal law 0.43 noise units above the floor (mean z² 1.185 on 840 readings): a model at the floor removes
    # less than half of that excess, which near the floor is mostly noise, and explains the data all the same
    weak = Candidate("a", _z(1.05, 840), float(np.sqrt(0.185)), fit=None)
    assert weak.shrink < 0.5 and Judge(n=840, ideal_score=1.185).explains(weak)
    assert not Judge(n=840, ideal_score=1.05).explains(weak)                   # the ideal at the floor too


def test_on_the_floor_the_verdict_is_none_and_lists_what_these_data_cannot_exclude():
    on = ideal(1.0 + SE)                                   # excess 0.16 noise units, below floor_tolerance
    near, far = law("saturation", 1.0), law("hysteresis", 1.0 + 6 * SE)
    v = decide(Rules(), on, [near, far])
    assert v.kind == "none" and v.name == "none" and v.grade is None and v.shrink == 0.0
    assert v.confounded_with == ("saturation",)
    # a structured region keeps the same small excess from being the floor
    assert decide(Rules(), on, [near, far], structured=True).kind != "none"
    assert not needs_pairs(Rules(), on, [near, far], structured=False)
    assert not needs_signatures(Rules(), on, [near, far], structured=False)


def test_a_law_that_explains_is_named_and_graded():
    sat, leak = law("saturation", 1.02), law("leakage", 1.9)
    v = decide(Rules(), ideal(), [leak, sat])
    assert v.kind == "named" and v.name == "saturation" and v.model is sat
    assert v.grade.by == "law" and v.grade.at_floor and v.grade.explains
    assert v.shrink == pytest.approx(sat.shrink) and v.best is None
    assert v.confounded_with == ()
    assert not needs_pairs(Rules(), ideal(), [leak, sat], structured=False)     # at the floor already


def test_a_pair_wins_only_when_needed():
    single, pair = law("saturation", 1.4, 30.0), law("saturation+current_offset", 1.02, 30.0)
    start = ideal(30.0)
    assert needs_pairs(Rules(), start, [single], structured=False)               # the single is not at the floor
    assert decide(Rules(), start, [single, pair]).name == "saturation+current_offset"    # significantly better
    assert decide(Rules(), start, [single, pair]).grade.by == "pair"
    assert decide(Rules(pair_verdict=False), start, [single, pair]).name == "saturation"
    close = law("saturation+leakage", 1.38, 30.0)
    v = decide(Rules(), start, [single, close])
    assert v.name == "saturation" and v.confounded_with == ("saturation+leakage",)  # not significantly better
    # at the floor, every model at the floor is consistent with noise: none can be told from the verdict's
    judge = Judge(N, 30.0)
    low, far = law("fringing+current_gain", 0.9, 30.0), law("position_gain", 1.0 + 2.8 * judge.se(), 30.0)
    assert decide(Rules(), start, [far, low]).confounded_with == ("position_gain",)
    beyond = law("position_gain", 1.0 + 3.2 * judge.se(), 30.0)
    assert decide(Rules(), start, [beyond, low]).confounded_with == ()


def test_a_clear_signature_names_its_family_when_no_law_explains():
    start = ideal(10.0)
    laws = [law("hysteresis", 6.0, 10.0), law("saturation", 5.0, 10.0)]
    assert needs_signatures(Rules(), start, laws, structured=False)
    hyst = widened("hysteresis", 1.01, 6.0, groups=("hysteresis", "memory"), before=10.0)
    sat = widened("saturation", 3.0, 5.0, before=10.0)
    v = decide(Rules(), start, laws + [sat, hyst])
    assert v.name == "hysteresis" and v.model is hyst and v.best is hyst and v.law is hyst.law
    assert v.grade.by == "signature" and v.grade.model == "hysteresis widened by its hysteresis+memory signature"
    # one the data do not clearly want is not a candidate: graded, the best law
    unclear = widened("hysteresis", 1.01, 6.0, groups=("hysteresis", "memory"), log_bayes=5.0, before=10.0)
    v = decide(Rules(), start, laws + [unclear])
    assert v.name == "unexplained" and v.best.effect == "saturation"
    assert decide(Rules(log_bayes_clear=4.0), start, laws + [unclear]).name == "hysteresis"


def test_families_sharing_a_signature_go_to_the_law_that_goes_furthest_and_the_rest_are_confounded():
    start = ideal(10.0)
    fringing = widened("fringing", 1.02, 3.0, before=10.0)
    leakage = widened("leakage", 1.03, 2.0, before=10.0)         # the same signature; its own law goes further
    v = decide(Rules(), start, [law("fringing", 3.0, 10.0), law("leakage", 2.0, 10.0), fringing, leakage])
    assert v.name == "leakage" and "fringing" in v.confounded_with


def test_graded_when_nothing_explains_and_unexplained_when_nothing_removes_half():
    start = ideal(10.0)
    # leaves 1.3 noise units (more than floor_tolerance) having removed 0.57 of 3: graded, short of explaining
    v = decide(Rules(), start, [law("saturation", 2.7, 10.0), law("leakage", 5.0, 10.0)])
    assert v.kind == "named" and v.name == "saturation" and not v.grade.explains and not v.grade.at_floor
    # removes 0.33 only: unexplained, with the best single's shrink and its force check
    v = decide(Rules(), start, [law("saturation", 5.0, 10.0)])
    assert v.kind == "unexplained" and v.name == "unexplained" and v.grade is None
    assert v.shrink == pytest.approx(1 - 2 / 3) and v.best.effect == "saturation"
    # the same scores under a lower min_shrink: graded
    assert decide(Rules(min_shrink=0.3), start, [law("saturation", 5.0, 10.0)]).name == "saturation"


def test_a_verdict_names_its_kind_and_a_circuit_its_families():
    with pytest.raises(ValueError, match="kind"):
        Verdict("maybe")
    circuit = law("magnetic_circuit", 1.01)
    v = decide(Rules(), ideal(), [circuit])
    assert v.name == "magnetic_circuit"
    named = v.with_families({"saturation": None, "fringing": None})
    assert named.name == "saturation+fringing" and named.grade.families == ("saturation", "fringing")
    assert v.with_families(()).name == "magnetic_circuit"          # no significant piece: the circuit stays
    assert Verdict("undecided", candidates=("a", "b")).name == "undecided"


def test_rules_are_one_object_and_every_field_is_used():
    # each threshold, moved, changes a decision that the default rules make otherwise
    start, a = ideal(10.0), law("saturation", 1.8, 10.0)          # removes 0.70, leaves 0.89
    assert decide(Rules(), start, [a]).grade.explains
    assert not decide(Rules(floor_tolerance=0.8), start, [a]).grade.explains
    assert decide(Rules(min_shrink=0.8), start, [a]).name == "unexplained"      # nor graded: removes too little
    on = law("saturation", 1.0 + 2.5 * SE, 10.0)
    assert decide(Rules(), start, [on]).grade.at_floor and not decide(Rules(floor_se=2.0), start, [on]).grade.at_floor
    single, pair = law("saturation", 1.4, 30.0), law("saturation+leakage", 1.1, 30.0)
    assert decide(Rules(), ideal(30.0), [single, pair]).name == "saturation+leakage"
    assert decide(Rules(better_se=6.0), ideal(30.0), [single, pair]).name == "saturation"
    assert {f.name for f in dataclasses.fields(Rules)} == {
        "floor_tolerance", "min_shrink", "floor_se", "better_se", "log_bayes_clear", "structure_alpha",
        "circuit_dchi2", "pairs", "pair_verdict"}
    assert not needs_pairs(Rules(pairs=False), ideal(30.0), [single], structured=False)
