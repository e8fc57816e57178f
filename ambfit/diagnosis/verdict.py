"""How a diagnosis turns held-out scores into a verdict: the rules, and one pure function that applies them.

Every model is scored by the mean squared held-out standardized residual (``score``; 1 at the noise floor).  With
``n`` held-out readings its standard error at the floor is ``sqrt(2 / n)`` (a mean of ``n`` squared standard
normals), scaled by the level above it.  A model

- is *at the floor* when its score is within ``Rules.floor_se`` of those standard errors of 1 (a right law's
  held-out score sits a little above 1: each fold's prediction carries its parameters' error too);
- *explains* the data when it leaves less than ``Rules.floor_tolerance`` noise units and either removes at least
  ``Rules.min_shrink`` of the ideal law's held-out excess or reaches the floor where the ideal law does not (a
  weak effect: the excess of a model near the floor is mostly noise, so its shrink says little);
- is *better* than another when its score is lower by more than ``Rules.better_se`` standard errors of the other's.

:func:`decide` applies them to scored models (:class:`~ambfit.diagnosis.heldout.Candidate` laws and pairs,
:class:`~ambfit.diagnosis.signatures.Signature` widened laws): the verdict is the best library law (or pair of
laws) that explains the data; else the best family whose law widened by its signature explains them; else,
graded, the best model of all that removes at least ``min_shrink`` of the excess, with what it leaves
(:class:`Grade`); ``unexplained`` only when nothing does.  :func:`needs_pairs` and :func:`needs_signatures` say,
from the same rules, whether the scores so far call for more candidates.  Nothing here fits: every function is
pure, and unit tests drive it with hand-made scores.
"""

from __future__ import annotations

import dataclasses

import numpy as np


@dataclasses.dataclass(frozen=True)
class Rules:
    """Every threshold of a verdict, in one place (:func:`ambfit.diagnose` takes them as ``rules``).

    Attributes
    ----------
    floor_tolerance : float
        A model explains the data only when it leaves less than this held-out excess [noise units]; the ideal
        law is on the floor (verdict ``none``) below it when no region is structured.
    min_shrink : float
        The share of the ideal law's held-out excess a model must remove to explain the data (or to be a graded
        verdict when nothing explains them).
    floor_se : float
        At the floor: a score within this many standard errors of 1.
    better_se : float
        Significantly better (a pair over a single, a widened law over a law) and indistinguishable
        (``confounded_with``): a difference of more than / less than this many standard errors.
    log_bayes_clear : float
        A signature is clearly in the residuals when the marginal likelihood wants one of its discrepancy groups
        by more than this (log Bayes factor; above 5 is 'very strong' on Kass and Raftery's 1995 scale; the FEM
        bearing, with no hysteresis, gives its direction group 3.3).
    structure_alpha : float
        False-alarm probability of the search for structured regions (:func:`ambfit.diagnosis.residuals.where`).
    circuit_dchi2 : float
        A piece of the magnetic circuit counts in the verdict when switching it off raises χ² by more than this
        many of χ²'s standard deviations ``sqrt(2 dof)`` (:func:`ambfit.diagnosis.circuit_families.circuit_families`).
    pairs : bool
        Try pairs of effects when no single one reaches the floor.
    pair_verdict : bool
        Let a pair be the verdict when no single explains the data or the pair is significantly better (with
        False the best pair is only reported).
    """

    floor_tolerance: float = 1.0
    min_shrink: float = 0.5
    floor_se: float = 3.0
    better_se: float = 3.0
    log_bayes_clear: float = 10.0
    structure_alpha: float = 0.01
    circuit_dchi2: float = 3.0
    pairs: bool = True
    pair_verdict: bool = True


