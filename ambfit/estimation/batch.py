"""Batch fits: many data sets in one call (Monte Carlo studies, fleets of bearings).

:func:`fit_batch`: data sets of one design (same rows in the same order: axes, biases,
set-points, load groups); only the measured values differ.  Each data set is
seeded by its own closed-form (Eq. 7) solution, computed for the whole batch at
once from the design's position/bias pairs, so a small fixed number of
Levenberg-Marquardt steps suffices.  ``method="vmap"`` runs one vectorised
solve, ``method="loop"`` a loop over the jitted single solve; which is faster
depends on the batch and is measured in ``benchmarks/ls_speed.py``.

:func:`fit_many`: data sets of *any* designs (lengths, axes, biases, iterations, load
groups, bearings).  They are padded to a few bucket lengths (padded rows weigh 0 and
point at no load; padded loads are referenced by no row) and solved a bucket at a time
by the same vmapped core solve, taking the steps :func:`ambfit.estimation.fit.fit` takes,
so each result is the single fit's.  To spread a study over processes or a cluster, map
chunks of data sets over :class:`ambfit.engine.Engine` and call :func:`fit_many` on each.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
import pandas as pd

from ambfit.data import Dataset, file_rows
from ambfit.estimation.closed_form import POSITION_TOLERANCE
from ambfit.estimation.core import (
    EDM_MAX,
    FIRST_STEPS,
    IDEAL,
    K_REFERENCE,
    FitError,
    Meta,
    Model,
    Problem,
    build_problem,
    free_mask,
    free_names,
    jacobian,
    param_scale,
    residuals,
    seed_loads_and_k,
    solve,
    solve_and_measure,
    to_theta,
)
from ambfit.physics.bearing import AXES, PAPER_BEARING, Bearing


@dataclasses.dataclass(frozen=True)
class BatchResult:
    """Estimates of every data set of a batch (SI units).

    ``values``, ``std``: array[n_sets, p]; ``converged``: array[n_sets] of bool
    (estimated distance to the minimum below ``ambfit.estimation.core.EDM_MAX``); ``num_steps``: array[n_sets].
    """

    names: list
    values: np.ndarray
    std: np.ndarray
    converged: np.ndarray
    num_steps: np.ndarray
    chi2: np.ndarray
    dof: int

    def column(self, name: str) -> np.ndarray:
        return self.values[:, self.names.index(name)]

    def error(self, name: str) -> np.ndarray:
        return self.std[:, self.names.index(name)]


def design_pairs(df: pd.DataFrame) -> list[tuple[int, np.ndarray]]:
    """Eq. 6-7 groups of a design: ``(axis, rows[2 positions, 2 biases])`` per iteration (row positions in ``df``).

    Only iterations (``experiment``, ``iteration``, axis) with exactly two positions and two biases, one row
    each, are used.  Positions are the own-axis set-points when the iteration has them, else the measured
    positions, clustered within ``POSITION_TOLERANCE``.  Vectorised over every iteration of the table (a joined
    table of thousands of data sets takes milliseconds).
    """
    n = len(df)
    if n == 0:
        return []
    exp = df["experiment"].astype(str) if "experiment" in df else pd.Series("", index=df.index)
    it = df["iteration"] if "iteration" in df else pd.Series(1, index=df.index)
    code = df.groupby([exp, it, df["axis"]], sort=False).ngroup().to_numpy()     # in order of first appearance
    ok_row = code >= 0
    n_groups = int(code.max(initial=-1)) + 1
    if n_groups == 0:
        return []
    code = np.where(ok_row, code, n_groups)           # rows of no group (a missing key) in a dummy group
    axis = df["axis"].to_numpy()
    is_w = axis == "w"

    def column(name):
        return df[name].to_numpy(float) if name in df else np.full(n, np.nan)

    own_set = np.where(is_w, column("w_set_um"), column("v_set_um"))
    own = np.where(is_w, column("w_um"), column("v_um"))
    set_complete = np.bincount(code, weights=np.isnan(own_set), minlength=n_groups + 1) == 0
    pos = np.where(set_complete[code], own_set, own) * 1e-6
    size = np.bincount(code, minlength=n_groups + 1)
    order = np.lexsort((pos, code))
    sc, sp = code[order], pos[order]
    new = np.zeros(n, dtype=int)
    new[1:] = (sc[1:] == sc[:-1]) & (sp[1:] - sp[:-1] > POSITION_TOLERANCE)    # a new cluster within the group
    csum = np.cumsum(new)
    start = np.zeros(n_groups + 1, dtype=int)
    start[sc[::-1]] = np.arange(n - 1, -1, -1)        # first sorted index of each group
    label = np.empty(n, dtype=int)
    label[order] = csum - csum[start[sc]]
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


def _eq7(it, ib, x, rows: np.ndarray, cos_alpha: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Eq. 7 for every position/bias pair at once: gap ``g`` [m], ``u = x0 cos(alpha)`` [m] and validity.

    ``it``, ``ib``, ``x``: arrays[..., rows]; ``rows``: array[pairs, 2 positions, 2 biases] of row indices.
    Returns arrays[..., pairs].
    """
    it, ib, x = (np.asarray(a, dtype=float) for a in (it, ib, x))
    rows = np.asarray(rows, dtype=int).reshape(-1, 2, 2)
    num = it[..., rows[:, :, 0]] ** 2 - it[..., rows[:, :, 1]] ** 2          # [..., pairs, 2 positions]
    den = ib[..., rows[:, :, 0]] ** 2 - ib[..., rows[:, :, 1]] ** 2
    with np.errstate(divide="ignore", invalid="ignore"):
        p = np.sqrt(num / den)
    pos = 0.5 * (x[..., rows[:, :, 0]] + x[..., rows[:, :, 1]])
    pa, pb, xa, xb = p[..., 0], p[..., 1], pos[..., 0], pos[..., 1]
    det = -(1 - pa) * (1 + pb) + (1 - pb) * (1 + pa)
    ca, cb = (1 + pa) * xa * cos_alpha, (1 + pb) * xb * cos_alpha
    with np.errstate(divide="ignore", invalid="ignore"):
        g = (-ca * (1 + pb) + cb * (1 + pa)) / det
        u = ((1 - pa) * cb - (1 - pb) * ca) / det
    return g, u, np.isfinite(g) & np.isfinite(u) & (g > 0)


