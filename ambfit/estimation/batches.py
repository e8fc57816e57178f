"""Many data sets' solves: the schedule every fit runs, and the buckets and padding that let one vmapped program
solve thousands of data sets.

:func:`solve_sets` is the schedule of :func:`ambfit.estimation.fit.fit_many`: a first budget of steps, then more
for the data sets not yet converged.  A data set alone is solved at its own shape (:func:`ambfit.estimation.lm.solve`);
several are padded to a few bucket shapes (:func:`pad`) and solved by one vmapped program per bucket, so a study of
thousands of data sets compiles a handful of programs.
"""

from __future__ import annotations

import functools
from collections.abc import Sequence

import equinox as eqx
import jax
import numpy as np

from ambfit.estimation.core import IDEAL, Model, Problem
from ambfit.estimation.lm import EDM_ROUND, FIRST_STEPS, REWEIGHTINGS, RTOL, Solution, solve, succeeded

ROW_BUCKET_MIN = 16
"""Shortest padded length; longer data sets are padded to the next power of two (16, 32, 64, 128, ... rows).
Every bucket is a compilation while the padded solve itself is cheap, so few coarse buckets beat tight padding."""

BATCH = 64
"""Data sets per vmapped solve: a bucket's data sets are solved 64 at a time, the last batch padded with copies,
so chunks of any size reuse one compiled shape per bucket."""

BATCH_AGAIN = 8
"""Data sets per vmapped later solve (the few that the first budget left short of convergence)."""


def row_bucket(n: int) -> int:
    """The padded length of a data set of ``n`` rows (see ``ROW_BUCKET_MIN``)."""
    return max(ROW_BUCKET_MIN, 1 << (int(n) - 1).bit_length())


def load_bucket(m: int) -> int:
    """The padded number of nuisance loads: 0, 1, 2, 4, 8, ..."""
    return 0 if m <= 0 else 1 << (int(m) - 1).bit_length()


_PAD_FILL = {".load": 0.0, ".known": True, ".gidx": -1, ".mask": 0.0, ".s_held": 0.0}
"""What a padded row holds, by field: no load, weight 0, no propagated noise; other fields repeat the first row."""


def pad(probs: Sequence[Problem], rows: int) -> Problem:
    """Problems stacked into one batch of ``rows`` rows each: padded rows repeat a data set's first row with weight 0
    and point at no load (zero residual, zero Jacobian row), so they cannot move an estimate."""
    paths, tree = jax.tree_util.tree_flatten_with_path(probs[0])
    names = [jax.tree_util.keystr(path) for path, _ in paths]
    leaves = [jax.tree_util.tree_leaves(p) for p in probs]
    lengths = np.array([len(np.asarray(p.mask)) for p in probs])
    j = np.arange(rows)
    real = j[None, :] < lengths[:, None]
    # each padded row's source in the data sets' rows one after another: its own row, or its data set's first
    source = (np.cumsum(lengths) - lengths)[:, None] + np.where(real, j[None, :], 0)
    out = []
    for i, name in enumerate(names):
        column = [np.asarray(ls[i]) for ls in leaves]
        if name.endswith(".k_free"):
            out.append(np.stack(column))
            continue
        stacked = np.concatenate(column)[source]
        fill = next((v for k, v in _PAD_FILL.items() if name.endswith(k)), None)
        out.append(stacked if fill is None else np.where(real, stacked, np.asarray(fill, dtype=stacked.dtype)))
    return jax.tree_util.tree_unflatten(tree, out)


@eqx.filter_jit
def _vmapped(theta0, probs, model, max_steps, settings) -> Solution:
    """:func:`solve` of a batch; the step budget and ``settings`` (reweightings, EDM stop and tolerance) as arrays:
    traced, one program for any values."""
    return jax.vmap(lambda t, p: solve(t, p, model, max_steps=max_steps, **settings))(theta0, probs)


def _text(ok: bool, result, b=None) -> str:
    return "successful" if ok else str(result if b is None else jax.tree.map(lambda a: a[b], result))


