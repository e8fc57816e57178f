"""Where a fit starts: the closed form (Eq. 7) over each data set's position/bias pairs, a grid where an axis has
none, and ``k`` and the nuisance loads profiled at that gap and origin (:func:`ambfit.estimation.profile.profile`).

Vectorised over data sets: a study's thousands of data sets arrive as one joined table and get their starts in
one pass.  Never the truth: a start only has to lie in the basin of the least-squares minimum.
"""

from __future__ import annotations

from collections.abc import Sequence

import jax
import numpy as np
import pandas as pd

from ambfit.data import group_labels, joint_codes
from ambfit.estimation.closed_form.equations import eq6, eq7, position_labels
from ambfit.estimation.core import K_REFERENCE, SCALE_HEAD, SCALE_LOAD
from ambfit.estimation.problem import Meta, Problem
from ambfit.estimation.profile import profile
from ambfit.physics.bearing import AXES, PAPER_BEARING, Bearing
from ambfit.physics.model import ideal_force, pole_gaps


def design_pairs(df: pd.DataFrame) -> list[tuple[int, np.ndarray]]:
    """Eq. 6-7 groups of a design: ``(axis, rows[2 positions, 2 biases])`` per iteration (row positions in ``df``).

    Only iterations (``experiment``, ``iteration``, axis) with exactly two positions and two biases, one row
    each, are used.  Positions are grouped by :func:`~ambfit.estimation.closed_form.equations.position_labels`
    (set-points or measured positions, within ``POSITION_TOLERANCE``).  Vectorised over every iteration of the
    table.
    """
    n = len(df)
    if n == 0:
        return []
    keys = [group_labels(df["experiment"]) if "experiment" in df else None,
            df["iteration"] if "iteration" in df else None, df["axis"]]
    code = joint_codes(*(k for k in keys if k is not None))      # a missing label: in no group
    n_groups = int(code.max(initial=-1)) + 1
    if n_groups == 0:
        return []
    code = np.where(code >= 0, code, n_groups)        # rows of no group (a missing key) in a dummy group
    axis = df["axis"].to_numpy()
    label = position_labels(df, code)
    size = np.bincount(code, minlength=n_groups + 1)
    bias = df["bias_A"].to_numpy(float)
    lo = np.full(n_groups + 1, np.inf)
    hi = np.full(n_groups + 1, -np.inf)
    np.minimum.at(lo, code, bias)
    np.maximum.at(hi, code, bias)
    two = (bias == lo[code]) | (bias == hi[code])
    combo = label * 2 + (bias == hi[code])
    seen = np.zeros((n_groups + 1, 4), dtype=int)
    fine = two & (label <= 1)
    np.add.at(seen, (code[fine], combo[fine]), 1)
    bad = np.bincount(code, weights=~fine, minlength=n_groups + 1) > 0
    valid = (size == 4) & (lo < hi) & ~bad & np.all(seen == 1, axis=1)
    valid[n_groups] = False
    rows = np.zeros((n_groups + 1, 2, 2), dtype=int)
    idx = np.nonzero(valid[code])[0]
    rows[code[idx], label[idx], (bias[idx] == hi[code[idx]]).astype(int)] = idx
    first_axis = np.empty(n_groups + 1, dtype=object)
    first_axis[code[::-1]] = axis[::-1]
    return [(AXES.index(first_axis[g]), rows[g]) for g in np.nonzero(valid)[0]]


