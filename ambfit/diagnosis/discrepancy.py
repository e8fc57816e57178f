"""The model-discrepancy term on held-out folds: the ceiling of what any smooth effect could explain.

The whole discrepancy (:mod:`ambfit.estimation.discrepancy`), added to the ideal law and to the verdict's model on
the same folds, gives the ceiling of what any effect expressible in flux density, gap, the other axis and approach
direction could explain (:func:`_discrepancy`).  A family's own groups of it are its signature
(:mod:`ambfit.diagnosis.signatures`).
"""

from __future__ import annotations

import functools

from ambfit.diagnosis.heldout import Candidate, excess, shrink
from ambfit.diagnosis.signatures import widened
from ambfit.diagnosis.threads import _Each


def _discrepancy(df, ideal: Candidate, verdict: Candidate | None, before: float, noise, progress=None,
                 each=None) -> dict:
    """The discrepancy's held-out shrink on the ideal law (the ceiling) and on the verdict's model, and the
    correction fitted on every row of the verdict's model (the ideal law's when there is none).  ``each``: how
    the independent pieces are run (:class:`_Each`; default one after the other)."""
    from ambfit.estimation.basis import GROUPS

    out = {"groups": list(GROUPS)}
    host = verdict if verdict is not None and verdict.fit.effects else ideal
    models = [ideal] if host is ideal else [ideal, host]
    done = (each or _Each(1))(lambda task: task(), [functools.partial(widened, c, df, GROUPS, noise) for c in models])
    wide = {c.effect: w for c, w in zip(models, done)}
    z_in = ideal.fit.residuals
    kept = ideal.fit.fitted_rows
    w = wide[ideal.effect]
    # in sample (every row fitted): what is left of the ideal law's excess once the correction is added
    out["ideal"] = {"heldout_excess_after": w.after, "shrink": shrink(before, w.after),
                    "insample_shrink": shrink(excess(z_in[kept]), excess((z_in + w.full.row_correction)[kept]))}
    out["folds"] = {c.effect: wide[c.effect].folds for c in models}
    if host is not ideal:
        w = wide[host.effect]
        out["verdict"] = {"model": host.effect, "heldout_excess_after": w.after, "shrink": shrink(before, w.after)}
    out["fit"] = wide[host.effect].full
    out["host"] = host.fit
    out["fitted_on"] = host.effect
    if progress is not None:
        progress("discrepancy", 1, 1)
    return out