def closed_form_batch(prob: Problem, pairs, model: Model = IDEAL) -> tuple[np.ndarray, np.ndarray]:
    """Mean Eq. 7 gap and origin per axis for a stacked batch of problems: arrays[n_sets, 2] [m].

    Iterations whose radicand is not positive or whose system is singular are
    skipped for that data set; an axis with no valid iteration gets the nominal
    gap and zero origin.
    """
    n = np.asarray(prob.i_top).shape[0]
    c = model.bearing.cos_alpha
    sums = np.zeros((n, 2, 2))
    counts = np.zeros((n, 2))
    if pairs:
        axes = np.array([ax for ax, _ in pairs])
        g, u, ok = _eq7(prob.i_top, prob.i_bottom, prob.x, np.stack([rows for _, rows in pairs]), c)
        for ax in range(2):
            sel = ok & (axes == ax)
            sums[:, ax, 0] = np.where(sel, g, 0.0).sum(axis=1)
            sums[:, ax, 1] = np.where(sel, u / c, 0.0).sum(axis=1)
            counts[:, ax] = sel.sum(axis=1)
    with np.errstate(invalid="ignore"):
        mean = sums / counts[:, :, None]
    g0 = np.where(counts > 0, mean[:, :, 0], model.bearing.nominal_gap)
    x0 = np.where(counts > 0, mean[:, :, 1], 0.0)
    return g0, x0


def stack(problems: Sequence[Problem]) -> Problem:
    """One :class:`Problem` whose arrays have a leading batch axis."""
    first = problems[0]
    for p in problems[1:]:
        if p.i_top.shape != first.i_top.shape or not np.array_equal(np.asarray(p.ax), np.asarray(first.ax)) \
                or not np.array_equal(np.asarray(p.gidx), np.asarray(first.gidx)):
            raise FitError("batch data sets must share one design (same rows, axes and load groups in the same order)")
    return jax.tree.map(lambda *xs: jnp.stack(xs), *problems)