def pair_estimates(it, ib, x, rows: np.ndarray, cos_alpha) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Eq. 6-7 of every position/bias pair: gap and origin [m] and whether the solution is usable (finite, a
    positive gap and no pole gap closed at either position, as :func:`ambfit.estimation.closed_form.solve` asks).

    ``it``, ``ib``, ``x``: arrays[rows]; ``rows``: array[pairs, 2 positions, 2 biases] of row indices;
    ``cos_alpha``: float or array[pairs].
    """
    rows = np.asarray(rows, dtype=int).reshape(-1, 2, 2)
    p = eq6(it[rows[:, :, 0]], ib[rows[:, :, 0]], it[rows[:, :, 1]], ib[rows[:, :, 1]])   # [pairs, 2 positions]
    pos = 0.5 * (x[rows[:, :, 0]] + x[rows[:, :, 1]])
    c = np.broadcast_to(np.asarray(cos_alpha, dtype=float), (len(rows),))
    g0, x0 = eq7(p, pos, c)
    with np.errstate(invalid="ignore"):
        ok = np.isfinite(g0) & np.isfinite(x0) & (g0 > 0)
        ok &= np.all(np.abs((x0[:, None] + pos) * c[:, None]) < g0[:, None], axis=1)
    return g0, x0, ok


def grid_start(prob: Problem, axis: int, bearing: Bearing = PAPER_BEARING) -> tuple[float, float]:
    """Best ``(gap, origin)`` of a coarse grid (gap 0.5-1.5 x nominal, origin ±0.3 x nominal) by the relative spread
    of the profiled force: of each known load about ``k u``, of each load group about its mean."""
    nominal = bearing.nominal_gap
    gs = np.linspace(0.5, 1.5, 41) * nominal
    xs = np.linspace(-0.3, 0.3, 61) * nominal
    sel = (np.asarray(prob.ax) == axis) & (np.asarray(prob.mask) > 0)
    it, ib, x = (np.asarray(v)[sel] for v in (prob.i_top, prob.i_bottom, prob.x))
    known, load = np.asarray(prob.known)[sel], np.asarray(prob.load)[sel]
    groups, inverse = np.unique(np.asarray(prob.gidx)[sel][~known], return_inverse=True)
    gidx = np.full(len(x), -1)
    gidx[~known] = inverse
    best, arg = np.inf, (nominal, 0.0)
    scale_known = max(float(np.sum(load[known] ** 2)), 1e-300)
    no_k, everywhere = -np.ones(len(x), dtype=int), np.zeros(len(x), dtype=int)
    for g in gs:
        gt, gb = pole_gaps(g, xs[:, None], x[None, :], bearing.cos_alpha)
        ok = np.all(np.minimum(gt, gb) > 0.05 * g, axis=1)
        with np.errstate(divide="ignore", invalid="ignore"):
            unit = ideal_force(g, xs[:, None], 1.0, it, ib, x[None, :], bearing.cos_alpha)    # [origin, row]
            k = profile(unit, load, known, everywhere, 1, no_k, 0, 1.0)[0]           # [origin, 1]
            cost = np.sum(np.where(known, k * unit - load, 0.0) ** 2, axis=1) / scale_known
            if len(groups):
                mean = profile(unit, load, np.zeros(len(x), bool), everywhere, 1, gidx, len(groups), 1.0)[2]
                mean = mean[:, np.maximum(gidx, 0)]
                cost = cost + np.sum(np.where(known, 0.0, (unit - mean) ** 2 / mean**2), axis=1)
        cost = np.where(ok & np.isfinite(cost), cost, np.inf)
        j = int(np.argmin(cost))
        if cost[j] < best:
            best, arg = cost[j], (float(g), float(xs[j]))
    return arg


def columns(probs: Sequence[Problem], names: Sequence[str]) -> dict[str, np.ndarray]:
    """The named row fields (a problem's own or its readings') of many problems, one after another: read from
    each problem's leaves, whose order one problem's paths give."""
    if not probs:
        return {name: np.zeros(0) for name in names}
    paths = [jax.tree_util.keystr(path) for path, _ in jax.tree_util.tree_flatten_with_path(probs[0])[0]]
    where = {name: next(i for i, path in enumerate(paths) if path.endswith(f".{name}")) for name in names}
    leaves = [jax.tree_util.tree_leaves(p) for p in probs]
    return {name: np.concatenate([np.asarray(ls[i]) for ls in leaves]) for name, i in where.items()}


_PROFILE_FIELDS = ("axis", "i_top", "i_bottom", "x", "mask", "known", "load", "gidx")


def with_profile(gaps, origins, probs: Sequence[Problem], bearings: Sequence[Bearing], k_held=K_REFERENCE,
                 col: dict | None = None, n_loads: Sequence[int] | None = None) -> list[np.ndarray]:
    """Each data set's scaled start from its ``(v, w)`` gaps and origins [m] (arrays[n_sets, 2]): ``k`` from its known
    loads (``k_held``, float or array[n_sets, 2], on an axis without) and its nuisance loads profiled there, for all
    data sets in one pass.  ``col``: the problems' :func:`columns`, when already read; ``n_loads``: their numbers of
    nuisance loads, when known (each :class:`Meta`'s load groups)."""
    gaps, origins = np.asarray(gaps, dtype=float), np.asarray(origins, dtype=float)
    n = len(probs)
    lengths = np.array([len(p.mask) for p in probs])
    set_of_row = np.repeat(np.arange(n), lengths)

    col = columns(probs, _PROFILE_FIELDS) if col is None else col
    ax, it, ib, x = col["axis"].astype(int), col["i_top"], col["i_bottom"], col["x"]
    used, known, load = col["mask"] > 0, col["known"].astype(bool), col["load"]
    n_loads = np.array([p.n_loads for p in probs] if n_loads is None else n_loads, dtype=int)
    first_load = np.concatenate([[0], np.cumsum(n_loads)])
    gidx = col["gidx"].astype(int)
    load_seg = np.where(gidx >= 0, first_load[set_of_row] + gidx, -1)
    cos = np.array([b.cos_alpha for b in bearings])[set_of_row]
    with np.errstate(divide="ignore", invalid="ignore"):
        unit = ideal_force(gaps[set_of_row, ax], origins[set_of_row, ax], 1.0, it, ib, x, cos)
    k_free = np.array([np.asarray(p.k_free) for p in probs], dtype=bool).reshape(n, 2)
    held = np.broadcast_to(np.asarray(k_held, dtype=float), (n, 2)).reshape(-1)
    k, _, _ = profile(unit, load, known & used, set_of_row * 2 + ax, 2 * n, -np.ones_like(gidx), 0, held)
    k = k.reshape(n, 2)
    k_used = np.where(k_free, k, K_REFERENCE)
    with np.errstate(invalid="ignore", divide="ignore"):
        loads = (np.bincount(load_seg[load_seg >= 0], weights=(k_used[set_of_row, ax] * unit)[load_seg >= 0],
                             minlength=first_load[-1])
                 / np.bincount(load_seg[load_seg >= 0], minlength=first_load[-1]))
    head = np.concatenate([gaps, origins, k], axis=1) / SCALE_HEAD                   # to_theta of every data set
    loads = loads / SCALE_LOAD
    return [np.concatenate([head[s], loads[first_load[s]:first_load[s + 1]]]) for s in range(n)]


def starts(table: pd.DataFrame, probs: Sequence[Problem], metas: Sequence[Meta], offsets: Sequence[int],
           bearings: Sequence[Bearing]) -> tuple[list[np.ndarray], list[str]]:
    """Each data set's scaled start and how it was found.

    ``table`` holds the data sets' rows one after another (data set ``s`` at rows ``offsets[s]:offsets[s+1]``,
    no labels shared between data sets); an axis's gap and origin are the mean of its valid Eq. 7 pairs, or a
    :func:`grid_start` when it has none; then :func:`with_profile`.
    """
    n = len(probs)
    offsets = np.asarray(offsets)
    set_of_row = np.repeat(np.arange(n), np.diff(offsets))
    col = columns(probs, _PROFILE_FIELDS)
    it, ib, x, used = col["i_top"], col["i_bottom"], col["x"], col["mask"] > 0
    sums, counts = np.zeros((n, 2, 2)), np.zeros((n, 2))
    pairs = design_pairs(table)
    if pairs:
        axes = np.array([a for a, _ in pairs])
        rows = np.stack([r for _, r in pairs])
        sid = set_of_row[rows[:, 0, 0]]
        g0, x0, ok = pair_estimates(it, ib, x, rows, np.array([b.cos_alpha for b in bearings])[sid])
        ok &= np.all(used[rows.reshape(len(rows), 4)], axis=1)     # a pair with a held-out row is not used
        np.add.at(sums, (sid[ok], axes[ok], 0), g0[ok])
        np.add.at(sums, (sid[ok], axes[ok], 1), x0[ok])
        np.add.at(counts, (sid[ok], axes[ok]), 1)
    with np.errstate(invalid="ignore"):
        mean = sums / counts[:, :, None]
    present = np.array([m.axes_present for m in metas], dtype=bool).reshape(n, 2)
    closed = counts > 0
    gaps = np.where(closed, mean[:, :, 0], np.array([b.nominal_gap for b in bearings])[:, None])
    origins = np.where(closed, mean[:, :, 1], 0.0)
    words = {(pv, pw, cv, cw): ", ".join(f"{ax}: {'closed form' if c else 'grid'}"
                                         for ax, p, c in zip(AXES, (pv, pw), (cv, cw)) if p)
             for pv in (False, True) for pw in (False, True) for cv in (False, True) for cw in (False, True)}
    how = [words[tuple(present[s]) + tuple(closed[s])] for s in range(n)]
    for s, a in zip(*np.nonzero(present & ~closed)):       # an axis without a valid pair starts from a grid
        gaps[s, a], origins[s, a] = grid_start(probs[s], int(a), bearings[s])
    return with_profile(gaps, origins, probs, bearings, col=col, n_loads=[len(m.load_groups) for m in metas]), how


def seed_loads_and_k(theta, prob: Problem, bearing: Bearing = PAPER_BEARING) -> np.ndarray:
    """``theta`` with ``k`` (from the known loads; kept on an axis without) and the nuisance loads set to their best
    values at its gap and origin (:func:`with_profile` of one data set)."""
    theta = np.asarray(theta, dtype=float)
    si = theta[:6] * SCALE_HEAD
    head = with_profile(si[None, 0:2], si[None, 2:4], [prob], [bearing], k_held=si[None, 4:6])[0]
    return np.concatenate([head, theta[len(head):]])