def _solve_batch(thetas: list[np.ndarray], probs: list[Problem], model: Model, max_steps: int, size: int, *,
                 reweightings: int = REWEIGHTINGS, edm_round: float = EDM_ROUND, rtol: float = RTOL) -> list[Solution]:
    """:func:`solve` of each problem: alone at its own shape, or padded to its bucket and vmapped ``size`` at a
    time (a smaller last batch padded to a power of two with copies of its first problem).  NumPy leaves,
    ``result`` as text."""
    settings = dict(reweightings=reweightings, edm_round=edm_round, rtol=rtol)
    if len(probs) == 1:
        sol = solve(np.asarray(thetas[0], dtype=float), probs[0], model, max_steps, **settings)
        return [sol._replace(result=_text(bool(succeeded(sol.result)), sol.result))]
    out: list = [None] * len(probs)
    for rows, loads, parts in _buckets(thetas, probs, model, size):
        order = [s for part, padded in parts for s in padded]
        stacked = pad([probs[s] for s in order], rows)          # every batch of the bucket at once
        starts = np.zeros((len(order), 6 + loads + model.n))
        for b, s in enumerate(order):
            starts[b, _columns(thetas[s], model, loads)] = thetas[s]
        ends = np.cumsum([len(padded) for _, padded in parts])
        for (part, padded), end in zip(parts, ends):
            batch = slice(end - len(padded), end)
            sol = _vmapped(starts[batch], jax.tree.map(lambda a, batch=batch: a[batch], stacked), model,
                           np.asarray(max_steps), {k: np.asarray(v) for k, v in settings.items()})
            ok = succeeded(sol.result)
            theta, steps, edm, jac, jac_all, z, s_eff = (np.asarray(a) for a in (
                sol.theta, sol.steps, sol.edm, sol.jac, sol.jac_all, sol.z, sol.s))
            for b, s in enumerate(part):
                nr, cols = len(np.asarray(probs[s].mask)), _columns(thetas[s], model, loads)
                if len(cols) == 6 + loads and not model.n:  # no padded loads nor priors: the data set's own block
                    cut = (slice(0, nr), slice(0, len(cols)))
                    th = theta[b, :len(cols)]
                else:
                    # rows: the data set's own, then the effect priors' (after the padded rows)
                    cut = np.ix_(np.r_[0:nr, rows:rows + model.n], cols)
                    th = theta[b, cols]
                out[s] = Solution(theta=th, result=_text(ok[b], sol.result, b), steps=steps[b], edm=edm[b],
                                  jac=jac[b][cut], jac_all=jac_all[b][cut], z=z[b, :nr], s=s_eff[b, :nr])
    return out


def _buckets(thetas, probs, model: Model, size: int):
    """The data sets grouped as a batched program takes them: per bucket ``(rows, loads, parts)``, its padded rows
    and nuisance loads (:func:`row_bucket`, :func:`load_bucket`) and its batches ``(members, padded)``, each at most
    ``size`` data sets, ``padded`` filled with copies of its first member up to ``size``, or for fewer members up to
    the next power of two (a few data sets are not solved ``size`` times over; a handful of batch shapes)."""
    # (rows, nuisance loads): a theta holds the six head entries, one per load, then the model's effect entries
    keys = [(row_bucket(len(np.asarray(p.mask))), load_bucket(len(t) - 6 - model.n)) for p, t in zip(probs, thetas)]
    for key in dict.fromkeys(keys):
        members = [s for s, k in enumerate(keys) if k == key]
        parts = [members[lo:lo + size] for lo in range(0, len(members), size)]
        yield key[0], key[1], [(part, part + [part[0]] * (min(size, 1 << (len(part) - 1).bit_length()) - len(part)))
                               for part in parts]


def _columns(theta, model: Model, loads: int) -> np.ndarray:
    """Where a data set's theta sits in its bucket's, whose ``loads`` nuisance loads follow the head: the head and
    its own loads, then the effect entries after the padded loads."""
    return placed_columns(len(theta) - model.n, model.n, loads)


@functools.lru_cache(maxsize=1024)
def placed_columns(own: int, n: int, loads: int) -> np.ndarray:
    """Where a theta of ``own`` head and load entries and ``n`` effect entries sits in a bucket's theta, whose
    ``loads`` nuisance loads follow the head (read-only: shared by every call with these sizes)."""
    cols = np.concatenate([np.arange(own), np.arange(6 + loads, 6 + loads + n)])
    cols.flags.writeable = False
    return cols


def solve_sets(thetas: Sequence[np.ndarray], probs: Sequence[Problem], model: Model = IDEAL,
               max_steps: int = 200, *, reweightings: int = REWEIGHTINGS, edm_round: float = EDM_ROUND,
               rtol: float = RTOL) -> list[Solution]:
    """Every problem's solve by the schedule of a fit: ``FIRST_STEPS`` per round for the ideal law from its
    closed-form or grid start (``max_steps`` for a model with effects, which start further away), then
    ``max_steps`` once more for the problems not converged (a model with effects: while its budget is not spent,
    since its effective-variance weights can move after the last round).  ``reweightings``, ``edm_round`` and
    ``rtol`` are :func:`ambfit.estimation.lm.solve`'s.  Returns one :class:`Solution` per problem (NumPy leaves,
    ``steps`` summed over the solves)."""
    settings = dict(reweightings=reweightings, edm_round=edm_round, rtol=rtol)
    first = max_steps if model.n else min(FIRST_STEPS, max_steps)
    out = _solve_batch(list(thetas), list(probs), model, first, BATCH, **settings)
    again = [s for s, sol in enumerate(out)
             if not sol.converged and (max_steps > first or (model.n and sol.steps < max_steps))]
    if again:
        more = _solve_batch([out[s].theta for s in again], [probs[s] for s in again], model, max_steps, BATCH_AGAIN,
                            **settings)
        for s, sol in zip(again, more):
            out[s] = sol._replace(steps=out[s].steps + sol.steps)
    return out