@eqx.filter_jit
def _vmapped(theta0, probs, model, max_steps):
    return jax.vmap(lambda t, p: solve(t, p, model, max_steps=max_steps))(theta0, probs)


@eqx.filter_jit
def _vmapped_jac(theta, probs, model):
    return jax.vmap(lambda t, p: jacobian(t, p, model))(theta, probs)


def fit_batch(datasets: Sequence[pd.DataFrame], *, sigma_i: float | None = None, sigma_x: float | None = None,
              bearing: Bearing = PAPER_BEARING, max_steps: int = 4, method: str = "vmap") -> BatchResult:
    """Fit every data set of one design; see the module docstring.

    Parameters
    ----------
    datasets : sequence of DataFrame
        Contract tables sharing one design.
    max_steps : int
        Levenberg-Marquardt steps per reweighting round (closed-form seeds need few; a data set
        that has not converged after them is flagged, not refitted).
    method : {"vmap", "loop"}
    """
    if method not in ("vmap", "loop"):
        raise ValueError(f"method must be 'vmap' or 'loop', got {method!r}")
    model = Model.of((), bearing)
    built = [build_problem(d, sigma_i=sigma_i, sigma_x=sigma_x) for d in datasets]
    meta = built[0][1]
    probs = stack([b[0] for b in built])
    pairs = design_pairs(datasets[0].reset_index(drop=True))
    g0, x0 = closed_form_batch(probs, pairs, model)
    n_loads = built[0][0].n_loads
    theta0 = np.zeros((len(datasets), 6 + n_loads))
    for s, (prob, _) in enumerate(built):
        theta0[s] = seed_loads_and_k(to_theta(g0[s], x0[s], K_REFERENCE, np.zeros(n_loads)), prob, model)
    if method == "vmap":
        theta, _, steps, edm = _vmapped(jnp.asarray(theta0), probs, model, max_steps)
        jac = np.asarray(_vmapped_jac(theta, probs, model))
    else:
        out = [solve(jnp.asarray(theta0[s]), built[s][0], model, max_steps=max_steps) for s in range(len(built))]
        theta = jnp.stack([o[0] for o in out])
        steps, edm = np.array([int(o[2]) for o in out]), np.array([float(o[3]) for o in out])
        jac = np.stack([np.asarray(jacobian(theta[s], built[s][0], model)) for s in range(len(built))])
    ok = np.asarray(edm) < EDM_MAX
    free = free_mask(built[0][0], meta)
    names = free_names(meta, free)
    scale = param_scale(n_loads)[free]
    j = jac[:, :, free]
    cov = np.linalg.pinv(np.einsum("sni,snj->sij", j, j)) * np.outer(scale, scale)
    theta = np.asarray(theta)
    r = np.asarray(_vmapped_res(jnp.asarray(theta), probs, model))
    return BatchResult(names=names, values=theta[:, free] * scale, std=np.sqrt(np.abs(np.einsum("sii->si", cov))),
                       converged=ok, num_steps=np.asarray(steps), chi2=np.sum(r**2, axis=1),
                       dof=r.shape[1] - int(free.sum()))


@eqx.filter_jit
def _vmapped_res(theta, probs, model):
    return jax.vmap(lambda t, p: residuals(t, p, model))(theta, probs)


# --- mixed designs: data sets of any lengths, designs and load groups in one vmapped solve ---------------------

ROW_BUCKET_MIN = 16
"""Shortest padded length; longer data sets are padded to the next power of two (16, 32, 64, 128, ... rows).

Every bucket is a compilation (a few seconds per process) while the padded solve itself is cheap (a vmapped
batch of 64 data sets of 48 rows solves in about 4 ms), so few coarse buckets beat tight padding."""

BATCH = 64
"""Data sets per vmapped solve: a bucket's data sets are solved 64 at a time, the last batch padded with copies,
so chunks of any size reuse one compiled shape per bucket."""

BATCH_AGAIN = 8
"""Data sets per vmapped second solve (the few that the first solve's step budget left short of convergence)."""

_ROW_COLUMNS = ("axis", "bias_A", "i_top_A", "i_bottom_A", "v_um", "w_um", "load_N", "load_id", "experiment",
                "iteration", "time_s", "temperature_C", "i_top_std_A", "i_bottom_std_A", "v_std_um", "w_std_um",
                "v_set_um", "w_set_um")
