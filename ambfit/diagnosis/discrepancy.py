"""The model-discrepancy term on held-out folds: the ceiling of what any smooth effect could explain.

The whole discrepancy (:mod:`ambfit.estimation.discrepancy`), added to the ideal law and to the verdict's model on
the same folds, gives the ceiling of what any effect expressible in flux density, gap, the other axis and approach
direction could explain (:func:`ceiling`, a :class:`Ceiling`).  A family's own groups of it are its signature
(:mod:`ambfit.diagnosis.signatures`).
"""

from __future__ import annotations

import dataclasses
import functools

from ambfit.diagnosis.heldout import Candidate, excess, shrink
from ambfit.diagnosis.signatures import widened
from ambfit.diagnosis.threads import _Each


@dataclasses.dataclass(frozen=True)
class CeilingScore:
    """The discrepancy added to one model: its held-out excess and shrink (and, on the ideal law, its in-sample
    shrink: the ceiling of what any such effect explains)."""

    heldout_excess_after: float
    shrink: float
    insample_shrink: float | None = None
    model: str | None = None

    def to_json(self) -> dict:
        head = {} if self.model is None else {"model": self.model}
        out = head | {"heldout_excess_after": self.heldout_excess_after, "shrink": self.shrink}
        return out if self.insample_shrink is None else out | {"insample_shrink": self.insample_shrink}


@dataclasses.dataclass(frozen=True)
class Ceiling:
    """The discrepancy on the ideal law (the ceiling) and on the verdict's model.

    Attributes
    ----------
    groups : tuple of str
        The discrepancy's groups (:data:`ambfit.estimation.basis.GROUPS`).
    ideal, verdict : CeilingScore
        Added to the ideal law; added to the verdict's model (None when the verdict has no effects).
    fit : Discrepancy
        The correction fitted on every row of ``host``.
    host : FitResult
        The verdict's model fitted to every row (the ideal law's when the verdict has no effects).
    fitted_on : str
        ``host``'s name.
    folds : dict
        Each model's ``(held-out mask, fit, discrepancy)`` per fold, by name (the force check reuses them).
    """

    groups: tuple
    ideal: CeilingScore
    verdict: CeilingScore | None
    fit: object
    host: object
    fitted_on: str
    folds: dict

    def to_json(self) -> dict:
        out = {"groups": list(self.groups), "ideal": self.ideal.to_json()}
        if self.verdict is not None:
            out["verdict"] = self.verdict.to_json()
        return out | {"fitted_on": self.fitted_on} | self.fit.summary()


def ceiling(df, ideal: Candidate, verdict: Candidate | None, before: float, noise, progress=None,
            each=None, scored=None) -> Ceiling:
    """The discrepancy's held-out shrink on the ideal law (the ceiling) and on the verdict's model, and the
    correction fitted on every row of the verdict's model (the ideal law's when there is none).  ``each``: how
    the independent pieces are run (:class:`_Each`; default one after the other); ``scored``: the readings that
    count (:func:`~ambfit.diagnosis.signatures.widened`)."""
    from ambfit.estimation.basis import GROUPS

    host = verdict if verdict is not None and verdict.fit.effects else ideal
    models = [ideal] if host is ideal else [ideal, host]
    done = (each or _Each(1))(lambda task: task(), [functools.partial(widened, c, df, GROUPS, noise, wanted=False,
                                                                      scored=scored) for c in models])
    wide = {c.effect: w for c, w in zip(models, done)}
    z_in = ideal.fit.residuals
    kept = ideal.fit.fitted_rows
    w = wide[ideal.effect]
    # in sample (every row fitted): what is left of the ideal law's excess once the correction is added
    on_ideal = CeilingScore(w.after, shrink(before, w.after),
                            insample_shrink=shrink(excess(z_in[kept]), excess((z_in + w.full.row_correction)[kept])))
    on_verdict = None
    if host is not ideal:
        w = wide[host.effect]
        on_verdict = CeilingScore(w.after, shrink(before, w.after), model=host.effect)
    if progress is not None:
        progress("discrepancy", 1, 1)
    return Ceiling(groups=tuple(GROUPS), ideal=on_ideal, verdict=on_verdict, fit=wide[host.effect].full,
                   host=host.fit, fitted_on=host.effect, folds={c.effect: wide[c.effect].folds for c in models})