def precompile(rows: Sequence[int], loads: Sequence[int] = (0,), *, bearing=None, max_steps: int = 200) -> int:
    """Compile the vmapped solves of :func:`solve_sets` for data sets of these row counts and numbers of nuisance
    loads (both budgets' shapes of every bucket they fall in), so that a worker or a timed run does not pay it on
    its first batch.  Compilation depends only on the shapes, so a synthetic table stands in for the data.
    Returns the number of buckets compiled."""
    import pandas as pd

    from ambfit.estimation.core import K_REFERENCE, to_theta
    from ambfit.estimation.problem import build_problem
    from ambfit.physics.bearing import PAPER_BEARING

    bearing = PAPER_BEARING if bearing is None else bearing
    model = Model.of((), bearing)
    done = set()
    for n in rows:
        for m in loads:
            r = max(int(n), int(m), 1)              # (rows of one axis: a load group is a load_id and an axis)
            key = (row_bucket(r), load_bucket(m))
            if key in done:
                continue
            done.add(key)
            frame = pd.DataFrame({"axis": ["v"] * r, "bias_A": 1.5, "i_top_A": 1.6, "i_bottom_A": 1.4, "v_um": 0.0,
                                  "w_um": 0.0, "load_N": np.nan if m else 5.0,
                                  "load_id": [f"l{j % max(m, 1)}" for j in range(r)]})
            prob, meta = build_problem(frame)
            theta = to_theta(bearing.nominal_gap, 0.0, K_REFERENCE, np.zeros(len(meta.load_groups)))
            for steps, size in ((min(FIRST_STEPS, max_steps), BATCH), (max_steps, BATCH_AGAIN)):
                _solve_batch([theta] * size, [prob] * size, model, steps, size)      # (a full batch's shape)
    return len(done)


def bias_sets(thetas: Sequence[np.ndarray], probs: Sequence[Problem], model: Model, frees: Sequence[np.ndarray],
              covs: Sequence[np.ndarray], shares: Sequence = None) -> list[np.ndarray]:
    """The second-order bias of each estimate (:func:`ambfit.estimation.debias.second_order_biases`): ``thetas``
    scaled, ``frees`` the estimated entries, ``covs`` their scaled covariance [free, free], ``shares`` each one's
    noise variance per kind of reading relative to its problem's (default 1).  A data set alone runs at its own
    shape (in its solve's program within :func:`ambfit.estimation.debias.by_solve`); several are padded to their
    solve's buckets and run ``BATCH`` at a time.  Returns each bias (scaled, over the whole of its theta; 0 outside
    the free entries, not finite where it is not determined)."""
    from ambfit.estimation.debias import MAX_ROWS, bias_by_solve, second_order_biases

    probs, scales = list(probs), np.ones(len(probs))
    for s, prob in enumerate(probs):        # a long data set: an evenly spaced subset of its fitted rows
        used = np.nonzero(np.asarray(prob.mask) > 0)[0]
        if len(used) > MAX_ROWS:
            probs[s] = _rows(prob, used[np.linspace(0, len(used) - 1, MAX_ROWS).round().astype(int)])
            scales[s] = len(used) / MAX_ROWS

    def full(t, free, cov):
        c = np.zeros((len(t), len(t)))
        c[np.ix_(free, free)] = cov
        return c

    shares = np.ones((len(probs), 3)) if shares is None else np.asarray(shares, dtype=float)
    if len(probs) == 1:
        one = jax.tree.map(lambda a: np.asarray(a)[None], probs[0])
        whole = scales[0] == 1.0            # (a subset of a long data set's rows is not the shape its fit compiled)
        return [second_order_biases(np.asarray(thetas[0])[None], one, model, np.asarray(frees[0])[None],
                                    full(thetas[0], frees[0], covs[0])[None], shares[:1], scales[:1],
                                    via_solve=bias_by_solve() and whole)[0]]
    out: list = [None] * len(probs)
    for rows, loads, parts in _buckets(thetas, probs, model, BATCH):
        width = 6 + loads + model.n
        for part, order in parts:
            k = len(order)
            theta, free, cov = np.zeros((k, width)), np.zeros((k, width), bool), np.zeros((k, width, width))
            for b, s in enumerate(order):
                c = _columns(thetas[s], model, loads)
                theta[b, c], free[b, c] = thetas[s], frees[s]
                cov[b][np.ix_(c, c)] = full(thetas[s], frees[s], covs[s])
            bias = second_order_biases(theta, pad([probs[s] for s in order], rows), model, free, cov, shares[order],
                                       scales[order])
            for b, s in enumerate(part):
                out[s] = bias[b, _columns(thetas[s], model, loads)]
    return out


def measure_sets(thetas: Sequence[np.ndarray], probs: Sequence[Problem], model: Model = IDEAL) -> list[Solution]:
    """Each problem measured at ``thetas`` as a solve ends (weights, residuals and Jacobians there), without a step:
    the solve's own compiled programs with no step budget and no reweighting round."""
    return _solve_batch(list(thetas), list(probs), model, 0, BATCH, reweightings=0)


def _rows(prob: Problem, rows: np.ndarray) -> Problem:
    """The problem of these rows only (every field with one entry per row; the axes' fields stay)."""
    n = len(np.asarray(prob.mask))
    return jax.tree.map(lambda a: np.asarray(a)[rows] if np.ndim(a) and np.shape(a)[0] == n else a, prob)
