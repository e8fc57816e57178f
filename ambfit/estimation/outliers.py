"""Outliers: the test that names readings a fit cannot explain, and the robust losses' reweighting.

:func:`screening` runs after every least-squares fit (:func:`ambfit.estimation.fit.fit_many`).  ``auto`` judges each
reading's studentized residual against a Bonferroni bound (false-alarm probability ``alpha`` per data set) on a fit
the outliers cannot drag (Cauchy reweighting), leaves the outliers out and refits until no new reading is beyond the
bound; ``huber``/``cauchy`` reweight by their loss (:mod:`ambfit.estimation.robust`).

Both refit as they go.  :func:`screening` yields each refit it needs (a :class:`Refit`) and each set of studentized
residuals (a :class:`Studentize`), and is sent the result, so that the data sets of a study screen in lockstep,
each round's refits solved as one batch and its residuals measured as one (:func:`run_screens`).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Generator
from typing import NamedTuple

import numpy as np
import pandas as pd

from ambfit.data import load_groups
from ambfit.estimation import robust
from ambfit.estimation.core import K_REFERENCE, Meta, Model, Problem, row_jacobian
from ambfit.estimation.results import FitResult
from ambfit.estimation.units import HEAD


def _studentized(res: FitResult, prob: Problem, meta: Meta, model: Model) -> np.ndarray:
    """Studentized residuals of every row at ``res`` (fit weights from ``prob.mask``)."""
    # measured with the solve (same theta, same model)
    jac = res.jacobian_rows if res.jacobian_rows is not None else row_jacobian(res.theta, prob, meta, model)
    w = np.asarray(prob.mask) ** 2
    return robust.studentized(jac, res.residuals, w > 0, w, known_noise=not meta.noise_estimated)


class Refit(NamedTuple):
    """A refit :func:`screening` asks for: ``prob`` (other row weights) from the result ``start``."""

    prob: Problem
    start: FitResult


class Studentize(NamedTuple):
    """Studentized residuals :func:`screening` asks for: every row's at ``res`` (which holds the solve's row
    Jacobian), with the fit weights of ``prob.mask`` and the noise ``known`` or estimated from the residuals."""

    res: FitResult
    prob: Problem
    known: bool


Screening = Generator[Refit | Studentize, FitResult | np.ndarray, FitResult]
"""A screen under way: it yields refits and studentized residuals, is sent them (or thrown the error their
measurement raised) and returns the screened result."""


def _studentize(res: FitResult, prob: Problem, meta: Meta, model: Model) -> Generator[Studentize, np.ndarray, np.ndarray]:
    """:func:`_studentized`, asked of :func:`run_screens` (which measures a round's together) when ``res`` holds the
    solve's row Jacobian."""
    if res.jacobian_rows is None:
        return _studentized(res, prob, meta, model)
    return (yield Studentize(res, prob, not meta.noise_estimated))


def _studentized_all(asked: dict) -> dict:
    """Each :class:`Studentize` of ``asked`` measured, those of one shape and noise source at once (stacked: each
    the same as measured alone).  A group that fails is measured one by one, and a screen whose own measurement
    fails is given the error (thrown into it, as if it had measured alone)."""
    def measured(keys, known):
        return robust.studentized_many(np.stack([asked[k].res.jacobian_rows for k in keys]),
                                       np.stack([asked[k].res.residuals for k in keys]),
                                       np.stack([np.asarray(asked[k].prob.mask, dtype=float) ** 2 for k in keys]),
                                       known_noise=known)

    out, groups = {}, {}
    for key, r in asked.items():
        groups.setdefault((np.shape(r.res.jacobian_rows), r.known), []).append(key)
    for (_, known), keys in groups.items():
        try:
            out.update(zip(keys, measured(keys, known)))
        except ValueError:                  # (numpy's LinAlgError among them)
            for k in keys:
                try:
                    out[k] = measured([k], known)[0]
                except ValueError as exc:
                    out[k] = exc
    return out


def _reweighted(res, prob, meta, model, loss, base) -> Generator[Refit | Studentize, FitResult | np.ndarray, tuple]:
    """Iteratively reweighted least squares with the robust ``loss`` from ``res``: ``(result, weights)``."""
    w = base.copy()
    for _ in range(robust.MAX_ROUNDS):
        t = yield from _studentize(res, prob.with_mask(np.sqrt(w)), meta, model)
        new = base * robust.weights(t, loss)
        if np.max(np.abs(new - w)) < 1e-3:
            break
        w = new
        res = yield Refit(prob.with_mask(np.sqrt(w)), res)
    return res, w


def run_screens(screens: dict, refit_all: Callable[[dict], list], errors: tuple = ()) -> dict:
    """Every screen of ``screens`` (key: generator, e.g. :func:`screening`) to its end, what they ask for in rounds:
    ``refit_all({key: Refit})`` fits the refits asked for in one round and returns their results in that order (a
    result may be the exception its fit raised: thrown into its screen); the studentized residuals asked for are
    measured together.  Returns ``{key: result}``, or the exception of ``errors`` a screen raised in its place."""
    out, asked = {}, {}

    def advance(key, gen, value=None):
        try:
            asked[key] = gen.throw(value) if isinstance(value, BaseException) else gen.send(value)
        except StopIteration as stop:
            out[key] = stop.value
        except errors as exc:
            out[key] = exc

    for key, gen in screens.items():
        advance(key, gen)
    while asked:
        now, asked = asked, {}
        refits = {k: r for k, r in now.items() if isinstance(r, Refit)}
        done = dict(zip(refits, refit_all(refits), strict=True)) if refits else {}
        done.update(_studentized_all({k: r for k, r in now.items() if isinstance(r, Studentize)}))
        for key in now:
            advance(key, screens[key], done[key])
    return out


def screening(res: FitResult, prob: Problem, meta: Meta, df: pd.DataFrame, model: Model, loss: str, alpha: float,
              rows: np.ndarray, t: np.ndarray | None = None) -> Screening:
    """The outlier test (``auto``, ``linear``) or the robust loss's reweighting, starting from the plain fit ``res``
    (a generator of the refits and residuals it needs, see :data:`Screening`); ``rows`` is the file row of each row of ``df``; ``t``: the
    studentized residuals of ``res`` when already measured (:func:`studentized`).

    The test judges each reading against a fit the outliers cannot drag (Cauchy reweighting; one reading 17 σ
    off pulls plain least squares so far that its neighbours look off too), then leaves the outliers out and
    refits by plain least squares, repeating until no new reading is beyond the bound.
    """
    base = np.asarray(prob.mask, dtype=float)
    if not np.all(np.isfinite(res.residuals[base > 0])):
        return res
    # (a plain fit dragged by gross outliers may not converge within its step budget; the robust rounds start
    # from it and are judged by their own convergence)
    plain = res
    if loss in ("huber", "cauchy"):
        res, w = yield from _reweighted(res, prob, meta, model, loss, base)
        return dataclasses.replace(res, loss=loss, weights=w, rows=rows, plain_shift=_shift(plain, res))
    if alpha <= 0:                                     # no outlier test
        return dataclasses.replace(res, loss=loss, rows=rows, weights=base)
    fitted = base > 0
    limit = robust.threshold(int(fitted.sum()), alpha, meta.noise_estimated)
    if t is None:
        t = yield from _studentize(res, prob, meta, model)
    if not np.any(np.abs(t[fitted]) > limit):
        return dataclasses.replace(res, loss=loss, rows=rows, weights=base)          # clean: plain least squares
    anchor, _ = yield from _reweighted(res, prob, meta, model, "cauchy", base)
    out = (np.abs((yield from _studentize(anchor, prob.with_mask(base), meta, model))) > limit) & fitted
    cur = prob
    for _ in range(robust.MAX_ROUNDS):
        if out.sum() > robust.MAX_FRACTION * fitted.sum():
            return dataclasses.replace(plain, loss=loss, rows=rows, weights=base, outlier_note=(
                f"{int(out.sum())} readings lie beyond the outlier bound |t| > {limit:.2f}: more than "
                f"{robust.MAX_FRACTION:.0%} of the data, so not a few bad readings but a model that does not fit "
                "them (none was left out); run ambfit diagnose"))
        if loss == "linear" or not out.any():
            break
        cur = prob.with_mask(base * ~out)
        res = yield Refit(cur, res)
        # judged again against the fit without them (a left-out reading is tested as a prediction)
        new = (np.abs((yield from _studentize(res, cur, meta, model))) > limit) & fitted
        if np.array_equal(new, out):
            break
        out = new
    if loss == "linear":
        res, cur = plain, prob
    t = yield from _studentize(res, cur, meta, model)
    found = tuple(_outlier(j, t[j], df, res, prob, rows) for j in np.nonzero(out)[0])
    return dataclasses.replace(res, loss=loss, rows=rows, weights=np.asarray(cur.mask) ** 2, outliers=found,
                               plain_shift=_shift(plain, res) if found and loss == "auto" else None)


def _shift(plain: FitResult, res: FitResult) -> dict:
    """How far plain least squares sits from ``res``, per head parameter, in ``res``'s standard errors."""
    return {n: (plain.value(n) - res.value(n)) / res.error(n) for n in HEAD
            if n in res.names and n in plain.names and res.error(n) > 0}


def _outlier(j: int, t: float, df: pd.DataFrame, res: FitResult, prob: Problem, rows) -> robust.Outlier:
    """The record of row ``j`` (0-based in ``df``): its reading and the values that would make it fit."""
    r = df.iloc[j]
    ax = str(r["axis"])
    own = f"{ax}_um"
    reading = {"i_top_A": float(r["i_top_A"]), "i_bottom_A": float(r["i_bottom_A"]), own: float(r[own])}
    if "load_N" in df.columns and np.isfinite(r["load_N"]):
        reading["load_N"] = float(r["load_N"])
    vals = dict(zip(res.names, res.values))
    g0, x0 = vals.get(f"g_{ax}0", np.nan), vals.get(f"{ax}0", 0.0)
    k = vals.get(f"k_{ax}", K_REFERENCE)
    load = float(np.asarray(prob.load)[j]) if bool(np.asarray(prob.known)[j]) else \
        vals.get(f"load[{load_groups(df).iloc[j]}]", np.nan)
    alt = {}
    if np.isfinite(g0) and np.isfinite(load):
        alt = robust.fits_with(reading["i_top_A"], reading["i_bottom_A"], reading[own] * 1e-6, load, g0, x0, k,
                               res.bearing.cos_alpha)
        if "x_um" in alt:
            alt[own] = alt.pop("x_um")
    return robust.Outlier(row=int(rows[j]), axis=ax, t=float(t), reading=reading, fits_with=alt)


def studentized(results: list[FitResult], probs: list[Problem], metas: list[Meta]) -> list[np.ndarray | None]:
    """The studentized residuals of many fits (each at its own row weights, with the solve's row Jacobian), measured
    together where the fits are alike (:func:`_studentized_all`); None for a fit whose own cannot be measured (its
    screen measures them again and says why)."""
    done = _studentized_all({s: Studentize(res, prob, not meta.noise_estimated)
                             for s, (res, prob, meta) in enumerate(zip(results, probs, metas))})
    return [None if isinstance(done[s], BaseException) else done[s] for s in range(len(results))]