_SEP = "\x1f"     # joins a data set's number to its labels in the joined table (a character no label contains)


def row_bucket(n: int) -> int:
    """The padded length of a data set of ``n`` rows (see ``ROW_BUCKET_MIN``)."""
    return max(ROW_BUCKET_MIN, 1 << (int(n) - 1).bit_length())


def load_bucket(m: int) -> int:
    """The padded number of nuisance loads: 0, 1, 2, 4, 8, ..."""
    return 0 if m <= 0 else 1 << (int(m) - 1).bit_length()


def _join_key(df: pd.DataFrame, sigma_i, sigma_x) -> tuple[bool, bool, bool, bool]:
    """What :func:`ambfit.estimation.problem.build_problem` decides for a whole table: whether the current and the
    position noise come from complete std columns (or a declared level), and which columns name the load groups.
    Data sets that agree are built as one joined table."""

    def complete(name):
        return name in df and not np.isnan(df[name].to_numpy(float)).any()

    cur = sigma_i is not None or (complete("i_top_std_A") and complete("i_bottom_std_A"))
    if sigma_x is not None:
        pos = True
    else:
        w = (df["axis"] == "w").to_numpy()
        nan = np.full(len(df), np.nan)
        v_s = df["v_std_um"].to_numpy(float) if "v_std_um" in df else nan
        w_s = df["w_std_um"].to_numpy(float) if "w_std_um" in df else nan
        pos = not np.isnan(np.where(w, w_s, v_s)).any()
    return cur, pos, "load_id" in df, "experiment" in df


def _numpy_problem(prob: Problem, lo: int, hi: int, k_free, gidx) -> Problem:
    """Rows ``lo:hi`` of a joined problem as a data set's own problem (numpy leaves)."""
    r = prob.readings
    readings = type(r)(**{f.name: np.asarray(getattr(r, f.name))[lo:hi] for f in dataclasses.fields(r)})
    return Problem(readings=readings, s_top=np.asarray(prob.s_top)[lo:hi], s_bottom=np.asarray(prob.s_bottom)[lo:hi],
                   s_x=np.asarray(prob.s_x)[lo:hi], load=np.asarray(prob.load)[lo:hi],
                   known=np.asarray(prob.known)[lo:hi], gidx=gidx, k_free=np.asarray(k_free),
                   mask=np.asarray(prob.mask)[lo:hi], s_held=np.asarray(prob.s_held)[lo:hi])


def _build_joined(frames: list[pd.DataFrame], sigma_i, sigma_x):
    """:func:`build_problem` once for many data sets of one :func:`_join_key`: their rows in one table, each data
    set's experiments and load groups prefixed with its number so that nothing is shared.  Returns the joined
    table, ``(Problem, Meta)`` per data set (numpy leaves) and the row offsets."""
    lengths = [len(f) for f in frames]
    joined = pd.concat([f[[c for c in _ROW_COLUMNS if c in f.columns]] for f in frames], ignore_index=True)
    prefix = pd.Series(np.repeat([f"{s}{_SEP}" for s in range(len(frames))], lengths), index=joined.index)
    joined["experiment"] = prefix + (joined["experiment"].astype(str) if "experiment" in joined else "")
    if "load_id" in joined:
        joined["load_id"] = prefix + joined["load_id"].astype(str)
    prob, meta = build_problem(joined, sigma_i=sigma_i, sigma_x=sigma_x)
    offsets = np.cumsum([0] + lengths)
    gidx_all, known, ax = np.asarray(prob.gidx), np.asarray(prob.known), np.asarray(prob.ax)
    out = []
    for s in range(len(frames)):
        lo, hi = offsets[s], offsets[s + 1]
        g = gidx_all[lo:hi]
        first = int(g[g >= 0].min()) if (g >= 0).any() else 0
        local = np.where(g >= 0, g - first, -1)
        m = int(local.max(initial=-1)) + 1
        a, kn = ax[lo:hi], known[lo:hi]
        k_free = tuple(bool(kn[a == i].any()) for i in range(2))
        present = tuple(bool((a == i).any()) for i in range(2))
        # the data set's own labels (ambfit.data.load_groups of it alone): the joined ones without the prefix
        names = [lab.replace(f"{s}{_SEP}", "", 1) for lab in meta.load_groups[first:first + m]]
        out.append((_numpy_problem(prob, lo, hi, k_free, local),
                    Meta(load_groups=names, k_free=k_free, axes_present=present, noise_source=meta.noise_source,
                         n_rows=int(hi - lo))))
    return joined, out, offsets


