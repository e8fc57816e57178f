"""The model-discrepancy term on held-out folds: what the library's laws leave.

Two uses in a diagnosis.  A family with a residual signature of its own (:data:`SIGNATURES`) may
follow a law other than the library's: that signature's group of the discrepancy basis
(:mod:`ambfit.estimation.discrepancy`) is fitted on the best candidate's residuals and judged by
its log Bayes factor and held-out shrink (:func:`_law_differs`).  And the whole discrepancy, added
to the ideal law and to the verdict's model on the same folds, gives the ceiling of what any
effect expressible in flux density, gap, the other axis and approach direction could explain
(:func:`_discrepancy`).
"""

from __future__ import annotations

import dataclasses
import functools

import numpy as np

from ambfit.data import load_groups
from ambfit.diagnosis.heldout import Candidate, excess, heldout_residuals, shrink
from ambfit.diagnosis.threads import _Each

SIGNATURES = {"hysteresis": "hysteresis", "cross_coupling": "coupling"}
"""Families with a residual signature of their own, and the discrepancy group that expresses it: hysteresis
makes the force depend on the direction from which each coil current was approached; cross-coupling on the
other axis' position and currents."""

LOG_BAYES_CLEAR = 10.0
"""A signature is clearly in the residuals when the marginal likelihood wants its discrepancy group by more
than this (log Bayes factor; above 5 is 'very strong' on Kass and Raftery's 1995 scale; the FEM bearing, with
no hysteresis, gives its direction group 3.3)."""


def _corrected_heldout(cand: Candidate, df, groups, noise) -> tuple[np.ndarray, list]:
    """Held-out residuals of ``cand``'s folds with the discrepancy (``groups``) fitted on the rows each fold's fit used,
    and the folds as ``(held-out mask, fit, discrepancy)``."""
    from ambfit.estimation.discrepancy import fit_discrepancy

    zs, folds_ = [], []
    loads = load_groups(df).to_numpy()
    for test, f in cand.folds:
        d = fit_discrepancy(f, df, groups=groups, **noise)          # on the rows the fold's fit used
        zs.append(heldout_residuals(dataclasses.replace(f, residuals=f.residuals + d.row_correction), df, test,
                                    loads))
        folds_.append((test, f, d))
    return np.concatenate(zs), folds_


def _law_differs(df, best: Candidate, before: float, noise) -> dict:
    """The best family's signature in its residuals and the held-out shrink of its law widened by it."""
    from ambfit.estimation.discrepancy import fit_discrepancy

    group = SIGNATURES[best.effect]
    full = fit_discrepancy(best.fit, df, groups=(group,), **noise)
    z, _ = _corrected_heldout(best, df, (group,), noise)
    after = excess(z)
    return {"family": best.effect, "signature": group, "log_bayes": full.log_bayes[group],
            "signature_clear": bool(full.log_bayes[group] > LOG_BAYES_CLEAR),
            "library_law_shrink": best.shrink, "library_law_leaves": 1.0 - best.shrink,
            "heldout_excess_after": after, "shrink": shrink(before, after),
            "widened_by": f"the discrepancy's '{group}' terms (orthogonal to gap, origin, k and the law's parameters)",
            "largest_terms": full.largest(3)}


def _discrepancy(df, ideal: Candidate, verdict: Candidate | None, before: float, noise, progress=None,
                 each=None) -> dict:
    """The discrepancy's held-out shrink on the ideal law (the ceiling) and on the verdict's model, and the
    correction fitted on every row of the verdict's model (the ideal law's when there is none).  ``each``: how
    the independent pieces are run (:class:`_Each`; default one after the other)."""
    from ambfit.estimation.discrepancy import GROUPS, fit_discrepancy

    out = {"groups": list(GROUPS)}
    host = verdict if verdict is not None and verdict.fit.effects else ideal
    models = [ideal] if host is ideal else [ideal, host]
    # each model's folds corrected, and the correction on every row
    tasks = ([functools.partial(_corrected_heldout, c, df, GROUPS, noise) for c in models]
             + [functools.partial(fit_discrepancy, c.fit, df, **noise) for c in models])
    done = (each or _Each(1))(lambda task: task(), tasks)
    corrected, fits = done[:len(models)], {c.effect: d for c, d in zip(models, done[len(models):])}
    (z, ideal_folds) = corrected[0]
    z_in = ideal.fit.residuals
    kept = ideal.fit.fitted_rows
    # in sample (every row fitted): what is left of the ideal law's excess once the correction is added
    out["ideal"] = {"heldout_excess_after": excess(z), "shrink": shrink(before, excess(z)),
                    "insample_shrink": shrink(excess(z_in[kept]), excess((z_in + fits[ideal.effect].row_correction)[kept]))}
    out["folds"] = {ideal.effect: ideal_folds}
    if host is not ideal:
        z, out["folds"][host.effect] = corrected[1]
        out["verdict"] = {"model": host.effect, "heldout_excess_after": excess(z), "shrink": shrink(before, excess(z))}
    out["fit"] = fits[host.effect]
    out["host"] = host.fit
    out["fitted_on"] = host.effect
    if progress is not None:
        progress("discrepancy", 1, 1)
    return out
