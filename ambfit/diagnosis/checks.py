"""The diagnosis' checks of its verdict, as typed records: force measurement with each model, the best pair.

:func:`force_checks` is contract section 3's ``force_check``: each known load left out and predicted by the ideal
law, the verdict's model, the model that removes most (when it is not the verdict's law) and the discrepancy model
(:class:`ForceCheck`, one :class:`ModelForce` per model).  The discrepancy's ceiling is
:class:`ambfit.diagnosis.discrepancy.Ceiling`, the magnetic circuit's pieces
:class:`ambfit.diagnosis.circuit_families.CircuitFamily`.
"""

from __future__ import annotations

import dataclasses

from ambfit.diagnosis.scoring import step_budget
from ambfit.diagnosis.verdict import WIDENED

FIGURES = ("rms_rel", "max_rel", "rms_rel_mean", "model_error_rel")
"""A model's force errors relative to the known load: per-reading RMS and largest, RMS of each load's mean, and the
per-reading RMS beyond the readings' noise (:func:`ambfit.estimation.measure.force_check`)."""

COUNTS = ("n_loads", "n_not_converged", "noise_floor_rel")


@dataclasses.dataclass(frozen=True)
class ModelForce:
    """One model's leave-one-load-out force errors (relative to the known load), or why there are none.

    ``model`` is None for the ideal law (the record's key says it); a discrepancy model carries only
    :data:`FIGURES`."""

    model: str | None = None
    rms_rel: float | None = None
    max_rel: float | None = None
    rms_rel_mean: float | None = None
    model_error_rel: float | None = None
    n_loads: int | None = None
    n_not_converged: int | None = None
    noise_floor_rel: float | None = None
    error: str | None = None

    @classmethod
    def of(cls, model: str | None, figures: dict, counts: dict | None = None) -> ModelForce:
        """From :func:`ambfit.estimation.measure.force_check`'s figures (``counts``: where the loads' counts come
        from, when not from ``figures``)."""
        counts = figures if counts is None else counts
        return cls(model=model, **{k: figures[k] for k in FIGURES}, **{k: counts[k] for k in COUNTS})

    def to_json(self) -> dict:
        head = {} if self.model is None else {"model": self.model}
        if self.error is not None:
            return head | {"error": self.error}
        return head | {k: getattr(self, k) for k in FIGURES + COUNTS if getattr(self, k) is not None}


@dataclasses.dataclass(frozen=True)
class ForceCheck:
    """Each known load left out and predicted, per model (contract section 3's ``force_check``).

    ``error``: why no check was possible (the ideal law's refits failed)."""

    method: str = "leave-one-load-out"
    ideal: ModelForce | None = None
    verdict: ModelForce | None = None
    discrepancy: ModelForce | None = None
    best: ModelForce | None = None
    error: str | None = None

    def models(self) -> list[tuple[str, ModelForce]]:
        """``(key, record)`` of each model checked without error, in the record's order."""
        out = [(k, getattr(self, k)) for k in ("ideal", "verdict", "best", "discrepancy")]
        return [(k, m) for k, m in out if m is not None and m.error is None]

    def to_json(self) -> dict:
        if self.error is not None:
            return {"method": self.method, "error": self.error}
        out = {"method": self.method, "ideal": self.ideal.to_json()}
        for key in ("verdict", "discrepancy", "best"):
            if getattr(self, key) is not None:
                out[key] = getattr(self, key).to_json()
        return out


@dataclasses.dataclass(frozen=True)
class Pair:
    """The best pair of effects scored, and whether it explains the data (reported whether or not it is the
    verdict)."""

    effect: str
    heldout_excess_after: float
    shrink: float
    explains: bool

    def to_json(self) -> dict:
        return dataclasses.asdict(self)


def force_checks(df, base, verdict_fit, bearing, noise, discrepancy: bool = True, max_steps: int = 60,
                 fitted=None, each=None, best=None) -> ForceCheck | None:
    """Leave-one-load-out for the ideal law, the verdict's model and the discrepancy model (the verdict's model
    with the correction, or the ideal law's when the verdict has no effects), from the same refits.

    Each refit gets the step budget its model had in the diagnosis; a left-out load that is one of the diagnosis'
    folds reuses that fold's refit (``fitted``, by model name: :func:`fold_fits`).  ``each``: how each check's
    left-out loads are run (default one after the other).  ``best``: the model that removes most of the excess when
    it is not the verdict's law (a family's law widened by its signature, or the best law when nothing is the
    verdict): its check is reported as ``best``, so force measurement can judge it even when it does not reach the
    floor.  None when the data have fewer than two known loads."""
    from ambfit.estimation.core import FitError
    from ambfit.estimation.measure import force_check

    with_effects = verdict_fit is not None and bool(verdict_fit.effects)
    fitted = fitted or {}
    jobs = [((), base, discrepancy and not with_effects, max_steps, fitted.get(base.model, ()))]
    if with_effects:
        jobs.append((verdict_fit.effects, verdict_fit, discrepancy, step_budget(verdict_fit.effects, max_steps),
                     fitted.get(verdict_fit.model, ())))
    widened = best is not None and best.kind in WIDENED
    best_fit = best.law.fit if widened else best.fit if best is not None else None
    if best_fit is not None and best_fit.effects:
        jobs.append((best_fit.effects, best_fit, best.groups if widened else False,
                     step_budget(best_fit.effects, max_steps),
                     best.folds if widened else fitted.get(best_fit.model, ())))

    def check(job):
        effects, fitted_all, with_discrepancy, steps, folds_ = job
        try:
            return force_check(df, effects, bearing=bearing, base=fitted_all, discrepancy=with_discrepancy,
                               max_steps=steps, fitted=folds_, each=each, debias="none", **noise)
        except FitError as exc:
            return exc

    # one check after the other, each spreading its left-out loads over the threads
    ideal, *verdict = [check(job) for job in jobs]
    best_check = verdict.pop() if len(jobs) > 1 + with_effects else None
    if isinstance(ideal, FitError):
        return ForceCheck(error=str(ideal))
    if ideal is None:
        return None
    out = {"method": ideal["method"], "ideal": ModelForce.of(None, ideal)}
    if "discrepancy" in ideal:
        out["discrepancy"] = ModelForce(**ideal["discrepancy"])
    if verdict and isinstance(verdict[0], FitError):
        out["verdict"] = ModelForce(model=verdict_fit.model, error=str(verdict[0]))
    elif verdict and verdict[0] is not None:
        v = verdict[0]
        out["verdict"] = ModelForce.of(verdict_fit.model, v)
        if "discrepancy" in v:
            out["discrepancy"] = ModelForce(**v["discrepancy"])
    name = best.model if widened else best_fit.model if best_fit is not None else None
    if isinstance(best_check, FitError):
        out["best"] = ModelForce(model=name, error=str(best_check))
    elif best_check is not None:
        # a widened law's figures are those of the law with its signature's correction
        out["best"] = ModelForce.of(name, best_check["discrepancy"] if widened else best_check, best_check)
    return ForceCheck(**out)


def fold_fits(cands, ceiling) -> dict:
    """Each model's cross-validation refits as ``(held-out mask, fit, discrepancy or None)``, by the fit's model
    name: a force check whose left-out load is a fold reuses them (the same model, start and step budget)."""
    out = {c.fit.model: [(t, f, None) for t, f in c.folds] for c in cands}
    names = {c.effect: c.fit.model for c in cands}
    for effect, folds_ in (ceiling.folds if ceiling is not None else {}).items():
        out[names[effect]] = folds_
    return out