@dataclasses.dataclass(frozen=True)
class Judge:
    """The :class:`Rules` applied to ``n`` held-out readings whose ideal law scores ``ideal_score``."""

    n: int
    ideal_score: float
    rules: Rules = Rules()

    def se(self, score: float = 1.0) -> float:
        """Standard error of a held-out score at ``score`` (at least that at the floor)."""
        return float(np.sqrt(2.0 / max(self.n, 1)) * max(score, 1.0))

    @property
    def floor(self) -> float:
        """The largest score at the floor."""
        return 1.0 + self.rules.floor_se * self.se()

    def at_floor(self, model) -> bool:
        return model.score <= self.floor

    def explains(self, model) -> bool:
        if model.after >= self.rules.floor_tolerance:
            return False
        return model.shrink >= self.rules.min_shrink or (self.at_floor(model) and self.ideal_score > self.floor)

    def better(self, a, b) -> bool:
        """Whether ``a`` leaves significantly less than ``b``."""
        return a.score < b.score - self.rules.better_se * self.se(b.score)

    def close(self, a, ref: float) -> bool:
        """Whether ``a``'s score cannot be told from ``ref``."""
        return abs(a.score - ref) < self.rules.better_se * self.se(ref)

    def clear(self, signature) -> bool:
        """Whether the data clearly want ``signature``'s discrepancy groups."""
        return signature.log_bayes_max > self.rules.log_bayes_clear

    def grade(self, model) -> Grade:
        """What ``model`` removes and what it leaves."""
        return Grade(model=model.label, families=tuple(model.families), by=model.kind, removes=model.shrink,
                     remainder=model.after, remainder_mean_z2=model.score, floor_mean_z2=self.floor,
                     at_floor=self.at_floor(model), explains=self.explains(model))


@dataclasses.dataclass(frozen=True)
class Grade:
    """What a verdict's model removes and what it leaves: noise units, at the floor or not, explaining or not.

    ``by`` is how the model was found: a library ``law``, a ``pair`` of laws, or a law widened by its family's
    ``signature``."""

    model: str
    families: tuple
    by: str
    removes: float
    remainder: float
    remainder_mean_z2: float
    floor_mean_z2: float
    at_floor: bool
    explains: bool

    def to_json(self) -> dict:
        return {"model": self.model, "families": list(self.families), "by": self.by, "removes": self.removes,
                "remainder": self.remainder, "remainder_mean_z2": self.remainder_mean_z2,
                "floor_mean_z2": self.floor_mean_z2, "at_floor": self.at_floor, "explains": self.explains}


KINDS = ("none", "named", "undecided", "unexplained")


@dataclasses.dataclass(frozen=True)
class Verdict:
    """What the data say.

    Attributes
    ----------
    kind : {"none", "named", "undecided", "unexplained"}
        ``none``: the ideal law's held-out residuals sit on the noise floor.  ``named``: one model's families
        (explaining the data, or graded when nothing does).  ``undecided``: several models explain the data and
        these data cannot tell them apart (``candidates``).  ``unexplained``: nothing removes enough.
    model : Candidate or Signature or None
        The named model.
    families : tuple of str
        The families it names, in the order of their contribution.
    confounded_with : tuple of str
        Models (``+``-joined families) whose held-out score cannot be told from the verdict's.
    grade : Grade or None
        What the named model removes and leaves.
    shrink : float
        Held-out shrink of the verdict (of the best single law when ``unexplained``; 0 for ``none``).
    best : Candidate or Signature or None
        The model that removes most of the excess when it is not the verdict's law (a widened law, or the best
        law when nothing is named): its force check is reported as ``best``.
    candidates : tuple of str
        ``undecided``: the models that explain the data, best first.
    """

    kind: str
    model: object = None
    families: tuple = ()
    confounded_with: tuple = ()
    grade: Grade | None = None
    shrink: float = 0.0
    best: object = None
    candidates: tuple = ()

    def __post_init__(self):
        if self.kind not in KINDS:
            raise ValueError(f"kind must be one of {KINDS}, got {self.kind!r}")

    @property
    def name(self) -> str:
        """The contract's ``verdict``: ``none``, ``undecided``, ``unexplained`` or the ``+``-joined families."""
        return "+".join(self.families) if self.kind == "named" else self.kind

    @property
    def law(self):
        """The named model's library law (a widened law's own; None when nothing is named)."""
        return getattr(self.model, "law", self.model)

    def with_families(self, families) -> Verdict:
        """The same verdict naming ``families`` (a magnetic circuit's significant pieces)."""
        families = tuple(families) or self.families
        grade = None if self.grade is None else dataclasses.replace(self.grade, families=families)
        return dataclasses.replace(self, families=families, grade=grade)


def on_floor(rules: Rules, ideal, structured: bool) -> bool:
    """Whether the ideal law's held-out residuals sit on the noise floor (no structured region either)."""
    return ideal.after < rules.floor_tolerance and not structured


def needs_pairs(rules: Rules, ideal, singles: list, structured: bool) -> bool:
    """Whether pairs of effects are to be scored: no single law reaches the floor explaining the data."""
    if on_floor(rules, ideal, structured) or not singles or not rules.pairs:
        return False
    judge = Judge(len(ideal.heldout_z), ideal.score, rules)
    best = min(singles, key=lambda c: c.score)
    return not (judge.explains(best) and judge.at_floor(best))


