"""The diagnosis' first stage: every model fitted to every row, then with each fold held out and scored on it.

:class:`Scorer` holds what the scores of one data set share (the table, its folds and load groups, the noise, the
bearing, the step budget, the threads) and turns models into typed records: :meth:`Scorer.laws` library laws and
pairs of them (:class:`~ambfit.diagnosis.heldout.Candidate`), :meth:`Scorer.signatures` each family's law widened
by its signature and :meth:`Scorer.widened_pairs` each pair with one of its laws so widened
(:class:`~ambfit.diagnosis.signatures.Signature`).  Deciding among them is
:func:`ambfit.diagnosis.verdict.decide`'s.

A model's fold refits are single fits started from its fit of every row, two at a time on threads (each compiled
solve releases the interpreter): one compiled solve at the data's own shape serves every model and fold.  Solving
a model's folds as one vmapped batch (:func:`ambfit.estimation.fit.fit_many` over fold masks) pads them to the
batches of a study (64 sets, rows to the next power of two) and compiles a program per model; on this work it is
the slower route (``benchmarks/diagnose_speed.py`` measures both).
"""

from __future__ import annotations

import dataclasses
import functools

import numpy as np
import pandas as pd

from ambfit.data import load_groups
from ambfit.diagnosis.heldout import Candidate, excess, folds, heldout_residuals, predictive_variance
from ambfit.diagnosis.signatures import Signature, widened
from ambfit.diagnosis.threads import _Each
from ambfit.estimation.fit import fit
from ambfit.estimation.results import FitResult
from ambfit.physics.bearing import Bearing


def step_budget(effects, max_steps: int) -> int:
    """Levenberg-Marquardt steps per round for a model's fits: a circuit of the whole bearing starts further from
    the ideal law and gets at least the default budget of :func:`ambfit.fit` (200)."""
    return max(max_steps, 200) if any(getattr(e, "needs_other_axis", False) for e in effects) else max_steps


