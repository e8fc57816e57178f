"""A family named by its signature, whatever its law: each library law widened by the variables its family acts through.

A family of unmodelled physics changes the force through variables of its own (drift: time and temperature;
hysteresis: the direction and path of each coil current; cross-coupling: the other axis; the flux families: flux
density and gap per coil; the sensors: their readings; :data:`ambfit.estimation.basis.FAMILY_GROUPS`).  When a
real bearing's law of that family differs from the library's, the library's law misses part of the structure,
but the law *widened by its signature* (the discrepancy's groups of those variables, orthogonal to every fitted
parameter: :mod:`ambfit.estimation.discrepancy`) reaches it.  Each family is scored so on the same held-out folds
as the laws: its held-out excess, and how clearly the data want its signature (the groups' log Bayes factor).
"""

from __future__ import annotations

import dataclasses

import numpy as np

from ambfit.diagnosis.heldout import Candidate, deviance, excess, predictive_variance, shrink


@dataclasses.dataclass(frozen=True)
class Signature:
    """One family's library law widened by its signature, scored on held-out folds.

    Attributes
    ----------
    law : Candidate
        The family's library law (its fit of every row and its folds).
    groups : tuple of str
        The discrepancy groups of the family's signature.
    log_bayes : dict
        Each group's log Bayes factor on the law's residuals of every reading with a finite one, the law's outliers
        among them (the rows the folds' corrections learn from; the law's parameters refitted to them, linearised).
    heldout_z : array
        Held-out standardized residuals of the widened law.
    folds : tuple
        ``(held-out mask, fit, discrepancy)`` per fold.
    full : Discrepancy
        The signature fitted on the rows the law's fit of every row used (its outliers left out): the saved
        correction, whose coefficients with the law's parameters reproduce it (``largest_terms`` of the record).
    heldout_var : array or None
        Each held-out reading's predictive variance (the law's parameters and the correction's coefficients).
    widens : str or None
        When ``law`` is a pair of laws, the family whose signature widens it (the other's law is the second effect);
        None for a single law.
    """

    law: Candidate
    groups: tuple
    log_bayes: dict
    heldout_z: np.ndarray
    folds: tuple
    full: object
    heldout_var: np.ndarray | None = None
    widens: str | None = None

    @property
    def kind(self) -> str:
        """``signature`` (a family's law widened), or ``widened_pair`` (one family of a pair widened, the other's
        library law beside it)."""
        return "signature" if self.widens is None else "widened_pair"

    @property
    def family(self) -> str:
        """The widened family."""
        return self.law.effect if self.widens is None else self.widens

    @property
    def families(self) -> tuple[str, ...]:
        return tuple(self.law.families)

    @property
    def second(self) -> str | None:
        """A widened pair's other family (None for a single law)."""
        return None if self.widens is None else next(f for f in self.law.families if f != self.widens)

    @property
    def model(self) -> str:
        text = f"{self.family} widened by its {'+'.join(self.groups)} signature"
        return text if self.widens is None else f"{text}, with {self.second}"

    label = model

    @property
    def heldout_deviance(self) -> np.ndarray:
        """Each held-out reading's ``z^2 + log(1 + h)`` (:func:`ambfit.diagnosis.heldout.deviance`)."""
        return deviance(self.heldout_z, self.heldout_var)

    @property
    def log_bayes_max(self) -> float:
        """How much the data want the signature: its groups' largest log Bayes factor."""
        return max(self.log_bayes.values(), default=0.0)

    @property
    def score(self) -> float:
        return float(np.mean(self.heldout_z**2))

    @property
    def after(self) -> float:
        return excess(self.heldout_z)

    @property
    def shrink(self) -> float:
        return shrink(self.law.before, self.after)

    def to_json(self, clear: bool) -> dict:
        """The record; ``clear``: whether the data clearly want the signature (:meth:`Judge.clear`).  A widened pair's
        names the other family (``with``) and the pair (``library_pair``), whose figures ``library_law_*`` are."""
        # (a widened pair: "library_law_*" are the library pair's, named by "library_pair")
        return {"family": self.family,
                **({"with": self.second, "library_pair": self.law.effect} if self.widens is not None else {}),
                "signature": "+".join(self.groups),
                "log_bayes": self.log_bayes_max, "log_bayes_groups": self.log_bayes,
                "signature_clear": clear, "heldout_excess_after": self.after, "shrink": self.shrink,
                "score": self.score, "library_law_shrink": self.law.shrink, "library_law_leaves": 1.0 - self.law.shrink,
                "library_law_excess_after": self.law.after,
                "widened_by": f"the discrepancy's {' and '.join(repr(g) for g in self.groups)} terms (orthogonal to "
                              "gap, origin, k and the law's parameters)",
                "largest_terms": self.full.largest(3)}


def widened(law: Candidate, df, groups, noise, *, wanted: bool = True, scored=None,
            widens: str | None = None) -> Signature:
    """``law`` widened by the discrepancy ``groups``: fitted on each fold's other rows (every reading with a finite
    residual, the law's outliers among them, its parameters refitted to them, linearised), scored on the fold; and
    on the rows the law's fit of every row used (``full``, the saved correction).  ``scored`` (bool per row, default
    every row): the readings that count, in the corrections and the scores (:func:`ambfit.diagnosis.heldout.
    gross_errors` leaves out those no model at the floor fits).  ``widens``: for a pair of laws, the family whose
    signature ``groups`` is.

    ``log_bayes`` (how much the data want the signature) is measured on the rows the folds' corrections learn from,
    the outliers too, so that it asks of the signature what the held-out test does; ``wanted=False`` skips that
    extra fit for a caller that does not read it (the discrepancy's ceiling) and reports ``full``'s."""
    from ambfit.data import load_groups
    from ambfit.diagnosis.heldout import heldout_residuals
    from ambfit.estimation.discrepancy import fit_discrepancy, seen_rows

    zs, vs, folds_ = [], [], []
    loads = load_groups(df).to_numpy()
    scored = np.ones(len(df), bool) if scored is None else np.asarray(scored, bool)
    for test, f in law.folds:
        d = fit_discrepancy(f, df, groups=groups, mask=seen_rows(f, ~test & scored), **noise)
        held = test & scored
        zs.append(heldout_residuals(dataclasses.replace(f, residuals=f.residuals + d.row_correction), df, held,
                                    loads))
        # the law's parameters and the correction's coefficients both widen the prediction
        vs.append(1.0 + predictive_variance(f, held) + d.row_variance[held])
        folds_.append((test, f, d))
    # on the rows the law's fit used: its saved correction is its law's parameters and these coefficients alone
    # (a law whose fit kept the left-out readings in, one that did not converge or misfits the bulk, without them)
    n = len(df)
    own = np.asarray(law.fit.row_weights[:n], dtype=float)
    full = fit_discrepancy(law.fit, df, groups=groups, mask=None if not np.any(own[~scored] > 0)
                           else np.sqrt(own) * scored, **noise)
    seen = seen_rows(law.fit, scored).astype(float)
    if wanted and not np.allclose(seen, law.fit.row_weights[:n]):
        # the law's outliers are where another law departs from it most (a play hysteresis' widest loops)
        log_bayes = fit_discrepancy(law.fit, df, groups=groups, mask=seen, **noise).log_bayes
    else:
        log_bayes = full.log_bayes
    var = np.concatenate(vs)
    return Signature(law=law, groups=tuple(groups), log_bayes=log_bayes, heldout_z=np.concatenate(zs),
                     folds=tuple(folds_), full=full, heldout_var=var, widens=widens)