def needs_signatures(rules: Rules, ideal, laws: list, structured: bool) -> bool:
    """Whether the families' laws widened by their signatures are to be scored: no law reaches the floor."""
    if on_floor(rules, ideal, structured):
        return False
    judge = Judge(len(ideal.heldout_z), ideal.score, rules)
    model = _choose_law(judge, *_split(laws))
    return not (model is not None and judge.at_floor(model))


def decide(rules: Rules, ideal, candidates: list, *, structured: bool = False) -> Verdict:
    """The verdict from scored models.

    Parameters
    ----------
    rules : Rules
        The thresholds.
    ideal : Candidate
        The ideal law's held-out score.
    candidates : list
        Scored models: library laws and pairs (``kind`` ``"law"`` / ``"pair"``) and widened laws (``kind``
        ``"signature"``), in the order they were scored (ties keep it).
    structured : bool
        Whether the ideal law's residuals have structured regions (:func:`ambfit.diagnosis.residuals.where`).
    """
    judge = Judge(len(ideal.heldout_z), ideal.score, rules)
    singles, pairs = _split(candidates)
    sigs = sorted((c for c in candidates if c.kind == "signature"), key=lambda s: s.score)
    if on_floor(rules, ideal, structured):
        ranking = sorted(singles + pairs, key=lambda c: c.score)
        return Verdict("none", confounded_with=tuple(c.label for c in ranking if judge.close(c, ideal.score)))
    model = _choose_law(judge, singles, pairs if rules.pair_verdict else [])
    clear = [s for s in sigs if judge.clear(s)]
    laws = sorted(singles + pairs, key=lambda c: c.score) if rules.pair_verdict else singles
    if clear and judge.explains(clear[0]) and (model is None or (
            judge.at_floor(clear[0]) and judge.better(clear[0], model))):
        # a family's law widened by its signature: when no law explains, or it reaches the floor and they not; of
        # families that share the signature and cannot be told apart by it, the one whose own law goes furthest
        model = min((s for s in clear if s.groups == clear[0].groups and judge.close(s, clear[0].score)),
                    key=lambda s: s.law.score)
    if model is None:
        # graded: the model that removes most of the excess, if it removes at least min_shrink of it
        pool = sorted(laws + clear, key=lambda m: m.score)
        model = pool[0] if pool and pool[0].shrink >= rules.min_shrink else None
    best_single = singles[0] if singles else None
    if model is None:
        return Verdict("unexplained", shrink=best_single.shrink if best_single is not None else 0.0,
                       best=best_single)
    confounded_with = _confounded(judge, model, laws + clear)
    if model.kind == "signature":
        # the families whose laws widened by the same signature explain the data too: it cannot tell them apart
        twins = [s.family for s in clear if s.groups == model.groups and judge.explains(s)]
        confounded_with = [f for f in dict.fromkeys(confounded_with + twins) if f != model.family]
    return Verdict("named", model=model, families=tuple(model.families), confounded_with=tuple(confounded_with),
                   grade=judge.grade(model), shrink=model.shrink if best_single is not None else 0.0,
                   best=model if model.kind == "signature" else None)


def _split(candidates: list) -> tuple[list, list]:
    """The single laws and the pairs, each best first (ties in the order given)."""
    key = lambda c: c.score    # noqa: E731
    return (sorted((c for c in candidates if c.kind == "law"), key=key),
            sorted((c for c in candidates if c.kind == "pair"), key=key))


def _choose_law(judge: Judge, singles: list, pairs: list):
    """The best library law that explains the data: the best single, or the best pair when no single explains or
    the pair is significantly better; None when none explains."""
    single = singles[0] if singles else None
    pair = pairs[0] if pairs and judge.rules.pair_verdict else None
    if pair is not None and judge.explains(pair) and (
            single is None or not judge.explains(single) or judge.better(pair, single)):
        return pair
    return single if single is not None and judge.explains(single) else None


def _confounded(judge: Judge, model, others: list) -> list[str]:
    """The models of ``others`` whose held-out score cannot be told from ``model``'s (or both at the noise floor:
    each is consistent with noise), not ``model``'s own families."""
    own = "+".join(model.families)
    floor = judge.at_floor(model)
    names = ["+".join(o.families) for o in others if judge.close(o, model.score) or (floor and judge.at_floor(o))]
    return [n for n in dict.fromkeys(names) if n != own]