class Scorer:
    """Held-out scores of models on one data set.

    Parameters
    ----------
    df : DataFrame
        The contract table (the diagnosis' own copy, indexed from 0).
    base : FitResult
        The ideal law fitted to every row (every model's fit of every row starts from it).
    bearing : Bearing
    noise : dict
        ``sigma_i`` / ``sigma_x`` as :func:`ambfit.fit` takes them.
    max_steps : int
        Step budget of each candidate fit (:func:`step_budget`).
    each : _Each
        How independent fits run (threads).
    progress : callable, optional
        ``progress("candidate effects", done, total)`` after each model's folds.
    scheme : {"regions", "time"}
        The cross-validation folds (:func:`ambfit.diagnosis.heldout.folds`).
    """

    def __init__(self, df: pd.DataFrame, base: FitResult, *, bearing: Bearing, noise: dict, max_steps: int,
                 each: _Each, progress=None, scheme: str = "regions"):
        self.df, self.base, self.bearing, self.noise = df, base, bearing, noise
        self.max_steps, self.each, self.progress = max_steps, each, progress
        self.fold_name, self.tests = folds(df, scheme)
        self.groups = load_groups(df).to_numpy()
        self.scored = np.ones(len(df), bool)
        self.done = self.total = 0

    def leave_out(self, rows: np.ndarray, models: list[Candidate]) -> list[Candidate]:
        """Every later score without ``rows`` (bool per row, :func:`ambfit.diagnosis.heldout.gross_errors`), and
        ``models`` scored again on their folds' other held-out readings, from the fold fits they hold (a model whose
        fit of every row named these rows outliers left them out of its fold refits; one that kept them, not at the
        floor, learnt from them there)."""
        self.scored = ~np.asarray(rows, bool)
        return [dataclasses.replace(c, **self._scores(c.folds)) for c in models]

    def _scores(self, fitted) -> dict:
        """Held-out residuals and predictive variances of ``fitted`` (``(test mask, fit)`` per fold) on the scored
        rows of each fold, pooled."""
        tests = [(test & self.scored, f) for test, f in fitted]
        return {"heldout_z": np.concatenate([heldout_residuals(f, self.df, test, self.groups) for test, f in tests]),
                "heldout_var": np.concatenate([1.0 + predictive_variance(f, test) for test, f in tests])}

    def expect(self, models: int) -> None:
        """Announce ``models`` more models to the progress count."""
        self.total += models

    def laws(self, effect_sets: list, before: float | None = None) -> list[Candidate]:
        """Each model (a tuple of effects; ``()`` the ideal law, whose fit of every row is ``base``) fitted to every
        row, then with each fold held out and scored on it.  ``before``: the ideal law's held-out excess (None
        when ``effect_sets[0]`` is the ideal law: its own excess)."""
        steps = [step_budget(effects, self.max_steps) for effects in effect_sets]
        full: list = [None] * len(effect_sets)

        def refit(k, test):
            # the readings the model's fit of every row named outliers are left out of every fold, which is not
            # tested again (alpha=0): one outlier test per model, not one per fold, whose Cauchy-weighted anchor
            # would cost a solve per fold of a misfitting candidate only to conclude that it does not fit
            return fit(self.df, effect_sets[k], bearing=self.bearing, mask=(~test & full[k].fitted_rows).astype(float),
                       start_from=full[k], max_steps=steps[k], throw=False, alpha=0.0, debias="none",
                       **self.noise)

        def fit_all(k):
            full[k] = self.base if not effect_sets[k] else fit(
                self.df, effect_sets[k], bearing=self.bearing, start_from=self.base, max_steps=steps[k], throw=False,
                debias="none", **self.noise)

        def fit_all_then_folds(k):
            fit_all(k)
            return [self.each.submit(refit, k, test) for test in self.tests]   # its folds as soon as it is fitted

        # the first model's first refit runs on this thread: a solve not yet compiled (a diagnosis given its
        # baseline) is then compiled once, not by two threads at the same time
        fit_all(0)
        first = refit(0, self.tests[0])
        queued = [[self.each.submit(refit, 0, test) for test in self.tests[1:]]]
        heads = [self.each.submit(fit_all_then_folds, k) for k in range(1, len(effect_sets))]
        queued += [h.result() for h in heads]
        out = []
        for k, effects in enumerate(effect_sets):
            fitted = [first] + [f.result() for f in queued[0]] if k == 0 else [f.result() for f in queued[k]]
            scores = self._scores(tuple(zip(self.tests, fitted)))
            kind = "ideal" if not effects else "pair" if len(effects) > 1 else "law"
            out.append(Candidate("+".join(type(e).name for e in effects) or "ideal", scores["heldout_z"],
                                 excess(scores["heldout_z"]) if before is None else before, full[k],
                                 tuple(zip(self.tests, fitted)), kind=kind, heldout_var=scores["heldout_var"]))
            self.done += 1
            if self.progress is not None:
                self.progress("candidate effects", self.done, self.total)
        return out

    def signatures(self, laws: list[Candidate]) -> list[Signature]:
        """Every family's library law (``laws``: single-effect candidates) widened by its signature, best first."""
        from ambfit.estimation.basis import FAMILY_GROUPS

        own = [c for c in laws if c.effect in FAMILY_GROUPS and c.folds]
        tasks = [functools.partial(widened, c, self.df, FAMILY_GROUPS[c.effect], self.noise, scored=self.scored)
                 for c in own]
        return sorted(self.each(lambda task: task(), tasks), key=lambda s: s.score)

    def widened_pairs(self, pairs: list[Candidate]) -> list[Signature]:
        """Each pair of laws widened by each of its families' signatures in turn (a family whose law differs from
        the library's, beside a second effect the library's law describes; once when both share one), best
        first."""
        from ambfit.estimation.basis import FAMILY_GROUPS

        # (a pair of two families of one signature is widened once: by the first's, the same terms)
        todo = {(c.effect, FAMILY_GROUPS[f]): (c, f) for c in pairs if c.folds for f in reversed(c.families)
                if f in FAMILY_GROUPS}
        tasks = [functools.partial(widened, c, self.df, FAMILY_GROUPS[f], self.noise, scored=self.scored, widens=f)
                 for c, f in todo.values()]
        return sorted(self.each(lambda task: task(), tasks), key=lambda s: s.score)