def _seeds(joined: pd.DataFrame, built, offsets, bearings) -> tuple[np.ndarray, list]:
    """Each data set's start (scaled theta, as :func:`ambfit.estimation.fit.start` and
    :func:`ambfit.estimation.core.seed_loads_and_k` make it) from the mean Eq. 7 solution of its position/bias
    pairs, computed for all data sets at once.  Returns the starts (a list of arrays) and the sets (and axes)
    without a valid pair, which get :func:`ambfit.estimation.fit.start` instead."""
    n = len(built)
    set_of_row = np.repeat(np.arange(n), np.diff(offsets))
    prob0 = [b[0] for b in built]
    it = np.concatenate([np.asarray(p.i_top) for p in prob0])
    ib = np.concatenate([np.asarray(p.i_bottom) for p in prob0])
    x = np.concatenate([np.asarray(p.x) for p in prob0])
    ax = np.concatenate([np.asarray(p.ax) for p in prob0])
    cos_set = np.array([b.cos_alpha for b in bearings])
    sums, counts = np.zeros((n, 2, 2)), np.zeros((n, 2))
    pairs = design_pairs(joined)
    if pairs:
        axes = np.array([a for a, _ in pairs])
        rows = np.stack([r for _, r in pairs])
        sid = set_of_row[rows[:, 0, 0]]
        c = cos_set[sid]                               # each pair's bearing's cos(alpha)
        g, u, ok = _eq7(it, ib, x, rows, c)
        # as closed_form.solve: no pole gap closed at either position (|(x0 + x) cos(alpha)| < g0)
        for q in range(2):
            xq = 0.5 * (x[rows[:, q, 0]] + x[rows[:, q, 1]])
            ok &= np.abs(u + xq * c) < g
        np.add.at(sums, (sid[ok], axes[ok], 0), g[ok])
        np.add.at(sums, (sid[ok], axes[ok], 1), u[ok] / c[ok])
        np.add.at(counts, (sid[ok], axes[ok]), 1)
    with np.errstate(invalid="ignore"):
        mean = sums / counts[:, :, None]
    present = np.array([b[1].axes_present for b in built])
    lacking = [s for s in range(n) if np.any(present[s] & (counts[s] == 0))]
    nominal = np.array([b.nominal_gap for b in bearings])
    g0 = np.where(counts > 0, mean[:, :, 0], nominal[:, None])
    x0 = np.where(counts > 0, mean[:, :, 1], 0.0)
    # k from the known loads and the nuisance loads at that gap and origin (core.seed_loads_and_k, all sets at once)
    from ambfit.physics.model import ideal_force

    srow = set_of_row
    unit = np.asarray(ideal_force(g0[srow, ax], x0[srow, ax], 1.0, it, ib, x, cos_set[srow]))
    known = np.concatenate([np.asarray(p.known) for p in prob0])
    load = np.concatenate([np.asarray(p.load) for p in prob0])
    used = np.concatenate([np.asarray(p.mask) for p in prob0]) > 0
    k_seed = np.full((n, 2), K_REFERENCE)
    for a in range(2):
        sel = known & (ax == a) & used
        num = np.bincount(srow[sel], weights=load[sel] * unit[sel], minlength=n)
        den = np.bincount(srow[sel], weights=unit[sel] ** 2, minlength=n)
        has = np.bincount(srow[sel], minlength=n) > 0
        k_seed[:, a] = np.where(has & (den > 0), num / np.where(den > 0, den, 1.0), K_REFERENCE)
    k_free = np.array([b[0].k_free for b in built], dtype=bool)
    k_used = np.where(k_free, k_seed, K_REFERENCE)
    thetas = []
    for s, (p, meta) in enumerate(built):
        lo, hi = offsets[s], offsets[s + 1]
        g = np.asarray(p.gidx)
        m = len(meta.load_groups)
        contrib = k_used[s, ax[lo:hi]] * unit[lo:hi]
        loads = np.array([np.mean(contrib[g == j]) for j in range(m)]) if m else np.zeros(0)
        thetas.append(to_theta(g0[s], x0[s], k_seed[s], loads))
    return thetas, lacking


