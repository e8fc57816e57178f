"""Batch fits: many data sets of one design in one call (Monte Carlo studies, fleets of bearings).

All data sets must share the design (same rows in the same order: axes, biases,
set-points, load groups); only the measured values differ.  Each data set is
seeded by its own closed-form (Eq. 7) solution, computed for the whole batch at
once from the design's position/bias pairs, so a small fixed number of
Levenberg-Marquardt steps suffices.  ``method="vmap"`` runs one vectorised
solve, ``method="loop"`` a loop over the jitted single solve; which is faster
depends on the batch and is measured in ``benchmarks/ls_speed.py``.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pandas as pd

from ambfit.estimation.closed_form import POSITION_TOLERANCE, _cluster_positions
from ambfit.estimation.core import (
    EDM_MAX,
    IDEAL,
    K_REFERENCE,
    FitError,
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


def design_pairs(df: pd.DataFrame) -> list[tuple[int, np.ndarray, np.ndarray]]:
    """Eq. 6-7 groups of a design: ``(axis, rows[2 positions, 2 biases], positions_key)`` per iteration.

    Only iterations with exactly two positions and two biases, one row each, are used.
    """
    exp = df["experiment"].astype(str) if "experiment" in df else pd.Series("", index=df.index)
    it = df["iteration"] if "iteration" in df else pd.Series(1, index=df.index)
    out = []
    for (_, _, ax), grp in df.groupby([exp, it, df["axis"]], sort=False):
        set_col = f"{ax}_set_um"
        pos = grp[set_col] if set_col in grp and grp[set_col].notna().all() else grp[f"{ax}_um"]
        labels = _cluster_positions(pos.to_numpy(float) * 1e-6, POSITION_TOLERANCE)
        biases = np.unique(grp["bias_A"].to_numpy(float))
        if len(np.unique(labels)) != 2 or len(biases) != 2 or len(grp) != 4:
            continue
        rows = np.empty((2, 2), dtype=int)
        ok = True
        for p in range(2):
            for b in range(2):
                m = np.nonzero((labels == p) & (grp["bias_A"].to_numpy(float) == biases[b]))[0]
                if len(m) != 1:
                    ok = False
                    break
                rows[p, b] = df.index.get_loc(grp.index[m[0]])
        if ok:
            out.append((AXES.index(ax), rows))
    return out


def closed_form_batch(prob: Problem, pairs, model: Model = IDEAL) -> tuple[np.ndarray, np.ndarray]:
    """Mean Eq. 7 gap and origin per axis for a stacked batch of problems: arrays[n_sets, 2] [m].

    Iterations whose radicand is not positive or whose system is singular are
    skipped for that data set; an axis with no valid iteration gets the nominal
    gap and zero origin.
    """
    it, ib, x = (np.asarray(a) for a in (prob.i_top, prob.i_bottom, prob.x))
    n = it.shape[0]
    c = model.bearing.cos_alpha
    sums = np.zeros((n, 2, 2))
    counts = np.zeros((n, 2))
    for ax, rows in pairs:
        p = []
        for q in range(2):
            num = it[:, rows[q, 0]] ** 2 - it[:, rows[q, 1]] ** 2
            den = ib[:, rows[q, 0]] ** 2 - ib[:, rows[q, 1]] ** 2
            with np.errstate(divide="ignore", invalid="ignore"):
                p.append(np.sqrt(num / den))
        xa = 0.5 * (x[:, rows[0, 0]] + x[:, rows[0, 1]])
        xb = 0.5 * (x[:, rows[1, 0]] + x[:, rows[1, 1]])
        pa, pb = p
        det = -(1 - pa) * (1 + pb) + (1 - pb) * (1 + pa)
        ca, cb = (1 + pa) * xa * c, (1 + pb) * xb * c
        with np.errstate(divide="ignore", invalid="ignore"):
            g = (-ca * (1 + pb) + cb * (1 + pa)) / det
            u = ((1 - pa) * cb - (1 - pb) * ca) / det
        ok = np.isfinite(g) & np.isfinite(u) & (g > 0)
        sums[ok, ax, 0] += g[ok]
        sums[ok, ax, 1] += u[ok] / c
        counts[ok, ax] += 1
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
