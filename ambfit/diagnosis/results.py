"""The diagnosis as a record: where the ideal model fails, the scores, the verdict and its checks; its JSON.

The record holds data only: its sentences are :mod:`ambfit.diagnosis.text`'s (``str(diagnosis)`` and the
notebook view call it), and :meth:`Diagnosis.to_json` is the only flattening.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pandas as pd

from ambfit.diagnosis.checks import ForceCheck, Pair
from ambfit.diagnosis.discrepancy import Ceiling
from ambfit.diagnosis.heldout import Candidate
from ambfit.diagnosis.residuals import NoiseFloor, Where
from ambfit.diagnosis.separation import Separation
from ambfit.diagnosis.verdict import WIDENED, Grade, Judge, Rules, Verdict
from ambfit.estimation.results import FitResult


@dataclasses.dataclass(frozen=True)
class Diagnosis:
    """Where the ideal model fails, which effect explains it on held-out data, how far the gap shrinks.

    Attributes
    ----------
    baseline : FitResult
        The ideal law fitted to every row.
    noise_floor, where :
        What the residuals would be if the model were right, and where they are structured.
    folds : str
        The cross-validation scheme.
    ideal : Candidate
        The ideal law's held-out score (the ``before`` of every candidate).
    ranking : list[Candidate]
        Library laws and pairs, best (lowest held-out score) first.
    decision : Verdict
        What :func:`ambfit.diagnosis.verdict.decide` made of the scores (``verdict`` is its contract name).
    rules : Rules
        The thresholds it applied.
    verdict_fit : FitResult or None
        The verdict's model fitted to every row: its residuals are the "after" of the residual map.
    operating : DataFrame
        Per-row operating variables (flux densities, positions, ...) the residuals are mapped against.
    parameter_gap : list[dict]
        Identified parameters against the bearing description.
    best_pair : Pair or None
        The best pair scored.
    families : list[CircuitFamily] or None
        When the verdict is the magnetic circuit: what each of its pieces contributes.
    force_check : ForceCheck or None
        Each known load left out and predicted, per model.
    ceiling : Ceiling or None
        The discrepancy's held-out shrink on the ideal law and the verdict's model.
    signatures : list[Signature] or None
        Every family's law widened by its signature (and, with :attr:`Rules.widened_pairs`, each pair with one of its
        laws widened), best first, when the ideal law is off the floor.
    separation : Separation or None
        ``undecided``: the protocol that would tell the candidates apart.
    left_out : tuple of int
        Data rows (from 1) that every model at the noise floor named outliers, left out of every held-out score
        (:func:`ambfit.diagnosis.heldout.gross_errors`).
    noise_estimate : NoiseEstimate or Unestimated or None
        The current noise from neighbouring readings, when the data state none and none was declared
        (:mod:`ambfit.diagnosis.noise`): every fit of the diagnosis was given it; :class:`~ambfit.diagnosis.noise.
        Unestimated` when too few readings had neighbours for it.
    scatter : Scatter or None
        With a stated noise (std columns, or declared): how the best-fitting law's residuals scatter between
        neighbouring readings against it (:class:`ambfit.diagnosis.noise.Scatter`).
    """

    baseline: FitResult
    noise_floor: NoiseFloor
    where: Where
    folds: str
    ideal: Candidate
    ranking: list
    decision: Verdict
    verdict_fit: FitResult | None
    operating: pd.DataFrame
    parameter_gap: list
    rules: Rules = Rules()
    best_pair: Pair | None = None
    families: list | None = None
    force_check: ForceCheck | None = None
    ceiling: Ceiling | None = None
    signatures: list | None = None
    separation: Separation | None = None
    left_out: tuple = ()
    noise_estimate: object = None
    scatter: object = None

    @property
    def verdict(self) -> str:
        """An effect name, ``a+b`` for several, ``none``, ``undecided`` or ``unexplained`` (contract section 3)."""
        return self.decision.name

    @property
    def confounded_with(self) -> list[str]:
        """Models whose held-out score is statistically indistinguishable from the verdict's."""
        return list(self.decision.confounded_with)

    @property
    def shrink(self) -> float:
        """Held-out shrink of the verdict (or of the best single candidate when ``unexplained``)."""
        return self.decision.shrink

    @property
    def grade(self) -> Grade | None:
        """What the verdict's model removes and leaves; None for ``none`` and ``unexplained``."""
        return self.decision.grade

    @property
    def law(self):
        """When the verdict's family was named by its signature, that widened law or widened pair
        (:class:`~ambfit.diagnosis.signatures.Signature`: how much the library's law or pair leaves); else None."""
        model = self.decision.model
        return model if model is not None and model.kind in WIDENED else None

    @property
    def judge(self) -> Judge:
        """The rules applied to these held-out readings."""
        return Judge(len(self.ideal.heldout_z), self.ideal.score, self.rules)

    @property
    def residuals_before(self) -> np.ndarray:
        return self.baseline.residuals

    @property
    def residuals_after(self) -> np.ndarray | None:
        return None if self.verdict_fit is None else self.verdict_fit.residuals

    @property
    def heldout_excess_before(self) -> float:
        return self.ideal.after

    @property
    def most_structured_variable(self) -> str:
        return self.where.regions[0].variable if self.where.regions else "b_top_T"

    def to_json(self) -> dict:
        """The contract section 3 record, marked as a diagnose model file (schema, kind, ambfit version)."""
        from ambfit.diagnosis import text
        from ambfit.estimation.model_file import stamp

        rec = {
            "baseline": "ideal", "noise_floor": self.noise_floor.to_json(),
            **({"noise_estimate": self.noise_estimate.to_json()} if self.noise_estimate is not None else {}),
            **({"neighbour_scatter": self.scatter.to_json()} if self.scatter is not None else {}),
            "folds": self.folds,
            "where": [r.to_json() for r in self.where.regions[:20]],
            "ranking": [c.to_json(self.ideal) for c in self.ranking], "verdict": self.verdict,
            "confounded_with": self.confounded_with, "shrink": self.shrink,
            "heldout_excess_before": self.heldout_excess_before,
            **({"heldout_left_out": {"rows": list(self.left_out),
                                     "why": "every model describing the other readings at the noise floor named "
                                            "them outliers: a sensor's gross errors, or an effect that no library "
                                            "law holds, confined to them; left out of every held-out score"}}
               if self.left_out else {}),
            "parameters_baseline": {n: self.baseline.value(n) for n in self.baseline.names if not n.startswith("load[")},
            "goodness_of_fit": self.baseline.goodness_of_fit(),
            "parameter_gap": self.parameter_gap,
            "rules": dataclasses.asdict(self.rules),
        }
        if self.decision.kind == "undecided":
            rec["candidates"] = list(self.decision.candidates)
            if self.decision.untested:
                rec["candidates_untested"] = {"models": list(self.decision.untested), "reason": text.untested(self)}
            if self.decision.shared:
                rec["candidates_share"] = {"families": list(self.decision.shared), "reason": text.shared(self)}
            if self.separation is not None:
                rec["separate_by"] = self.separation.to_json()
        if self.decision.unjudged:
            rec["widened_laws_not_judged"] = {"models": list(self.decision.unjudged), "reason": text.unjudged(self)}
        if blind := text.blind_spot(self):
            rec["blind_spot"] = blind
        if self.best_pair is not None:
            rec["best_pair"] = self.best_pair.to_json()
        if self.families is not None:
            rec["verdict_model"] = "magnetic_circuit"
            rec["families"] = [f.to_json() for f in self.families]
        if self.verdict_fit is not None and self.verdict_fit.effects:
            rec["verdict_params"] = {n: {"value": v, "std": s} for n, v, s in zip(
                self.verdict_fit.names, self.verdict_fit.values, self.verdict_fit.std) if not n.startswith("load[")}
        if self.force_check is not None:
            rec["force_check"] = self.force_check.to_json()
        if self.law is not None:
            rec["law"] = self.law.to_json(self.judge.clear(self.law))
        if self.grade is not None:
            rec["grade"] = self.grade.to_json()
        if self.signatures is not None:
            rec["signatures"] = [s.to_json(self.judge.clear(s)) for s in self.signatures]
        rec["steps"] = self.steps()
        if self.ceiling is not None:
            rec["discrepancy"] = self.ceiling.to_json()
        # what ambfit force needs to measure with either model
        rec["baseline_fit"] = {"model_state": self.baseline.model_state()}
        if self.verdict_fit is not None:
            rec["verdict_fit"] = {"model": self.verdict_fit.model, "model_state": self.verdict_fit.model_state()}
        if self.ceiling is not None:
            host = self.ceiling.host
            rec["discrepancy_fit"] = {"model": f"{host.model}+discrepancy",
                                      "model_state": host.model_state() | {"discrepancy": self.ceiling.fit.to_json()}}
        return stamp(rec, "diagnose")

    def steps(self) -> list[dict]:
        """How the verdict was reached, each step with its held-out shrink: the first effect, then the second of
        a pair; for a family whose law differs, the library's law (or pair), then the law widened by its
        signature."""
        by_name = {c.effect: c for c in self.ranking}
        if self.decision.kind != "named":
            return []
        if self.law is not None:
            # (a widened pair: its first law, the pair, then the pair widened)
            first = [{"model": self.law.law.families[0], "shrink": by_name[self.law.law.families[0]].shrink}] \
                if self.law.widens is not None and self.law.law.families[0] in by_name else []
            return first + [{"model": self.law.law.label, "shrink": self.law.law.shrink},
                            {"model": self.law.model, "shrink": self.law.shrink}]
        if self.families is not None:
            return [{"model": "magnetic_circuit", "shrink": self.shrink,
                     "families": [f.family for f in self.families if f.significant]}]
        parts = self.verdict.split("+")
        out = []
        for j in range(1, len(parts) + 1):
            c = by_name.get("+".join(parts[:j]))
            if c is not None:
                out.append({"model": c.effect, "shrink": c.shrink})
        return out

    def to_dataframe(self) -> pd.DataFrame:
        """The ranking as a table: effect, held-out excess after, shrink, in-sample mean z²."""
        return pd.DataFrame([{"effect": c.effect, "heldout_excess_after": c.after, "shrink": c.shrink,
                              "insample_mean_z2": float(np.mean(c.fit.residuals**2)), "converged": c.fit.converged}
                             for c in self.ranking])

    def __str__(self) -> str:
        from ambfit.diagnosis import text

        return text.summary(self)

    def __repr__(self) -> str:
        return f"Diagnosis(verdict={self.verdict!r}, shrink={self.shrink:.3f}, confounded_with={self.confounded_with})"

    def _repr_html_(self) -> str:
        from ambfit.diagnosis import text

        return text.html(self)