def _pad(probs: list[Problem], rows: int) -> Problem:
    """Problems stacked into one batch of ``rows`` rows each: padded rows repeat a data set's first row with weight 0
    and point at no load (zero residual, zero Jacobian row), so they cannot move an estimate."""
    first = probs[0]

    def stack(get, fill=None):
        out = []
        for p in probs:
            a = np.asarray(get(p))
            pad = np.repeat(a[:1], rows - len(a), axis=0) if fill is None else np.full(rows - len(a), fill, a.dtype)
            out.append(np.concatenate([a, pad]))
        return jnp.asarray(np.stack(out))

    r = first.readings
    readings = type(r)(**{f.name: stack(lambda p, f=f: getattr(p.readings, f.name)) for f in dataclasses.fields(r)})
    return Problem(readings=readings, s_top=stack(lambda p: p.s_top), s_bottom=stack(lambda p: p.s_bottom),
                   s_x=stack(lambda p: p.s_x), load=stack(lambda p: p.load, 0.0), known=stack(lambda p: p.known, True),
                   gidx=stack(lambda p: p.gidx, -1), k_free=jnp.asarray(np.stack([np.asarray(p.k_free) for p in probs])),
                   mask=stack(lambda p: p.mask, 0.0), s_held=stack(lambda p: p.s_held, 0.0))


@eqx.filter_jit
def _vmapped_measure(theta0, probs, model, max_steps):
    return jax.vmap(lambda t, p: solve_and_measure(t, p, model, max_steps=max_steps))(theta0, probs)


def _solve_padded(thetas: list[np.ndarray], probs: list[Problem], rows: int, loads: int, model: Model,
                  max_steps: int, size: int) -> list[tuple]:
    """:func:`ambfit.estimation.core.solve_and_measure` of every problem, ``size`` at a time (the last batch padded
    with copies of its first problem).  Returns ``(theta, lm, steps, edm, jac, z)`` per problem."""
    out = []
    for lo in range(0, len(probs), size):
        part = list(range(lo, min(lo + size, len(probs))))
        idx = part + [part[0]] * (size - len(part))
        theta0 = np.zeros((size, 6 + loads))
        for b, s in enumerate(idx):
            theta0[b, :len(thetas[s])] = thetas[s]
        theta, result, steps, edm, jac, z = _vmapped_measure(jnp.asarray(theta0), _pad([probs[s] for s in idx], rows),
                                                             model, max_steps)
        ok = np.asarray(result == optx.RESULTS.successful)
        theta, steps, edm, jac, z = (np.asarray(a) for a in (theta, steps, edm, jac, z))
        for b in range(len(part)):
            lm = "successful" if ok[b] else str(jax.tree.map(lambda a, b=b: a[b], result))
            out.append((theta[b], lm, int(steps[b]), float(edm[b]), jac[b], z[b]))
    return out


def _solve_all(thetas, probs, bearings, max_steps: int) -> list[tuple]:
    """The ideal law's least squares of every problem, bucketed by bearing, padded length and number of loads; the
    steps of :func:`ambfit.estimation.fit.fit`: ``FIRST_STEPS`` per round from the seed, then, for the problems
    not converged, ``max_steps`` more."""
    n = len(probs)
    key = [(bearings[s], row_bucket(len(probs[s].mask)), load_bucket(len(thetas[s]) - 6)) for s in range(n)]
    out = [None] * n
    first = min(FIRST_STEPS, max_steps)
    for k in dict.fromkeys(key):
        members = [s for s in range(n) if key[s] == k]
        bearing, rows, loads = k
        model = Model.of((), bearing)       # (one per bucket: the bearing is a static part of the compiled solve)
        solved = _solve_padded([thetas[s] for s in members], [probs[s] for s in members], rows, loads, model, first,
                               BATCH)
        again = [j for j, r in enumerate(solved) if not r[3] < EDM_MAX]
        if again and max_steps > first:
            more = _solve_padded([solved[j][0] for j in again], [probs[members[j]] for j in again], rows, loads,
                                 model, max_steps, BATCH_AGAIN)
            for j, r in zip(again, more):
                solved[j] = r[:2] + (solved[j][2] + r[2],) + r[3:]
        for s, r in zip(members, solved):
            m = len(thetas[s])
            nr = len(probs[s].mask)
            out[s] = (r[0][:m], r[1], r[2], r[3], r[4][:nr, :m], r[5][:nr])
    return out


