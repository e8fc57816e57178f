"""How a diagnosis turns held-out scores into a verdict: explained, graded, or unexplained.

Every model is scored by the mean squared held-out standardized residual (``score``; 1 at the noise floor).  With
``n`` held-out readings its standard error at the floor is ``sqrt(2 / n)`` (a mean of ``n`` squared standard
normals), scaled by the level above it.  A model

- is *at the floor* when its score is within three of those standard errors of 1 (a right law's held-out score
  sits a little above 1: each fold's prediction carries its parameters' error too);
- *explains* the data when it leaves less than ``floor_tolerance`` noise units and either removes at least
  ``min_shrink`` of the ideal law's held-out excess or reaches the floor where the ideal law does not (a weak
  effect: the excess of a model near the floor is mostly noise, so its shrink says little);
- is *better* than another when its score is lower by more than three standard errors of the other's.

The verdict is the best library law (or pair of laws) that explains the data; else the best family whose law
widened by its signature (:mod:`ambfit.diagnosis.signatures`) explains them; else, graded, the best model of all
that removes at least ``min_shrink`` of the excess, with what it leaves (:meth:`Judge.grade`); ``unexplained`` only
when nothing does.
"""

from __future__ import annotations

import dataclasses

import numpy as np


@dataclasses.dataclass(frozen=True)
class Judge:
    """The thresholds of a verdict on ``n`` held-out readings."""

    n: int
    ideal_score: float
    floor_tolerance: float = 1.0
    min_shrink: float = 0.5

    def se(self, score: float = 1.0) -> float:
        """Standard error of a held-out score at ``score`` (at least that at the floor)."""
        return float(np.sqrt(2.0 / max(self.n, 1)) * max(score, 1.0))

    @property
    def floor(self) -> float:
        """The largest score at the floor."""
        return 1.0 + 3.0 * self.se()

    def at_floor(self, model) -> bool:
        return model.score <= self.floor

    def explains(self, model) -> bool:
        if model.after >= self.floor_tolerance:
            return False
        return model.shrink >= self.min_shrink or (self.at_floor(model) and self.ideal_score > self.floor)

    def better(self, a, b) -> bool:
        """Whether ``a`` leaves significantly less than ``b``."""
        return a.score < b.score - 3.0 * self.se(b.score)

    def close(self, a, ref: float) -> bool:
        """Whether ``a``'s score cannot be told from ``ref`` (within three standard errors)."""
        return abs(a.score - ref) < 3.0 * self.se(ref)

    def grade(self, model, by: str, families: list[str]) -> dict:
        """What the verdict's model removes and what it leaves (noise units; at the floor or not)."""
        return {"model": getattr(model, "model", None) or model.effect, "families": families, "by": by,
                "removes": model.shrink, "remainder": model.after, "remainder_mean_z2": model.score,
                "floor_mean_z2": self.floor, "at_floor": self.at_floor(model), "explains": self.explains(model)}


def family_names(model) -> list[str]:
    """The families a model names: a signature's family, or a law's ``+``-joined effects."""
    return [model.family] if hasattr(model, "family") else model.effect.split("+")


def choose_law(judge: Judge, singles: list, pairs: list, pair_verdict: bool):
    """The best library law that explains the data: the best single, or the best pair when no single explains or
    the pair is significantly better (``pair_verdict``); None when none explains."""
    single = singles[0] if singles else None
    pair = pairs[0] if pairs and pair_verdict else None
    if pair is not None and judge.explains(pair) and (
            single is None or not judge.explains(single) or judge.better(pair, single)):
        return pair
    return single if single is not None and judge.explains(single) else None


def confounded(judge: Judge, model, others: list) -> list[str]:
    """The families of ``others`` whose held-out score cannot be told from ``model``'s (within three standard
    errors, or both at the noise floor: each is consistent with noise), not ``model``'s own."""
    own = "+".join(family_names(model))
    floor = judge.at_floor(model)
    names = ["+".join(family_names(o)) for o in others
             if judge.close(o, model.score) or (floor and judge.at_floor(o))]
    return [n for n in dict.fromkeys(names) if n != own]