def fit_many(datasets: Sequence[Dataset | pd.DataFrame], *, bearing: Bearing | Sequence[Bearing] = PAPER_BEARING,
             sigma_i: float | None = None, sigma_x: float | None = None, require_k: bool = False,
             max_condition: float = 1e8, max_relative_gap_std: float = 0.1, p_min: float = 1e-3,
             max_steps: int = 200, loss: str = "auto", alpha: float | None = None, debias: int = 0,
             name_outliers: bool = True) -> list:
    """Least squares of the ideal law for data sets of *any* designs, vmapped: ``fit(d, throw=False)`` for each.

    The data sets may differ in length, axes, biases, set-points, iterations, load groups and bearing.  They
    are bucketed by bearing, padded length (:func:`row_bucket`) and number of nuisance loads
    (:func:`load_bucket`) and solved a bucket at a time by one compiled, vmapped solve; padded rows have weight 0
    and point at no load, padded loads are referenced by no row (zero Jacobian columns, held at their start).
    Seeds are the mean Eq. 7 solution of each data set's position/bias pairs (:func:`ambfit.estimation.fit.start`
    for a data set without such pairs on an axis), and the solve takes the steps :func:`ambfit.estimation.fit.fit`
    takes, so each result equals the single fit's (to its convergence: the largest differences seen are 4e-9
    relative, far below a standard error).  Data sets in which the outlier test finds a reading beyond its bound
    (``loss="auto"`` or ``"linear"``) are refitted by :func:`fit` itself (the test then needs several refits of that
    data set alone, and a compilation for its shape); ``name_outliers=False`` skips the test (a Monte Carlo study's
    plain least-squares estimates: what ``loss="linear"`` gives, without naming the readings beyond the bound).

    Parameters
    ----------
    datasets : sequence of Dataset or DataFrame
        Contract tables.
    bearing : Bearing or sequence of Bearing
        One bearing for all, or one per data set.
    sigma_i, sigma_x, require_k, max_condition, max_relative_gap_std, p_min, max_steps, loss, alpha
        As in :func:`ambfit.estimation.fit.fit` (``loss`` "auto" or "linear"; robust losses, effects and the bias
        correction need :func:`ambfit.estimation.fit.fit` per data set).
    name_outliers : bool
        Run the outlier test (default); False: plain least squares for every data set, no refits.

    Returns
    -------
    list of FitResult or Exception
        One entry per data set, in order: its :class:`~ambfit.estimation.results.FitResult` (health as data, as
        with ``throw=False``), or the :class:`FitError` / :class:`ambfit.data.DataError` that :func:`fit` raises
        for it.
    """
    from ambfit.data import DataError
    from ambfit.estimation import fit as single
    from ambfit.estimation import plausibility, robust
    from ambfit.estimation.results import Thresholds

    if loss not in ("auto", "linear"):
        raise ValueError(f"fit_many fits the plain least squares (loss 'auto' or 'linear'), got {loss!r}; robust "
                         "losses reweight each data set in rounds of their own: use ambfit.fit per data set")
    if debias:
        raise ValueError("fit_many does not apply the bootstrap bias correction (debias); use ambfit.fit per data set")
    alpha = robust.ALPHA if alpha is None else alpha
    frames = [d.frame if isinstance(d, Dataset) else d for d in datasets]
    n = len(frames)
    bearings = list(bearing) if isinstance(bearing, (list, tuple)) else [bearing] * n
    if len(bearings) != n:
        raise ValueError(f"bearing: one for all data sets or one per data set ({n}), got {len(bearings)}")
    kw = dict(sigma_i=sigma_i, sigma_x=sigma_x, require_k=require_k, max_condition=max_condition,
              max_relative_gap_std=max_relative_gap_std, p_min=p_min, max_steps=max_steps, loss=loss, alpha=alpha)
    thresholds = Thresholds(max_condition=max_condition, max_relative_gap_std=max_relative_gap_std, p_min=p_min,
                            max_steps=max_steps)
    out: list = [None] * n

    def alone(s):
        """The single fit (the reference path) for data set ``s``; its exception as the result when it raises."""
        try:
            return single.fit(frames[s], bearing=bearings[s], throw=False, **kw)
        except (FitError, DataError, ValueError) as exc:
            return exc

    rows = [file_rows(df) for df in frames]
    dfs = [df.reset_index(drop=True) for df in frames]
    keys = [_join_key(df, sigma_i, sigma_x) for df in dfs]
    todo = []                                   # (set, problem, meta, start, how)
    for key in dict.fromkeys(keys):
        members = [s for s in range(n) if keys[s] == key]
        try:
            joined, built, offsets = _build_joined([dfs[s] for s in members], sigma_i, sigma_x)
        except (DataError, ValueError, KeyError):
            for s in members:                   # the single fit names the data set and the problem
                out[s] = alone(s)
            continue
        starts, lacking = _seeds(joined, built, offsets, [bearings[s] for s in members])
        for j, s in enumerate(members):
            prob, meta = built[j]
            if require_k and any(meta.axes_present[a] and not meta.k_free[a] for a in range(2)):
                out[s] = alone(s)               # raises its FitError ("k is not identifiable ...")
                continue
            how = ", ".join(f"{ax}: closed form" for a, ax in enumerate(AXES) if meta.axes_present[a])
            theta = starts[j]
            if j in lacking:
                theta, how = single.start(prob, meta, dfs[s], bearings[s])
            todo.append((s, prob, meta, np.asarray(theta, dtype=float), how))
    solved = _solve_all([t[3] for t in todo], [t[1] for t in todo], [bearings[t[0]] for t in todo], max_steps)
    models = {b: Model.of((), b) for b in dict.fromkeys(bearings)}
    for (s, prob, meta, _, how), (theta, lm, steps, edm, jac, z) in zip(todo, solved):
        model = models[bearings[s]]
        try:
            res = single._finish(theta, jac, z, edm, lm, steps, prob, meta, model, how, thresholds)
        except FitError as exc:
            out[s] = exc
            continue
        base = np.asarray(prob.mask, dtype=float)
        fitted = base > 0
        if not name_outliers:
            res = dataclasses.replace(res, loss="linear", rows=rows[s], weights=base)
        elif np.all(np.isfinite(res.residuals[fitted])):
            # the outlier test of fit (its Jacobian rows are the solve's: every row has weight 1 here)
            free = free_mask(prob, meta, model)
            t = robust.studentized(jac[:, free], res.residuals, fitted, base ** 2,
                                   known_noise=not meta.noise_estimated)
            if np.any(np.abs(t[fitted]) > robust.threshold(int(fitted.sum()), alpha)):
                out[s] = alone(s)               # outliers: named (and left out) by fit's rounds
                continue
            res = dataclasses.replace(res, loss=loss, rows=rows[s], weights=base)
        out[s] = dataclasses.replace(res, implausible=tuple(plausibility.check_result(
            dict(zip(res.names, res.values)), bearings[s])))
    return out


def precompile(rows: Sequence[int], loads: Sequence[int] = (0,), *, bearing: Bearing = PAPER_BEARING,
               max_steps: int = 200) -> int:
    """Compile :func:`fit_many`'s solves for data sets of these row counts and numbers of nuisance loads (both steps'
    shapes of every bucket they fall in), so that a worker or a timed run does not pay it on its first batch.

    Compilation depends only on the shapes, so a synthetic table stands in for the data.  Returns the number of
    buckets compiled.
    """
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
            _, built, _ = _build_joined([frame], None, None)
            prob, meta = built[0]
            theta = to_theta(bearing.nominal_gap, 0.0, K_REFERENCE, np.zeros(len(meta.load_groups)))
            for steps, size in ((min(FIRST_STEPS, max_steps), BATCH), (max_steps, BATCH_AGAIN)):
                _solve_padded([theta], [prob], key[0], key[1], model, steps, size)
    return len(done)
